"""A virtual LSC-24 board behind a real pseudo-terminal, so serial code is tested end to end.

``VirtualControllerPty`` opens a ``pty.openpty()`` pair and runs a thread on the master side
that reads what the serial code writes, hands it to a
:class:`~.virtual_controller.VirtualController` and writes the board's replies back. The slave
side is a real tty path (``/dev/pts/N``): pyserial opens it like any port, which is how
pyserial's own tests use ptys (pyserial's test suite)::

    with VirtualControllerPty(VirtualController("A", record=True)) as bridge:
        device = open_device(f"serial://{bridge.port}", layout)

A pty moves bytes at memory speed. With ``baud`` set, the thread drains the pty no faster than
``baud / 10`` bytes a second (in chunks of at most 64 bytes, each delivered when its last byte
has had its wire time), so bytes back up in the pty as they would in a real UART's output
buffer; with ``baud=None`` bytes reach the board as fast as the kernel passes them. A
``baud`` below the writer's (9000 against 9600) plays a wire slower than nominal (a USB
adapter's baud error, gaps between bytes).

The backlog: Linux reports 0 for ``TIOCOUTQ`` (pyserial's ``out_waiting``) on a pty slave
whatever waits in it, unlike a USB serial adapter's driver. :meth:`VirtualControllerPty.backlog`
counts what a UART would (bytes not yet read by the board's side, ``FIONREAD`` on the master,
plus the chunk still on the wire), and :meth:`VirtualControllerPty.open_serial` opens the
slave as a pyserial port whose ``out_waiting`` is that backlog::

    device = SerialDevice(layout, [a.open_serial(), b.open_serial()], clock)

:meth:`vanish` closes the master side: the slave's writes then fail with EIO, as when a USB
serial adapter is pulled out mid-stream.

The tap: with ``tap=True`` every byte the board receives is copied, as it arrives, to a second
pty whose slave path is :attr:`VirtualControllerPty.tap_port`, so ``crs-study device monitor
--port TAP`` decodes the line to the board as a hardware tap on its RX wire would. Nobody
reading the tap never holds the board up: copies go out without blocking and, while more
than :data:`TAP_STALE_BYTES` wait unread, what waits is dropped first (a monitor attached
later sees the line from about then). ``listener(data, arrived)``, when given, is called with
every chunk the board receives (the ``device boards`` command's live view).
"""

from __future__ import annotations

import fcntl
import math
import os
import pty
import select
import struct
import termios
import threading
import time
import tty
from collections.abc import Callable
from typing import Any

import serial

from crs_study.device.virtual_controller import VirtualController

#: Longest the thread blocks in select(): how quickly it notices stop() and vanish().
POLL_S = 0.01
#: Unread bytes on the tap beyond which the tap is flushed before the next copy.
TAP_STALE_BYTES = 1024


class VirtualControllerPty:
    """A virtual board on the master side of a pty pair; :attr:`port` is the slave path."""

    def __init__(self, board: VirtualController | None = None, baud: int | None = None,
                 tap: bool = False,
                 listener: Callable[[bytes, float], None] | None = None) -> None:
        self.board = board or VirtualController(t0=time.monotonic())
        self.listener = listener
        self.tap_port: str | None = None
        self._tap = (-1, -1)
        if tap:
            self._tap = pty.openpty()
            tty.setraw(self._tap[1])
            os.set_blocking(self._tap[0], False)
            self.tap_port = os.ttyname(self._tap[1])
        self.baud = baud
        self.master, self.slave = pty.openpty()
        tty.setraw(self.slave)  # no echo, no line discipline: bytes pass untouched
        self.port = os.ttyname(self.slave)
        self.bytes_received = 0
        self.error: BaseException | None = None  # what stopped the thread, if not stop()
        self._lock = threading.Lock()  # guards the board against readers in other threads
        self._stop = threading.Event()
        self._master_open = True
        self._byte_s = 10.0 / baud if baud else 0.0
        self._on_wire_until = 0.0  # when the chunk read last has had its wire time
        self._thread = threading.Thread(target=self._serve, name=f"lsc-pty-{self.port}",
                                        daemon=True)
        self._thread.start()

    # -- the board's side ---------------------------------------------------------------------

    def _serve(self) -> None:
        byte_s = self._byte_s
        wire_free = time.monotonic()
        try:
            while not self._stop.is_set():
                ready, _, _ = select.select([self.master], [], [], POLL_S)
                if not ready:
                    continue
                try:
                    data = os.read(self.master, 64 if byte_s else 4096)
                except OSError:  # EIO: no slave open at the moment; wait for one
                    time.sleep(POLL_S)
                    continue
                if not data:
                    continue
                now = time.monotonic()
                arrived = now
                if byte_s:
                    wire_free = max(wire_free, now) + len(data) * byte_s
                    arrived = self._on_wire_until = wire_free
                    self._stop.wait(max(0.0, wire_free - time.monotonic()))
                with self._lock:
                    self.bytes_received += len(data)
                    reply = self.board.receive(data, arrived)
                self._copy_to_tap(data)
                if self.listener is not None:
                    self.listener(data, arrived)
                if reply:
                    os.write(self.master, reply)
        except (OSError, ValueError) as exc:  # the master was closed under us (vanish)
            if self._master_open:
                self.error = exc

    def _copy_to_tap(self, data: bytes) -> None:
        """Copy what the board received to the tap, never blocking (module docstring)."""
        master, slave = self._tap
        if master < 0:
            return
        try:
            unread = struct.unpack("i", fcntl.ioctl(slave, termios.FIONREAD, b"\0\0\0\0"))[0]
            if unread > TAP_STALE_BYTES:
                termios.tcflush(slave, termios.TCIFLUSH)
            os.write(master, data)
        except (BlockingIOError, OSError):
            pass  # a full or closed tap loses the copy, never the board's bytes

    # -- control ------------------------------------------------------------------------------

    def wait_for_bytes(self, count: int, timeout: float = 5.0) -> bool:
        """Wait until the board has received at least ``count`` bytes; False on timeout."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            with self._lock:
                if self.bytes_received >= count:
                    return True
            time.sleep(0.002)
        return False

    def backlog(self) -> int:
        """Bytes written to the slave that have not reached the board: what a UART's
        ``TIOCOUTQ`` counts (its buffer and the byte being shifted out)."""
        if not self._master_open:
            return 0
        try:
            waiting = struct.unpack("i", fcntl.ioctl(self.master, termios.FIONREAD,
                                                     b"\0\0\0\0"))[0]
        except OSError:
            return 0
        if self._byte_s:
            waiting += max(0, math.ceil((self._on_wire_until - time.monotonic()) / self._byte_s))
        return waiting

    def open_serial(self, **settings: Any) -> Any:
        """The slave as an open pyserial port whose ``out_waiting`` is :meth:`backlog`
        (``settings`` go to :class:`serial.Serial`; default 9600 baud, 0.05 s read and 0.5 s
        write timeouts, as :class:`~.serial_device.SerialDevice` opens its ports)."""
        bridge = self

        class PtySerial(serial.Serial):
            @property
            def out_waiting(self) -> int:
                return bridge.backlog()

        options: dict[str, Any] = {"baudrate": 9600, "timeout": 0.05, "write_timeout": 0.5}
        options.update(settings)
        return PtySerial(self.port, **options)

    def positions_us(self, t: float | None = None):
        """The board's servo pulse widths at ``t`` (default now), safely from any thread."""
        with self._lock:
            return self.board.positions_us(time.monotonic() if t is None else t)

    def hang(self, at: float | None = None) -> None:
        """The board stops reading at ``at`` (``time.monotonic``; default now): bytes still
        flow into the pty, but the board acts on none and answers nothing."""
        with self._lock:
            self.board.hang(time.monotonic() if at is None else at)

    def vanish(self) -> None:
        """Close the master side now: the port disappears under the writer."""
        self._master_open = False
        self._stop.set()
        self._thread.join(timeout=1.0)
        _close(self.master)

    def close(self) -> None:
        """Stop the thread and close both ends (idempotent)."""
        self._stop.set()
        self._thread.join(timeout=1.0)
        if self._master_open:
            self._master_open = False
            _close(self.master)
        _close(self.slave)
        self.slave = -1
        for fd in self._tap:
            _close(fd)
        self._tap = (-1, -1)

    def __enter__(self) -> VirtualControllerPty:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()


def _close(fd: int) -> None:
    if fd >= 0:
        try:
            os.close(fd)
        except OSError:
            pass
