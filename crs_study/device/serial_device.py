"""SerialDevice: the CRS display on LSC-24 boards through pyserial, one port per controller.

URL syntax::

    serial://PORT[,PORT...]

one PORT per ``[[controllers]]`` table of the device file, in file order. A PORT is a device
path (``/dev/ttyUSB0``, ``COM3``) or any pyserial URL (``spy:///dev/ttyUSB0``, ``loop://``,
``rfc2217://host:port``, or a scheme registered through ``serial.protocol_handler_packages``,
such as the simulator's); it is handed to :func:`serial.serial_for_url` unchanged, so a
``?query`` inside a PORT belongs to that port's pyserial URL. A PORT cannot contain a comma.
Device options (:class:`SerialOptions`) are keyword arguments of :meth:`SerialDevice.from_url`
(the ``crs-study device`` flags), never part of the URL.

Writing (what goes on the wire, and when: the write policy, :mod:`~crs_study.device.writes`)
    Each port has a writer thread (:class:`~crs_study.device.serial_port.SerialPort`, which
    says how it paces the wire), so controllers are written concurrently.
    :meth:`SerialDevice.send` converts setpoints to whole-us pulses (refusing anything outside
    calibrated limits before any byte moves), hands them to each port as its *latest wanted
    pulses* and returns at once.

Which channel goes on which controller (the decision, and why)
    The device file pins every channel (``"A:3"``), and software never moves one: there is no
    automatic balancing, in this device or the simulated one. A channel is a servo's lead
    plugged into a pin of one board; a frame sent for it to another board would move whatever
    is plugged in there, and PWM servos give no feedback to catch the mix-up. So the device
    file is the record of the wiring, and balancing is a wiring decision made once, when the
    servos are plugged in. What software does: it measures the balance
    (:func:`~crs_study.device.schedule.channel_balance`), warns on open
    (:class:`DeviceWarning`) when the busiest controller's full frame is more than 10 %
    longer than an even split's, naming how many channels to rewire from which board to
    which, and ``crs-study device check`` prints the map in use. What balancing buys, from
    :func:`~crs_study.device.schedule.wire_plan` on the default protocol's CRS digits: the
    even count is the lever (``crs-study bench device``: median latency 29.2 ms for the
    shipped 19/18 split, 38.5 ms for a lopsided 24/13 one); which channels make up an even
    split moves the tail a little and the median hardly (without the refresh: shipped median
    29.2 ms, max 51.0 ms; an interleaved or a random 19/18 split median 29.2 to 32.3 ms, max
    47.9 to 51.0 ms), so no assignment is worth a rewiring for one stimulus.

Safety: :meth:`SerialDevice.open` asks each board for its battery voltage (a board that does
not answer gives None and a :class:`DeviceWarning`; one below ``min_battery_mv`` is a
:class:`DeviceError`), and :meth:`SerialDevice.heartbeat_ask` asks again (the runner does at every
trial boundary): a board that no longer answers has stopped reading, which nothing else would
show, since the LSC protocol acknowledges no move. A port that fails (vanished, write timeout,
stalled writer) makes the next :meth:`SerialDevice.send` raise :class:`DeviceError`; a reader
thread per port notices a vanished port within ``read_timeout_s`` even when nothing is being
sent. :meth:`close` (also on error and Ctrl-C through the context manager) sends every channel
to the neutral pose, waits for it to leave, and releases the ports in ``finally``.
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Sequence
from typing import Any

import numpy as np

from crs_study.clock import Clock
from crs_study.device.base import (
    BITS_PER_BYTE,
    Device,
    DeviceWarning,
    FrameReport,
    default_move_ms,
    servo_move_bytes,
)
from crs_study.device.calibration import PulseMap
from crs_study.device.codec import (
    MOVE_TIME_MAX_MS,
    PULSE_MAX_US,
    PULSE_MIN_US,
)
from crs_study.device.schedule import channel_balance, warn_if_unbalanced
from crs_study.device.serial_port import SerialOptions, SerialPort, is_whole, parse_serial_url
from crs_study.device.writes import (
    ChannelSplit,
    WritePolicy,
)
from crs_study.errors import DeviceError
from crs_study.geometry.layout import Layout


class SerialDevice(Device):
    """A CRS display on real LSC-24 boards (module docstring). Build with :meth:`from_url`.

    ``ports`` holds one pyserial URL or path per controller, or ready serial-like objects
    (``write``, ``read``, ``in_waiting``, ``reset_input_buffer``, ``close``), e.g. for tests.
    """

    def __init__(self, layout: Layout, ports: Sequence[str | Any], clock: Clock | None = None,
                 options: SerialOptions | None = None) -> None:
        super().__init__(layout, clock)
        if len(ports) != len(layout.controllers):
            names = ", ".join(c.name for c in layout.controllers)
            raise DeviceError(
                f"serial device: expected {len(layout.controllers)} port(s), one per controller "
                f"({names}) in device-file order, got {len(ports)}: {list(ports)!r}"
            )
        self.options = options or SerialOptions()
        self.pulse_map = PulseMap.from_layout(layout)
        self.split = ChannelSplit(layout)
        self.policy = WritePolicy(self.options.deadband_us, self.options.refresh_s,
                                  self.options.baud)
        self.balance = channel_balance(layout)
        self.ports = [SerialPort(i, c.name, spec, self.options, self.clock, self.split, self.policy)
                      for i, (c, spec) in enumerate(zip(layout.controllers, ports, strict=True))]
        self.default_move_ms = (self.options.move_ms if self.options.move_ms is not None else
                                default_move_ms(layout, self.options.baud))
        self._last_setpoints = layout.neutral_setpoints()
        self._state = "new"

    @classmethod
    def from_url(cls, url: str, layout: Layout, clock: Clock | None = None, **options: Any
                 ) -> SerialDevice:
        return cls(layout, parse_serial_url(url), clock, SerialOptions.from_options(options))

    # -- Device interface ------------------------------------------------------------------

    def open(self) -> None:
        if self._state != "new":
            raise DeviceError(f"serial device: cannot open a device that is {self._state}")
        self._state = "opening"
        warn_if_unbalanced(self.layout)
        try:
            for port in self.ports:
                port.open()
            if self.options.check_battery:
                self._check_batteries()
            for port in self.ports:
                port.start()
        except BaseException:
            self._state = "closed"
            for port in self.ports:
                port.stop()
                port.close()
            raise
        self._state = "open"

    def _check_batteries(self) -> None:
        for port in self.ports:
            port.battery_mv = port.query_battery()
            if port.battery_mv is None:
                warnings.warn(f"{port.label}: no answer to GET_BATTERY_VOLTAGE within "
                              f"{self.options.battery_timeout_s:g} s; battery unknown",
                              DeviceWarning, stacklevel=3)
            elif port.battery_mv < self.options.min_battery_mv:
                raise DeviceError(
                    f"{port.label}: battery {port.battery_mv} mV is below the "
                    f"{self.options.min_battery_mv} mV minimum (option min_battery_mv); "
                    f"charge or replace it"
                )

    def send(self, setpoints_mm: np.ndarray, move_ms: int | None = None) -> FrameReport:
        commanded_at = self.clock.now()
        self._check_open()
        pulses = self.pulse_map.to_pulses(setpoints_mm)
        report = self._hand_over(pulses, move_ms, commanded_at)
        self._last_setpoints = np.asarray(setpoints_mm, dtype=float).copy()
        return report

    def send_pulses(self, pulses_us: np.ndarray, move_ms: int | None = None) -> FrameReport:
        """Command raw pulse widths (us, actuator order), for calibration only.

        Checked against the board's 500..2500 us, not the calibration being established.
        """
        commanded_at = self.clock.now()
        self._check_open()
        pulses = np.asarray(pulses_us)
        if pulses.shape != (self.layout.n_actuators,) or not np.all(
                (pulses >= PULSE_MIN_US) & (pulses <= PULSE_MAX_US) & (pulses == np.rint(pulses))):
            raise DeviceError(f"pulse widths: expected {self.layout.n_actuators} whole numbers "
                              f"{PULSE_MIN_US}..{PULSE_MAX_US} us, got {pulses_us!r}")
        return self._hand_over(pulses.astype(np.int64), move_ms, commanded_at)

    def _check_open(self) -> None:
        if self._state != "open":
            raise DeviceError(f"serial device: send() on a device that is {self._state}; "
                              f"open it first (use it as a context manager)")

    def _hand_over(self, pulses: np.ndarray, move_ms: int | None, commanded_at: float
                   ) -> FrameReport:
        """Make ``pulses`` every port's latest wanted frame; predict when it leaves the wire."""
        move = self.default_move_ms if move_ms is None else move_ms
        if not is_whole(move, 0, MOVE_TIME_MAX_MS):
            raise DeviceError(f"move time: expected a whole number of ms 0..{MOVE_TIME_MAX_MS}, "
                              f"got {move!r}")
        for port in self.ports:
            port.check(commanded_at)
        sent, done, channels, merged = [], commanded_at, 0, False
        for port in self.ports:
            with port.cond:
                merged |= port.writes.want(commanded_at, pulses[self.split.members[port.index]],
                                           move)
                n, n_bytes, port_done = port.writes.predict(commanded_at)
                port.cond.notify_all()
            sent.append(n_bytes)
            channels += n
            done = max(done, port_done)
        return FrameReport(commanded_at, done, tuple(sent), channels, merged)

    def close(self) -> None:
        if self._state in ("closed", "new"):
            self._state = "closed"
            return
        self._state = "closing"
        try:
            self._neutral_on_close()
        finally:
            for port in self.ports:
                port.stop()
            for port in self.ports:
                port.close()
            self._state = "closed"

    def _neutral_on_close(self) -> None:
        """Every channel to neutral, slowly; best effort, failures recorded in ``faults``."""
        pulses = self.pulse_map.to_pulses(self.layout.neutral_setpoints())
        byte_s = BITS_PER_BYTE / self.options.baud
        now = self.clock.now()
        for port in self.ports:
            with port.cond:
                healthy = port.error is None and all(t.is_alive() for t in port.threads)
                if healthy:
                    port.writes.want(now, pulses[self.split.members[port.index]],
                                     self.options.neutral_move_ms, full=True)
                    port.cond.notify_all()
            if not healthy:
                self._neutral_direct(port, pulses)
        budget = (2 * servo_move_bytes(self.layout.n_actuators) * byte_s
                  + self.options.write_timeout_s)
        for port in self.ports:
            if port.error is None and port.threads and not port.wait_sent(budget):
                self.faults.append(f"{port.label}: neutral pose not confirmed sent "
                                   f"({port.error or 'timeout'})")
        self._last_setpoints = self.layout.neutral_setpoints()

    def _neutral_direct(self, port: SerialPort, pulses: np.ndarray) -> None:
        local = np.arange(len(self.split.members[port.index]))
        data = self.split.frame(port.index, pulses, local, self.options.neutral_move_ms)
        if port.serial is None or not data:
            return
        # the writer thread may still be inside a write (a reader noticed the failure first):
        # wait for it rather than interleave, but never longer than a write may take
        if not port.write_lock.acquire(timeout=self.options.write_timeout_s + 0.5):
            self.faults.append(f"{port.label}: neutral pose not sent: a write is still stuck "
                               f"({port.error})")
            return
        try:
            port.serial.write(data)
        except Exception as exc:  # noqa: BLE001 - the port already failed; report, go on
            self.faults.append(f"{port.label}: neutral pose not sent: {exc}")
        finally:
            port.write_lock.release()

    def heartbeat_ask(self) -> tuple[list[int], float]:
        """GET_BATTERY_VOLTAGE on every port now (between two frames, never inside one); the
        reader threads collect the answers. Returns what :meth:`heartbeat_check` needs."""
        self._check_open()
        for port in self.ports:
            port.check(self.clock.now())
        before = [port.ask_battery() for port in self.ports]
        return before, time.monotonic() + self.options.heartbeat_timeout_s

    def heartbeat_check(self, asked: object) -> None:
        """Every board answered the question :meth:`heartbeat_ask` put, within
        ``heartbeat_timeout_s`` of it (an answer already in is not waited for; a board that
        did not answer is asked once more, as a garbled reply is no hung board), else a
        :class:`DeviceError` naming the silent ones; an answer below ``min_battery_mv`` is
        one too. Failures are also appended to :attr:`faults`."""
        before, deadline = asked  # type: ignore[misc]
        answers = [port.battery_answer(b, deadline) for port, b in zip(self.ports, before,
                                                                        strict=True)]
        if None in answers:  # asked once more: a reply garbled on the wire is no hung board
            again = {i: port.ask_battery() for i, (port, mv) in
                     enumerate(zip(self.ports, answers, strict=True)) if mv is None}
            deadline = time.monotonic() + self.options.heartbeat_timeout_s
            for i, token in again.items():
                answers[i] = self.ports[i].battery_answer(token, deadline)
        silent = [port.label for port, mv in zip(self.ports, answers, strict=True) if mv is None]
        problem = None
        if silent:
            problem = (f"{'; '.join(silent)}: no answer to GET_BATTERY_VOLTAGE within "
                       f"{self.options.heartbeat_timeout_s:g} s: the board stopped reading (or "
                       "lost power), so its servos may hold their last position rather than "
                       "neutral")
        else:
            low = [f"{port.label} {mv} mV" for port, mv in zip(self.ports, answers, strict=True)
                   if mv < self.options.min_battery_mv]
            if low:
                problem = (f"battery below {self.options.min_battery_mv} mV: {', '.join(low)}; "
                           "charge or replace it")
        if problem:
            self.faults.append(problem)
            raise DeviceError(problem)

    def wait_sent(self, timeout_s: float = 1.0) -> bool:
        """Wait until every frame handed over has been written (or merged and written).

        Returns False when ``timeout_s`` (real time) passes first or a port failed.
        """
        deadline = time.monotonic() + timeout_s
        return all(p.wait_sent(max(0.0, deadline - time.monotonic())) for p in self.ports)

    def displayed_setpoints(self, t: float | None = None) -> np.ndarray:
        """The last commanded setpoints: PWM servos report no position."""
        return self._last_setpoints.copy()

    def battery_mv(self) -> list[float | None]:
        return [None if p.battery_mv is None else float(p.battery_mv) for p in self.ports]

    def stats(self) -> dict[str, dict[str, int]]:
        """Frames and bytes written per controller so far."""
        return {p.name: {"frames": p.frames_written, "bytes": p.bytes_written}
                for p in self.ports}
