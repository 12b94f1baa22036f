"""When each frame reached the boards and the servos reached its position.

Two sources, one interface (``add(frame)``, ``poll(now) -> finished frames``):

:class:`BoardTap` (virtual boards: ``sim://`` and pty boards)
    reads what the boards themselves decoded (:attr:`VirtualController.received`, with the
    time each frame's last byte arrived), matches every decoded SERVO_MOVE to the frame it
    came from by content (its channels' pulse widths equal the frame's, exactly), and replays
    the decoded moves through the servo model (:class:`~crs_study.device.virtual_controller.
    ServoBank`, started from the boards' own servo specs) to find when every servo of the
    display reaches its commanded position. A frame whose write was replaced before it went
    (merged) is skipped by the next match; a decoded move that matches no frame (garbage on
    the wire) is counted and still moves the replayed servos, as it moves the board's.
:class:`HostModel` (any device, the only source on real boards)
    the device's own account: :attr:`FrameReport.wire_done_at`, the write policy's model of
    the wire; no servo times (PWM servos report nothing).

Servos in place: after frame f has landed, the time every servo of every board reaches its
latest command, ``max(arrive)`` of the servo model (a move takes ``max(T, |dp| / v)``,
docs/device.md), as if no later frame came. A board that got nothing for f (no channel changed)
counts with its servos' state after its last write before f.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from crs_study.device.calibration import PulseMap
from crs_study.device.codec import ServoMove
from crs_study.device.virtual_boards import board_specs
from crs_study.device.virtual_controller import (
    ServoBank,
    VirtualController,
)
from crs_study.geometry.layout import Layout

#: A write still missing this long after the host expected it to land is given up (s).
GIVE_UP_S = 0.5


@dataclass(eq=False)
class ShownFrame:
    """A frame the session handed to the device, and what became of it.

    ``kind``: ``start`` (the neutral pose at the start), ``finger`` (a bump under a finger),
    ``flat`` (a finger outside the area or not pressing), ``silence`` (no packet for the
    timeout), ``close`` (the neutral pose at the end).
    """

    index: int
    kind: str
    setpoints: np.ndarray
    handed_at: float
    host_done: float  # FrameReport.wire_done_at
    bytes_sent: tuple[int, ...]
    sequence: int | None = None  # the packet it carries
    arrivals: list[float] = field(default_factory=list)  # carried packet first, then superseded
    software_s: float = math.nan  # decode + render + hand-over of the carried packet
    shown: tuple[float, float, float] | None = None  # finger frame: (x_f, y_f, z_f) rendered
    rendered_for: float = math.nan  # the time that position was predicted for
    landed: list[float | None] = field(default_factory=list)  # per board; None: nothing came
    settled: list[float] = field(default_factory=list)  # per board: servos in place
    lost: bool = False  # a write expected on a board never matched
    done_at: float = math.nan  # when its last byte arrived (the latest board)
    in_place_at: float = math.nan  # when every servo reached its position (NaN: unknown)

    @property
    def wrote(self) -> bool:
        return any(self.bytes_sent)


class HostModel:
    """Frames land when the device said they would (module docstring)."""

    source = "host model"
    unmatched = 0  # nothing is decoded here

    def __init__(self) -> None:
        self.pending: deque[ShownFrame] = deque()

    def add(self, frame: ShownFrame) -> None:
        self.pending.append(frame)

    def poll(self, now: float, flush: bool = False) -> list[ShownFrame]:
        done = []
        while self.pending and (flush or self.pending[0].host_done <= now):
            frame = self.pending.popleft()
            frame.done_at = frame.host_done
            done.append(frame)
        return done

    def next_due(self) -> float:
        return self.pending[0].host_done if self.pending else math.inf


class BoardTap:
    """Frames matched to the virtual boards' decoded bytes (module docstring).

    Parameters
    ----------
    layout : the display.
    boards : one :class:`VirtualController` per controller, in device-file order, each made
        with ``record=True``; what the tap has read is removed from ``received``.
    advance : called before reading (the simulated device delivers bytes lazily).
    """

    source = "boards"

    def __init__(self, layout: Layout, boards: Sequence[VirtualController],
                 advance=None) -> None:
        if len(boards) != len(layout.controllers):
            raise ValueError(f"expected {len(layout.controllers)} boards, got {len(boards)}")
        self.layout = layout
        self.boards = list(boards)
        self.advance = advance
        self.pulse_map = PulseMap.from_layout(layout)
        self.banks = [ServoBank(b.servos.rest_us.copy(), b.servos.max_speed.copy(), -math.inf)
                      for b in self.boards]
        # per board: channel id -> actuator index (-1: no actuator on that channel)
        self.actuator_of = []
        for c, board in zip(layout.controllers, self.boards, strict=True):
            table = np.full(board.channel_base + board.channels, -1, dtype=np.intp)
            for a in layout.actuators:
                if a.controller == c.name:
                    table[a.channel] = a.index
            self.actuator_of.append(table)
        self.pending: deque[ShownFrame] = deque()
        self._pulses: dict[int, np.ndarray] = {}
        self.cursor = [0] * len(self.boards)  # per board: position in ``pending`` to match from
        self.carry = [-math.inf] * len(self.boards)  # servos in place after the last write
        self.unmatched = 0  # decoded moves that matched no frame

    def add(self, frame: ShownFrame) -> None:
        frame.landed = [None] * len(self.boards)
        frame.settled = [math.nan] * len(self.boards)
        self.pending.append(frame)

    def _expected(self, frame: ShownFrame) -> np.ndarray:
        pulses = self._pulses.get(frame.index)
        if pulses is None:
            pulses = self._pulses[frame.index] = self.pulse_map.to_pulses(frame.setpoints)
        return pulses

    def next_due(self) -> float:
        return self.pending[0].host_done if self.pending else math.inf

    def poll(self, now: float, flush: bool = False) -> list[ShownFrame]:
        """Read the boards, match, and return the frames now finished, in order. ``flush``:
        the session is over and every byte has arrived; give up on what is missing."""
        if self.advance is not None:
            self.advance(now)
        for b, board in enumerate(self.boards):
            received = board.received
            count = len(received)  # a board's thread may append meanwhile: read a prefix
            for entry in received[:count]:
                if isinstance(entry.message, ServoMove):
                    self._apply(b, entry.t, entry.message)
            del received[:count]
        finished = []
        while self.pending:
            frame = self.pending[0]
            waiting = [b for b in range(len(self.boards))
                       if frame.bytes_sent[b] and frame.landed[b] is None
                       and self.cursor[b] == 0]
            if waiting and not flush and now < frame.host_done + GIVE_UP_S:
                break
            frame.lost = any(frame.bytes_sent[b] and frame.landed[b] is None
                             for b in range(len(self.boards)))
            for b in range(len(self.boards)):
                if frame.landed[b] is None:
                    frame.settled[b] = self.carry[b]
                else:
                    self.carry[b] = frame.settled[b]
                self.cursor[b] = max(0, self.cursor[b] - 1)
            landed = [t for t in frame.landed if t is not None]
            frame.done_at = max(landed) if landed else frame.handed_at
            frame.in_place_at = max(max(frame.settled), frame.done_at)
            self.pending.popleft()
            self._pulses.pop(frame.index, None)
            finished.append(frame)
        return finished

    def _apply(self, b: int, t: float, move: ServoMove) -> None:
        board = self.boards[b]
        ids = np.array([servo for servo, _ in move.positions], dtype=np.intp)
        values = np.array([pulse for _, pulse in move.positions], dtype=np.int64)
        local = ids - board.channel_base
        ok = (local >= 0) & (local < board.channels)
        bank = self.banks[b]
        if ok.any():
            bank.command(local[ok], values[ok].astype(float), move.time_ms / 1000.0, t)
        settle = float(bank.arrive.max())
        table = self.actuator_of[b]
        actuators = np.where((ids >= 0) & (ids < len(table)), table[np.clip(ids, 0,
                                                                            len(table) - 1)], -1)
        if np.any(actuators < 0):
            self.unmatched += 1
            return
        for k in range(self.cursor[b], len(self.pending)):
            frame = self.pending[k]
            if frame.landed[b] is None and np.array_equal(self._expected(frame)[actuators],
                                                          values):
                frame.landed[b] = t
                frame.settled[b] = settle
                self.cursor[b] = k + 1
                return
        self.unmatched += 1


def virtual_boards(layout: Layout, t0: float) -> list[VirtualController]:
    """One recording :class:`VirtualController` per controller of ``layout`` (device-file
    order), with the layout's servos (:func:`~crs_study.device.virtual_boards.board_specs`, as
    the simulated device models them): boards for pty ports."""
    return [VirtualController(c.name, c.channels, c.channel_base, board_specs(layout, c.name),
                              t0=t0, record=True) for c in layout.controllers]
