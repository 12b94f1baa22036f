"""Where the repository's shipped files (protocols/, analysis/, consent/) are found.

They live at the top of the repository, beside the package, so a researcher edits them in
place. A relative name is looked up in the current directory first, then beside the installed
package (the checkout, for the README's editable install).
"""

from __future__ import annotations

from pathlib import Path

import crs_study
from crs_study.errors import ConfigError

REPO_ROOT = Path(crs_study.__file__).resolve().parents[1]
#: The paper's experiment (``crs-study demo`` and ``device check`` use it when given none).
DEFAULT_PROTOCOL = "protocols/digit_identification.toml"


def shipped_file(relative: str | Path) -> Path:
    """Resolve ``relative`` (e.g. ``protocols/pilot.toml``): as given, else in the checkout."""
    path = Path(relative)
    if path.is_absolute() or path.exists():
        return path
    candidate = REPO_ROOT / path
    if candidate.exists():
        return candidate
    raise ConfigError(f"{relative}: no such file (looked in {Path.cwd()} and {REPO_ROOT})")
