"""Which board is behind which port: what the hardware says of a port, and the identities an
experimenter confirmed (``crs-study device identify``), remembered between sessions.

Two LSC-24 boards on two USB serial adapters look alike to software; plugged the other way
round, every channel of A would drive B's servos. A person tells them apart once (a servo of
one board wiggles; the experimenter says which board moved), and the adapters' identity is
remembered where the hardware has one, so later checks need nobody to watch:

* a **USB serial number** (``serial.tools.list_ports``: the adapter's iSerial, e.g. an FTDI
  chip's ``A50285BI``), the best: it follows the adapter to any socket;
* a **by-id path** (``/dev/serial/by-id/usb-FTDI_..._A50285BI-if00-port0``, udev's link,
  which names the adapter's vendor, model and serial), when the serial number is not
  reported otherwise;
* a **USB location** (bus and port path, ``1-1.2``): the socket, not the adapter;
* nothing: a pseudo-terminal (``/dev/pts/N``, as ``crs-study device boards`` makes) or a
  pyserial URL has no hardware identity, only its path.

The register is a JSON file (default ``~/.crs-study/boards.json``, or
``$CRS_STUDY_BOARDS``): per device file name, per controller, the identity confirmed and when.
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass
from datetime import UTC, datetime
from pathlib import Path

from serial.tools import list_ports  # pyserial's own port lister

from crs_study.errors import DeviceError

BOARDS_ENV = "CRS_STUDY_BOARDS"
BY_ID_DIR = Path("/dev/serial/by-id")


def default_register() -> Path:
    """``$CRS_STUDY_BOARDS``, else ``~/.crs-study/boards.json``."""
    return Path(os.environ.get(BOARDS_ENV) or Path.home() / ".crs-study" / "boards.json")


@dataclass(frozen=True)
class PortIdentity:
    """What is known of the board behind one port (module docstring)."""

    port: str
    serial_number: str | None = None
    by_id: str | None = None
    location: str | None = None
    kind: str = "path"  # "usb", "pty", "virtual" (lscsim://NAME) or "path"

    @property
    def key(self) -> tuple[str, str] | None:
        """The strongest identity: ("serial_number" | "by_id" | "location" | "virtual", value),
        None when only the path is known."""
        for name in ("serial_number", "by_id", "location"):
            value = getattr(self, name)
            if value:
                return name, value
        if self.kind == "virtual":
            return "virtual", self.port
        return None

    def describe(self) -> str:
        """How this port's board is told apart, in words."""
        key = self.key
        if key is None:
            why = ("a pseudo-terminal" if self.kind == "pty" else "a port")
            return f"{self.port}: {why} with no USB serial number or by-id path (path only)"
        words = {"serial_number": "USB serial number", "by_id": "by-id path",
                 "location": "USB socket (location)", "virtual": "virtual board name"}
        return f"{self.port}: {words[key[0]]} {key[1]}"


def port_identity(spec: str) -> PortIdentity:
    """What the hardware reports of the port ``spec`` (a path or a pyserial URL)."""
    if spec.startswith("lscsim://"):
        return PortIdentity(spec, kind="virtual")
    if "://" in spec:
        return PortIdentity(spec)
    try:
        real = os.path.realpath(spec)
    except (OSError, ValueError):
        return PortIdentity(spec)
    if real.startswith("/dev/pts/") or real == "/dev/ptmx":
        return PortIdentity(spec, kind="pty")
    by_id = _by_id_link(real)
    for info in list_ports.comports():
        if os.path.realpath(info.device) == real:
            return PortIdentity(spec, info.serial_number or None, by_id,
                                info.location or None, kind="usb")
    return PortIdentity(spec, by_id=by_id, kind="usb" if by_id else "path")


def _by_id_link(real: str) -> str | None:
    try:
        links = sorted(BY_ID_DIR.iterdir())
    except OSError:
        return None
    for link in links:
        if os.path.realpath(link) == real:
            return link.name
    return None


@dataclass(frozen=True)
class Verdict:
    """How ``device check`` told the boards apart: ``ok`` False means swapped or replaced."""

    ok: bool
    how: str


class BoardRegister:
    """The confirmed identities (module docstring), by device file name and controller."""

    def __init__(self, path: Path | None = None) -> None:
        self.path = Path(path) if path is not None else default_register()

    def read(self) -> dict:
        try:
            text = self.path.read_text(encoding="utf-8")
        except FileNotFoundError:
            return {}
        except (OSError, UnicodeDecodeError) as error:
            raise DeviceError(f"{self.path}: cannot read the board register ({error})") from None
        try:
            data = json.loads(text)
        except (ValueError, RecursionError):
            data = None
        if not isinstance(data, dict) or not all(isinstance(v, dict) for v in data.values()):
            raise DeviceError(f"{self.path}: not a board register (expected a JSON object of "
                              "device files); delete it and run crs-study device identify")
        return data

    def remember(self, layout_name: str, boards: dict[str, PortIdentity]) -> None:
        data = self.read()
        when = datetime.now(UTC).isoformat(timespec="seconds")
        data[layout_name] = {name: {**asdict(identity), "confirmed": when}
                             for name, identity in boards.items()}
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            partial = self.path.with_name(self.path.name + ".partial")
            partial.write_text(json.dumps(data, indent=1) + "\n", encoding="utf-8")
            os.replace(partial, self.path)  # whole or not at all
        except OSError as error:
            why = error.strerror or str(error)
            raise DeviceError(f"{self.path}: cannot remember the boards ({why})") from None

    def check(self, layout_name: str, boards: dict[str, PortIdentity]) -> Verdict:
        """Compare the ports' identities with the confirmed ones (module docstring)."""
        stored = self.read().get(layout_name, {})
        keys = {name: identity.key for name, identity in boards.items()}
        if any(key is None for key in keys.values()):
            bare = [i for i in boards.values() if i.key is None]
            kinds = {"pty": "pseudo-terminals"}
            paths = [f"{', '.join(i.port for i in bare)}: "
                     f"{kinds.get(bare[0].kind, 'ports')} with no USB serial number or "
                     "by-id path, so by path only"]
            confirmed = [v.get("confirmed") for v in stored.values()
                         if isinstance(v, dict) and v.get("port") in
                         {i.port for i in boards.values()}]
            seen = (f"; the order was confirmed by eye with `crs-study device identify` on "
                    f"{confirmed[0]}, but a path says nothing of which board is behind it"
                    if confirmed else "; confirm which is which with `crs-study device "
                    "identify` (a servo of each board wiggles)")
            return Verdict(True, "not told apart by the hardware: " + "; ".join(paths) + seen)
        known = {name: _key(entry) for name, entry in stored.items() if isinstance(entry, dict)}
        if not known:
            return Verdict(True, "by " + ", ".join(i.describe() for i in boards.values())
                           + "; not yet confirmed: run `crs-study device identify` once")
        for name, key in keys.items():
            owner = next((other for other, k in known.items() if k == key), None)
            if owner is not None and owner != name:
                port_of = {identity.key: identity.port for identity in boards.values()}
                order = [port_of.get(known.get(n)) for n in boards]
                fix = (f"--device serial://{','.join(order)}" if all(order) else
                       "the ports in the device file's order")
                return Verdict(False, f"board {name}'s port {boards[name].port} is board "
                               f"{owner} ({key[1]}, confirmed {stored[owner].get('confirmed')})"
                               f": the ports are swapped; use {fix}, or run `crs-study device "
                               "identify` again if the boards were rewired")
            if key != known.get(name):
                return Verdict(False, f"board {name}'s port {boards[name].port} ({key[1]}) is "
                               "not the board confirmed for it; a board was replaced? run "
                               "`crs-study device identify` again")
        when = min(str(stored[n].get("confirmed")) for n in boards)
        return Verdict(True, "by " + ", ".join(f"{n} = {i.describe()}" for n, i in
                                               boards.items())
                       + f" (as confirmed by `crs-study device identify` on {when})")


def _key(entry: dict) -> tuple[str, str] | None:
    fields = {k: entry.get(k) for k in ("port", "serial_number", "by_id", "location", "kind")}
    try:
        return PortIdentity(**{k: v for k, v in fields.items() if v is not None}).key
    except TypeError:
        return None
