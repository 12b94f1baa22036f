"""crs-study: experiment framework for the continuity reinforcement skeleton haptic display.

The public surface is small on purpose; stages of the pipeline live in their own modules:
``layout`` (device geometry), ``targets``, ``render``, ``display`` (what the skin meets),
``quality``, ``device`` (LSC-24 I/O and the simulator), ``protocol``, ``plan``, ``runner``,
``dataset`` (with ``bids``, its paths, and ``session_metadata``, the session sidecar),
``analysis`` and ``consent``; ``paths`` finds the shipped protocols, plans and consent forms.
"""

from importlib.metadata import PackageNotFoundError, version

from crs_study.errors import CrsStudyError

try:
    __version__ = version("crs-study")
except PackageNotFoundError:  # running from a source tree that was never installed
    __version__ = "0.0.0+unknown"

__all__ = ["CrsStudyError", "__version__"]
