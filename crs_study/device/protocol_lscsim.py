"""pyserial URL handler ``lscsim://NAME``: a port whose far end is a virtual LSC-24 board.

After :func:`register`, ``serial.serial_for_url("lscsim://A")`` (and so anything built on
pyserial, such as :class:`~crs_study.device.serial_device.SerialDevice`) talks to the
:class:`~.virtual_controller.VirtualController` registered under ``A`` (:func:`attach`), or to
a fresh one made on first use and then reachable through :func:`controller` or
``port.controller``. pyserial finds the handler by module name (``protocol_<scheme>`` in a
package listed in ``serial.protocol_handler_packages``), hence this module's name.

URL::

    lscsim://NAME[?channels=24&channel_base=1&battery_mv=7400&vanish_after=S&hang_after=S]

``vanish_after``: the port fails (like a USB adapter pulled out) ``S`` seconds after open; so
does :meth:`Serial.vanish` at once. Writes then raise ``SerialException`` (EIO), as pyserial's
POSIX port does. ``hang_after``: the board stops reading ``S`` seconds after open
(:meth:`~.virtual_controller.VirtualController.hang`): the port still takes bytes, but the
board acts on none and answers nothing.

Timing is real (``time.monotonic``): written bytes leave at ``baudrate / 10`` bytes a second
(``out_waiting`` counts those not yet gone, ``flush`` waits for them), each frame reaches the
board when its last byte does, and the board's replies arrive byte-timed too. ``read`` honours
``timeout``; ``write`` honours ``write_timeout`` when the wire is already more than that far
behind. Nothing here starts a thread: the port catches up whenever it is used.

Threads: every call that touches the wire (``write``, ``read``, ``in_waiting``,
``out_waiting``, ``flush``, the resets) holds the port's lock while it delivers and queues, so
one thread reading and another writing the same port (as
:class:`~crs_study.device.serial_device.SerialDevice` does) hand frames to the board whole and
in the order they were written, with arrival times that never go backwards. The lock is not
held while ``read`` or ``flush`` waits.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from urllib.parse import parse_qsl, urlsplit

import serial
from serial.serialutil import PortNotOpenError, SerialBase, SerialException, SerialTimeoutException

from crs_study.device.virtual_controller import NORMAL_BATTERY_MV, VirtualController

_BOARDS: dict[str, VirtualController] = {}
_LOCK = threading.Lock()
PACKAGE = "crs_study.device"


def register() -> None:
    """Let ``serial.serial_for_url`` resolve ``lscsim://`` (idempotent)."""
    if PACKAGE not in serial.protocol_handler_packages:
        serial.protocol_handler_packages.append(PACKAGE)


def attach(name: str, board: VirtualController) -> VirtualController:
    """Serve ``board`` at ``lscsim://name`` (replacing any board of that name)."""
    with _LOCK:
        _BOARDS[name] = board
    return board


def detach(name: str) -> None:
    with _LOCK:
        _BOARDS.pop(name, None)


def controller(name: str) -> VirtualController:
    """The board behind ``lscsim://name``."""
    with _LOCK:
        return _BOARDS[name]


class Serial(SerialBase):
    """A pyserial port wired to a virtual LSC-24 (module docstring)."""

    def __init__(self, *args, **kwargs) -> None:
        self.controller: VirtualController | None = None
        self._outgoing: deque[tuple[float, bytes]] = deque()  # (arrival of last byte, bytes)
        self._incoming = bytearray()
        self._replies: deque[tuple[float, bytes]] = deque()
        self._wire_free = 0.0
        self._vanish_at = float("inf")
        # one lock for the wire state above: a reader and a writer thread each pump the wire,
        # and two pumps could otherwise pop two frames and hand them to the board swapped
        self._wire_lock = threading.RLock()
        super().__init__(*args, **kwargs)

    # -- pyserial plumbing --------------------------------------------------------------------

    def open(self) -> None:
        if self.is_open:
            raise SerialException("Port is already open.")
        if self._port is None:
            raise SerialException("Port must be configured before it can be used.")
        self._from_url(self.portstr)
        self.is_open = True

    def close(self) -> None:
        with self._wire_lock:
            if self.is_open:
                try:
                    self._pump(self._vanish_at)  # what is on the wire still arrives
                finally:
                    self.is_open = False
        super().close()

    def _reconfigure_port(self) -> None:
        if not isinstance(self._baudrate, int) or self._baudrate <= 0:
            raise ValueError(f"invalid baudrate: {self._baudrate!r}")

    def _from_url(self, url: str) -> None:
        parts = urlsplit(url)
        form = ("lscsim://NAME[?channels=24&channel_base=1&battery_mv=7400&vanish_after=S"
                "&hang_after=S]")
        if parts.scheme != "lscsim" or not parts.netloc:
            raise SerialException(f"expected {form}, got {url!r}")
        options = {"channels": 24, "channel_base": 1, "battery_mv": NORMAL_BATTERY_MV}
        vanish_after = hang_after = None
        for key, value in parse_qsl(parts.query, keep_blank_values=True):
            try:
                if key == "vanish_after":
                    vanish_after = float(value)
                elif key == "hang_after":
                    hang_after = float(value)
                elif key in options:
                    options[key] = int(value)
                else:
                    raise ValueError(f"unknown option {key!r}")
            except ValueError as exc:
                raise SerialException(f"{url!r}: {exc}; expected {form}") from None
        now = time.monotonic()
        with _LOCK:
            board = _BOARDS.get(parts.netloc)
            if board is None:
                board = VirtualController(parts.netloc, options["channels"],
                                          options["channel_base"],
                                          battery_mv=options["battery_mv"], t0=now)
                _BOARDS[parts.netloc] = board
        self.controller = board
        self._wire_free = now
        if vanish_after is not None:
            self._vanish_at = now + vanish_after
        if hang_after is not None:
            with self._wire_lock:
                board.hang(now + hang_after)

    # -- the wire -----------------------------------------------------------------------------

    @property
    def _byte_s(self) -> float:
        return 10.0 / self._baudrate

    def vanish(self) -> None:
        """The port fails now (an adapter pulled out)."""
        with self._wire_lock:
            self._vanish_at = min(self._vanish_at, time.monotonic())

    def _pump(self, now: float | None = None) -> None:
        """Deliver what has arrived at the board by ``now``; collect replies that have come.

        Callers hold ``_wire_lock``: popping a frame and handing it to the board is one step.
        """
        now = time.monotonic() if now is None else now
        board = self.controller
        while self._outgoing and self._outgoing[0][0] <= min(now, self._vanish_at):
            arrived, data = self._outgoing.popleft()
            reply = board.receive(data, arrived)
            if reply:
                self._replies.append((arrived + len(reply) * self._byte_s, reply))
        while self._replies and self._replies[0][0] <= now:
            self._incoming += self._replies.popleft()[1]
        if now >= self._vanish_at:
            self._outgoing.clear()

    def _check(self) -> None:
        """Raise when the port is closed or has vanished; callers hold ``_wire_lock``."""
        if not self.is_open:
            raise PortNotOpenError()
        if time.monotonic() >= self._vanish_at:
            self._pump(self._vanish_at)
            raise SerialException("write failed: [Errno 5] Input/output error (port vanished)")

    def write(self, data: bytes) -> int:
        data = bytes(data)
        with self._wire_lock:
            self._check()
            now = time.monotonic()
            self._pump(now)
            start = max(now, self._wire_free)
            if self._write_timeout is not None and start - now > self._write_timeout:
                raise SerialTimeoutException("Write timeout")
            if data:
                self._wire_free = start + len(data) * self._byte_s
                self._outgoing.append((self._wire_free, data))
        return len(data)

    def flush(self) -> None:
        with self._wire_lock:
            if not self.is_open:  # io's close() flushes after we closed
                return
            self._check()
            wire_free = self._wire_free
        time.sleep(max(0.0, wire_free - time.monotonic()))
        with self._wire_lock:
            if self.is_open:
                self._pump()

    @property
    def out_waiting(self) -> int:
        with self._wire_lock:
            self._check()
            now = time.monotonic()
            self._pump(now)
            return max(0, round((self._wire_free - now) / self._byte_s))

    @property
    def in_waiting(self) -> int:
        with self._wire_lock:
            self._check()
            self._pump()
            return len(self._incoming)

    def read(self, size: int = 1) -> bytes:
        deadline = None if self._timeout is None else time.monotonic() + self._timeout
        while True:
            with self._wire_lock:
                self._check()
                self._pump()
                if len(self._incoming) >= size or (deadline is not None
                                                   and time.monotonic() >= deadline):
                    data = bytes(self._incoming[:size])
                    del self._incoming[:size]
                    return data
            time.sleep(0.0005)

    def reset_input_buffer(self) -> None:
        with self._wire_lock:
            self._check()
            self._pump()
            self._incoming.clear()

    def reset_output_buffer(self) -> None:
        with self._wire_lock:
            self._check()
            self._outgoing.clear()
            self._wire_free = time.monotonic()

    def _update_rts_state(self) -> None:
        pass

    def _update_dtr_state(self) -> None:
        pass

    def _update_break_state(self) -> None:
        pass

    @property
    def cts(self) -> bool:
        return True

    @property
    def dsr(self) -> bool:
        return True

    @property
    def ri(self) -> bool:
        return False

    @property
    def cd(self) -> bool:
        return True
