"""A package's names loaded from their modules on first use (module ``__getattr__``, PEP 562).

A package whose public names live in heavy modules (the analysis and its charts, power with
its fits) exports them through :func:`lazy_exports`, so that importing one light module of
it, or the package itself, does not import them all.
"""

from __future__ import annotations

from collections.abc import Callable
from importlib import import_module


def lazy_exports(package: str, exports: dict[str, str], namespace: dict
                 ) -> tuple[Callable[[str], object], Callable[[], list[str]]]:
    """``(__getattr__, __dir__)`` for ``package``: each name of ``exports`` (name -> the
    module that owns it) is imported on first use and kept in ``namespace`` (the package's
    globals) from then on; any other name is an ``AttributeError``."""

    def __getattr__(name: str) -> object:
        if name not in exports:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(import_module(exports[name]), name)
        namespace[name] = value
        return value

    def __dir__() -> list[str]:
        return sorted(set(namespace) | set(exports))

    return __getattr__, __dir__
