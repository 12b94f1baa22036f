"""The subcommands of ``crs-study``, one module each (see :mod:`crs_study.cli`)."""

import argparse

from crs_study.errors import DeviceError


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


def add_device_options(parser: argparse.ArgumentParser, battery_limits: bool = False) -> None:
    """The device options of a command that opens a device: the write policy's (both devices
    model it) and the serial boards' battery check (``battery_limits``: its thresholds too).
    :func:`device_options` reads them back."""
    group = parser.add_argument_group("device options")
    group.add_argument("--deadband-us", type=int, default=None,
                       help="resend a channel when it moved more than this (us; default 1)")
    group.add_argument("--refresh-s", type=float, default=None,
                       help="the first frame this long after the last full one carries every "
                            "channel (s; 0: never; default 1)")
    if battery_limits:
        group.add_argument("--min-battery-mv", type=int, default=None,
                           help="serial:// only: refuse a board reporting less (mV; 0: no "
                                "check)")
        group.add_argument("--battery-timeout-s", type=float, default=None,
                           help="serial:// only: wait this long for each board's battery "
                                "reply")
    group.add_argument("--no-battery-check", action="store_true",
                       help="serial:// only: do not ask the boards for their battery voltage")


def device_options(args: argparse.Namespace, url: str) -> dict[str, object]:
    """The options :func:`add_device_options` added that were given, as ``open_device``
    takes them; an option the device cannot honour is refused, never ignored (the battery
    options on ``sim://``). An unknown scheme gets none: ``open_device`` names it."""
    flags = {"deadband_us": ("--deadband-us", args.deadband_us),
             "refresh_s": ("--refresh-s", args.refresh_s),
             "min_battery_mv": ("--min-battery-mv", getattr(args, "min_battery_mv", None)),
             "battery_timeout_s": ("--battery-timeout-s",
                                   getattr(args, "battery_timeout_s", None)),
             "check_battery": ("--no-battery-check", False if args.no_battery_check else None)}
    options = {key: value for key, (_, value) in flags.items() if value is not None}
    if url.startswith("sim://"):
        serial_only = [flags[k][0] for k in options if k not in ("deadband_us", "refresh_s")]
        if serial_only:
            raise DeviceError(f"{', '.join(serial_only)}: for serial:// devices only, got "
                              f"--device {url!r}")
        return options
    return options if url.startswith("serial://") else {}
