"""Strict reading of TOML configuration: unknown keys and wrong types are one-line errors.

Shared by device files, protocols and analysis plans. Messages name the file, the key path and
the value received, e.g. ``crs2d.toml: geometry.pitch_mm: expected a number > 0, got -3``.
"""

from __future__ import annotations

import tomllib
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from crs_study.errors import ConfigError


def read_toml(path: str | Path, error: type[ConfigError] = ConfigError) -> dict[str, Any]:
    """Parse a TOML file; a missing file or a syntax error raises ``error`` in one line."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise error(f"{path}: no such file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise error(f"{path}: cannot read: {exc}") from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise error(f"{path}: not valid TOML: {exc}") from None


class Section:
    """A view of one TOML table that checks each key as it is taken and rejects leftovers.

    ``source`` names the file and ``path`` the table's dotted key path (empty for the root), so
    messages read ``protocol.toml: stimulus.speed_mm_s: expected ...``. Call :meth:`done` after
    taking every known key: any key left is reported with the list of valid ones.
    """

    def __init__(
        self, data: Any, source: str | Path, path: str = "",
        error: type[ConfigError] = ConfigError,
    ) -> None:
        self.source = str(source)
        self.path = path
        self.error = error
        if not isinstance(data, Mapping):
            raise error(f"{self.where}: expected a table, got {data!r}")
        self.data = dict(data)
        self._taken: set[str] = set()

    @property
    def where(self) -> str:
        return f"{self.source}: {self.path}" if self.path else self.source

    def key_path(self, key: str) -> str:
        return f"{self.path}.{key}" if self.path else key

    def fail(self, key: str, message: str) -> ConfigError:
        """An error naming this section's ``key`` (to be raised by the caller)."""
        return self.error(f"{self.source}: {self.key_path(key)}: {message}")

    def has(self, key: str) -> bool:
        return key in self.data

    def raw(self, key: str, default: Any = ...) -> Any:
        self._taken.add(key)
        if key in self.data:
            return self.data[key]
        if default is ...:
            raise self.error(f"{self.where}: missing required key {key!r}")
        return default

    def number(
        self,
        key: str,
        default: Any = ...,
        *,
        minimum: float | None = None,
        maximum: float | None = None,
        exclusive_minimum: bool = False,
    ) -> float:
        value = self.raw(key, default)
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise self.fail(key, f"expected a number, got {value!r}")
        value = float(value)
        if value != value or value in (float("inf"), float("-inf")):
            raise self.fail(key, f"expected a finite number, got {value!r}")
        if minimum is not None:
            if exclusive_minimum and value <= minimum:
                raise self.fail(key, f"expected a number > {minimum:g}, got {value!r}")
            if not exclusive_minimum and value < minimum:
                raise self.fail(key, f"expected a number >= {minimum:g}, got {value!r}")
        if maximum is not None and value > maximum:
            raise self.fail(key, f"expected a number <= {maximum:g}, got {value!r}")
        return value

    def integer(
        self, key: str, default: Any = ..., *, minimum: int | None = None,
        maximum: int | None = None,
    ) -> int:
        value = self.raw(key, default)
        if isinstance(value, bool) or not isinstance(value, int):
            raise self.fail(key, f"expected a whole number, got {value!r}")
        if minimum is not None and value < minimum:
            raise self.fail(key, f"expected a whole number >= {minimum}, got {value!r}")
        if maximum is not None and value > maximum:
            raise self.fail(key, f"expected a whole number <= {maximum}, got {value!r}")
        return value

    def string(self, key: str, default: Any = ..., *, choices: Iterable[str] | None = None) -> str:
        value = self.raw(key, default)
        if not isinstance(value, str):
            raise self.fail(key, f"expected a string, got {value!r}")
        if choices is not None:
            options = list(choices)
            if value not in options:
                raise self.fail(key, f"expected one of {options}, got {value!r}")
        return value

    def boolean(self, key: str, default: Any = ...) -> bool:
        value = self.raw(key, default)
        if not isinstance(value, bool):
            raise self.fail(key, f"expected true or false, got {value!r}")
        return value

    def array(self, key: str, default: Any = ...) -> list[Any]:
        value = self.raw(key, default)
        if not isinstance(value, list):
            raise self.fail(key, f"expected an array, got {value!r}")
        return value

    def table(self, key: str, default: Any = ...) -> Section:
        value = self.raw(key, default)
        return Section(value, self.source, self.key_path(key), self.error)

    def done(self) -> None:
        """Raise if the table holds keys nobody took (a typo must never pass silently)."""
        extra = sorted(set(self.data) - self._taken)
        if extra:
            valid = ", ".join(sorted(self._taken))
            raise self.error(
                f"{self.where}: unknown key {extra[0]!r} (valid keys: {valid})"
            )
