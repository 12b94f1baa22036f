"""A virtual LSC-24 board behind a real pseudo-terminal, so serial code is tested end to end.

``VirtualControllerPty`` opens a ``pty.openpty()`` pair and runs a thread on the master side
that reads what the serial code writes, hands it to a
:class:`~.virtual_controller.VirtualController` and writes the board's replies back. The slave
side is a real tty path (``/dev/pts/N``): pyserial opens it like any port, which is how
pyserial's own tests use ptys (hardware.md, "Testing serial code without hardware")::

    with VirtualControllerPty(VirtualController("A", record=True)) as bridge:
        device = open_device(f"serial://{bridge.port}", layout)

A pty moves bytes at memory speed. With ``baud`` set, the thread drains the pty no faster than
``baud / 10`` bytes a second, so the writer sees the backlog (``out_waiting``) of a real UART
at that rate; with ``baud=None`` bytes reach the board as fast as the kernel passes them.

:meth:`vanish` closes the master side: the slave's writes then fail with EIO, as when a USB
serial adapter is pulled out mid-stream.
"""

from __future__ import annotations

import os
import pty
import select
import threading
import time
import tty

from crs_study.device.virtual_controller import VirtualController

#: Longest the thread blocks in select(): how quickly it notices stop() and vanish().
POLL_S = 0.01


class VirtualControllerPty:
    """A virtual board on the master side of a pty pair; :attr:`port` is the slave path."""

    def __init__(self, board: VirtualController | None = None, baud: int | None = None) -> None:
        self.board = board or VirtualController(t0=time.monotonic())
        self.baud = baud
        self.master, self.slave = pty.openpty()
        tty.setraw(self.slave)  # no echo, no line discipline: bytes pass untouched
        self.port = os.ttyname(self.slave)
        self.bytes_received = 0
        self.error: BaseException | None = None  # what stopped the thread, if not stop()
        self._lock = threading.Lock()  # guards the board against readers in other threads
        self._stop = threading.Event()
        self._master_open = True
        self._thread = threading.Thread(target=self._serve, name=f"lsc-pty-{self.port}",
                                        daemon=True)
        self._thread.start()

    # -- the board's side ---------------------------------------------------------------------

    def _serve(self) -> None:
        byte_s = 10.0 / self.baud if self.baud else 0.0
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
                    arrived = wire_free
                    self._stop.wait(max(0.0, wire_free - time.monotonic()))
                with self._lock:
                    self.bytes_received += len(data)
                    reply = self.board.receive(data, arrived)
                if reply:
                    os.write(self.master, reply)
        except (OSError, ValueError) as exc:  # the master was closed under us (vanish)
            if self._master_open:
                self.error = exc

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

    def positions_us(self, t: float | None = None):
        """The board's servo pulse widths at ``t`` (default now), safely from any thread."""
        with self._lock:
            return self.board.positions_us(time.monotonic() if t is None else t)

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
