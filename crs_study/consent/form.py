"""Consent forms: versioned Markdown documents, read and checked (no register, no dataset).

A form has a ``# Title`` line, exactly one ``Version: X`` line and ``- [ ]`` consent
statements. Reading one is all a protocol needs to check its ``study.consent_form_version``
(:mod:`crs_study.protocol.feasibility`), and all the register records of the form a
participant consented on (its version and sha256).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

from crs_study._files import sha256_bytes
from crs_study.errors import ConsentError

#: the version is the first word on its line ("Version: 1.0 (2026-11-22)"), never the next line's
_VERSION_RE = re.compile(r"^Version:[ \t]*(\S*)", re.MULTILINE)


@dataclass(frozen=True)
class ConsentForm:
    """A versioned consent form: Markdown with a title and a ``Version:`` line."""

    path: Path
    title: str
    version: str
    sha256: str


def read_form(path: str | Path) -> ConsentForm:
    """Read and check a consent form; malformed forms are one-line :class:`ConsentError` s."""
    path = Path(path)
    try:
        data = path.read_bytes()
        text = data.decode("utf-8")
    except FileNotFoundError:
        raise ConsentError(f"{path}: no such consent form") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConsentError(f"{path}: cannot read the consent form: {exc}") from None
    titles = [line[2:].strip() for line in text.splitlines() if line.startswith("# ")]
    if not titles:
        raise ConsentError(f"{path}: not a consent form: expected a '# Title' line")
    versions = _VERSION_RE.findall(text)
    if len(versions) != 1:
        raise ConsentError(
            f"{path}: expected exactly one 'Version: X' line, found {len(versions)}"
        )
    if not versions[0]:
        raise ConsentError(f"{path}: the 'Version:' line gives no version; expected e.g. "
                           "'Version: 1.0'")
    if "- [ ]" not in text:
        raise ConsentError(f"{path}: not a consent form: expected '- [ ]' consent statements")
    return ConsentForm(path, titles[0], versions[0], sha256_bytes(data))
