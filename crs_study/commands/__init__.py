"""The subcommands of ``crs-study``, one module each (see :mod:`crs_study.cli`)."""

import argparse


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Shows an option's default where it tells the reader something.

    Not for options without one (``None``, an empty list, an unset flag), nor where the help
    text already says what the default is.
    """

    def _get_help_string(self, action: argparse.Action) -> str | None:
        text = action.help or ""
        if "default" in text or action.default in (None, False, [], argparse.SUPPRESS):
            return text
        return super()._get_help_string(action)
