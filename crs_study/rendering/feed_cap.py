"""The feed cap: no beam is commanded, or left on the boards, longer than it can stably be.

A beam cannot be made longer than its longest stable shape through its pixel heights, the one
at the solver's margin of the critical load (0.98 N_cr: :meth:`CompressedBeams.longest_feeds
<crs_study.display.beam.CompressedBeams.longest_feeds>`); beyond it the ``beam`` model raises
:class:`~crs_study.errors.CollapseError` (the rule that asks for more, and when:
:mod:`crs_study.rendering.render`). The cap keeps each beam's total feed at or below that.

What the boards hold is not the setpoint (the wire's slack, :class:`WireSlack`)
    The host sends whole-microsecond pulses (:class:`~crs_study.device.calibration.PulseMap`
    rounds to the nearest), and its write policy (:mod:`crs_study.device.writes`) resends a
    channel only when its pulse moved by more than the dead-band, so a board may hold an older
    pulse. Each channel's pulse on the board is therefore within ``hold = quantum / 2 +
    dead-band`` (1.5 us by default: 0.0135 mm on a 9 mm / 1000 us servo) of the exact one.
    Capped at the longest stable shape alone, 2 of 201 frames of a finger writing 9 collapsed
    once rounded (a feed of 9.3 um on two servos became 2 x 9 um), and 39 more once the
    dead-band held a servo's old pulse (feeds left at 1 us on each end of a beam whose pixels
    had gone flat, where the straight beam takes 3.6 um).
So, with a :class:`WireSlack`, two rules (Renderer's ``wire``; ``None``: the setpoints reach the
beams exactly, the cap is the longest stable shape itself, as the quality criteria use it)
    1. *Room for the slack.* Each beam's total feed F is capped at
       ``longest(h) - stretch * sum_p |dL/dh_p| hold_p - (hold_start + hold_end)``: the feed
       on the boards is at most F plus the two ends' hold, and the longest feed for any pixel
       heights within their hold of h is at least ``longest(h)`` less the pixel term, because
       the arc length ``L(h) = sum_q w_q sqrt(1 + (T h)_q^2)`` is convex in h and so lies
       above its tangent plane: ``L(h') >= L(h) - sum_p |dL/dh_p| |h'_p - h_p|``, with
       ``dL/dh_p = sum_q w_q (T h)_q / sqrt(1 + (T h)_q^2) T_qp``.
    2. *A feed servo is at rest or clear of it.* A servo's feed at or below its hold (the
       largest pulse that could be held over a later rest) is set to 0: every pulse a feed
       servo is sent is then its rest pulse or more than the dead-band away from it, so a
       command to rest is always written and the boards never keep a feed on a beam the
       renderer flattened (rule 1 cannot help there: a flat beam's longest feed, ~3.6 um on
       ``crs2d``, is less than one pulse). Feeds this small are below what the wire shows
       reliably; setting them to rest is a quantisation, not a clip, and is not reported.
    Together: whatever the boards hold, F' <= F + hold_start + hold_end <= longest(h'), and
    ``BeamModel`` solves the decoded setpoints (tests/test_feed_cap.py decodes the simulated
    boards' pulses). Not covered: the moments while one board has a frame and the other not
    yet, and servos in motion (transitions, which a sensed surface may skip).

Reported: a message (:attr:`Rendering.clamped`, an error under ``policy="error"``) when the
condition asks for more than the longest stable shape itself. Lowering a feed that fits that
shape but not the room (rule 1), or setting it to rest (rule 2), is the wire's margin, not a
clip of what the condition asks, and is not reported (the protocols' device checks run under
``policy="error"``).

Measured (``Renderer(layout, "crs")`` against ``wire=None`` over every CRS frame of the
shipped protocols; the boards: tests/test_feed_cap.py)
    ``digit_identification`` and ``pilot``: 412 of 561 frames change, by rule 2 (1298 feeds
    of at most 13.5 um set to rest); ``digit_size_psychometric``: 1962 of 2942 (6760 feeds set
    to rest, 21 frames lowered by rule 1), by at most 25 um (3 us of pulse); no message in
    any. So the frame logs of sessions change (resume refuses a session begun before:
    :func:`crs_study.session.resume.check_frames`). A finger writing 9, 8 or 2 in live mode:
    6 of 201, 15 of 265 and 9 of 196 frames collapsed a beam on the boards with the cap alone,
    none with the room.

How it is computed (within the live link's budget: under 1 % of a frame's wire time)
    :meth:`CompressedBeams.longest_operator` gives the longest shape's slopes per mm of each
    pixel's height; here they become one dense matrix for all beams (the slopes at every node
    = one product with the pixel heights) and, per beam, one matrix of its length's weights and
    its gradient terms (one batched product of ``[sqrt(1 + top^2); top / sqrt(1 + top^2)]``),
    so a frame's cap is two products and two ufuncs, and the rules run on Python floats. It
    equals ``longest_feeds`` to rounding (sums in another order: ~1e-13 mm;
    tests/test_feed_cap.py). Rule 2's guarantee assumes whole-us rest pulses (``zero_us``), as
    the shipped device files have: a fractional one rounds the rest pulse itself.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from crs_study.display.beam import CompressedBeams
from crs_study.errors import RenderError
from crs_study.geometry.layout import Layout

#: The LSC-24's pulse resolution (us): SERVO_MOVE carries whole microseconds
#: (:data:`crs_study.device.calibration.PULSE_QUANTUM_US`; tests check they agree).
PULSE_QUANTUM_US = 1.0
#: The write policy's default dead-band (us) (:data:`crs_study.device.writes.DEFAULT_DEADBAND_US`;
#: tests check they agree).
WIRE_DEADBAND_US = 1
#: A feed servo's rest floor is its hold times this: a feed just above the hold must not round
#: (half to even) onto the dead-band's last pulse.
_FLOOR_GUARD = 1.0 + 1e-9


@dataclass(frozen=True)
class WireSlack:
    """How far the pulse a board holds may be from a setpoint's exact pulse (module docstring).

    ``deadband_us``: the device's write-policy dead-band (its ``deadband_us`` option);
    ``quantum_us``: the pulse resolution.
    """

    deadband_us: int = WIRE_DEADBAND_US
    quantum_us: float = PULSE_QUANTUM_US

    def __post_init__(self) -> None:
        if isinstance(self.deadband_us, bool) or not isinstance(self.deadband_us, int) \
                or self.deadband_us < 0:
            raise RenderError(f"wire slack: dead-band: expected a whole number of us >= 0, "
                              f"got {self.deadband_us!r}")
        if isinstance(self.quantum_us, bool) or not isinstance(self.quantum_us, int | float) \
                or not (math.isfinite(self.quantum_us) and self.quantum_us > 0):
            raise RenderError(f"wire slack: pulse quantum: expected us > 0, "
                              f"got {self.quantum_us!r}")

    @classmethod
    def for_device(cls, device: object) -> WireSlack:
        """The slack of ``device``'s write policy: its ``options.deadband_us`` (both shipped
        devices have one: ``sim://?deadband_us=``, ``SerialOptions.deadband_us``); the default
        dead-band for a device without one. A dead-band wider than the default needs more
        room under the longest stable shape, so every renderer that feeds a device takes the
        device's own."""
        deadband = getattr(getattr(device, "options", None), "deadband_us", WIRE_DEADBAND_US)
        return cls(int(deadband))

    @property
    def hold_us(self) -> float:
        """Farthest a board's pulse may be from the exact one: half a quantum of rounding
        plus the dead-band a held channel may lag by."""
        return 0.5 * self.quantum_us + self.deadband_us


#: The slack of the shipped write policy (whole-us pulses, the default dead-band): a
#: renderer's default.
DEFAULT_WIRE = WireSlack()


def mm_per_us(layout: Layout) -> np.ndarray:
    """Each actuator's stroke per microsecond of pulse width (mm), from the device file's
    calibration (:class:`~crs_study.device.calibration.PulseMap`'s linear map)."""
    return np.array([a.calibration.travel_mm / abs(a.calibration.full_us - a.calibration.zero_us)
                     for a in layout.actuators])


class FeedCap:
    """The feed cap of one layout (module docstring): :meth:`apply` per frame.

    The beams' tables (:class:`CompressedBeams`, ~0.2 s) are built on the first frame that
    feeds a beam.
    """

    def __init__(self, layout: Layout, wire: WireSlack | None) -> None:
        self.layout = layout
        self.wire = wire
        self.n_pixels = layout.n_pixels
        self.travel = float(layout.boundary_travel_mm)
        self.n_beams = len(layout.beams)
        self._beams: CompressedBeams | None = None
        self._slopes: np.ndarray | None = None  # (B nq, n_pixels)
        self._terms: np.ndarray | None = None  # (B, nq, 1 + pixels a beam)
        self._buffer: np.ndarray | None = None  # (B, 1 or 2, nq)
        self._offset: list[float] = []
        self._n_gradient: list[int] = []  # pixels on each beam (0 without a wire)
        self.height_hold: np.ndarray | None = None
        self.feed_hold = [0.0] * self.n_beams
        #: each beam's (start, end) feed at or below which the servo is set to rest (rule 2)
        self.floor: list[tuple[float, float]] | None = None
        if wire is not None:
            hold = wire.hold_us * mm_per_us(layout)
            hold.setflags(write=False)
            self.height_hold = hold[: self.n_pixels]
            pairs = [(b.start_servo, b.end_servo) for b in layout.beams]
            self.feed_hold = [float(hold[s] + hold[e]) for s, e in pairs]
            self.floor = [(float(hold[s]) * _FLOOR_GUARD, float(hold[e]) * _FLOOR_GUARD)
                          for s, e in pairs]

    @property
    def beams(self) -> CompressedBeams:
        if self._beams is None:
            self._beams = CompressedBeams.for_layout(self.layout)
        return self._beams

    def _build(self) -> None:
        """The products of the module docstring, from the beams' longest shapes."""
        slopes, weights, offset = self.beams.longest_operator()
        n_beams, nq, n_pixels = slopes.shape
        pixels = [beam.pixels for beam in self.layout.beams] if self.height_hold is not None \
            else [() for _ in self.layout.beams]
        # per beam, columns: its length's weights, then per pixel on it the weights of
        # stretch |dL/dh_p| hold_p (applied to top / sqrt(1 + top^2))
        terms = np.zeros((n_beams, nq, 1 + max(len(p) for p in pixels)))
        terms[:, :, 0] = weights
        for b, beam_pixels in enumerate(pixels):
            for j, p in enumerate(beam_pixels, start=1):
                terms[b, :, j] = weights[b] * slopes[b, :, p] * self.height_hold[p]
        self._slopes = np.ascontiguousarray(slopes.reshape(n_beams * nq, n_pixels))
        self._terms = terms
        # per beam: row 0 sqrt(1 + top^2) at its nodes, row 1 top / sqrt(1 + top^2)
        self._buffer = np.empty((n_beams, 2 if self.height_hold is not None else 1, nq))
        self._offset = offset.tolist()
        self._n_gradient = [len(p) for p in pixels]

    def limits(self, heights: np.ndarray) -> tuple[list[float], list[float]]:
        """``(longest, room)`` per beam (mm, >= 0) for pixel heights ``heights`` (n_pixels,):
        the longest stable shape's feed, and the largest feed whose pulses on the boards stay
        stable (rule 1; ``longest`` itself without a wire)."""
        if self._slopes is None:
            self._build()
        buffer = self._buffer
        top = (self._slopes @ heights).reshape(buffer.shape[0], buffer.shape[2])  # slopes
        root = np.hypot(top, 1.0, out=buffer[:, 0])  # sqrt(1 + top^2)
        if self.height_hold is None:
            longest = [total - offset for (total,), offset in
                       zip((buffer @ self._terms)[:, 0].tolist(), self._offset, strict=True)]
            longest = [feed if feed > 0.0 else 0.0 for feed in longest]
            return longest, longest
        np.divide(top, root, out=buffer[:, 1])
        longest, room = [], []
        for (length, gradient), offset, n, hold in zip(
                (buffer @ self._terms).tolist(), self._offset, self._n_gradient,
                self.feed_hold, strict=True):
            feed = length[0] - offset
            longest.append(feed if feed > 0.0 else 0.0)
            for term in gradient[1:n + 1]:
                feed -= term if term > 0.0 else -term
            feed -= hold
            room.append(feed if feed > 0.0 else 0.0)
        return longest, room

    def apply(self, heights: np.ndarray, starts: list[float], ends: list[float]
              ) -> tuple[list[float], list[float], list[str]]:
        """Each beam's capped (start, end) feeds and one message per beam whose rule asks for
        more than its longest stable shape.

        ``heights``: the pixel heights (n_pixels,); ``starts``, ``ends``: each beam's start
        and end feed (mm). Rule 2 first (a feed at rest needs no room: the boards hold exactly
        its rest pulse), then rule 1 on the feeds left, then rule 2 on the capped ones. The
        lists returned are new; equal to the ones given when nothing changed.
        """
        if not (any(starts) or any(ends)):
            return starts, ends, []
        floor = self.floor
        fed_starts, fed_ends = list(starts), list(ends)
        if floor is not None:
            for b, (low_start, low_end) in enumerate(floor):
                if fed_starts[b] <= low_start:
                    fed_starts[b] = 0.0
                if fed_ends[b] <= low_end:
                    fed_ends[b] = 0.0
        longest, room = self.limits(heights)
        messages = []
        for b in range(self.n_beams):
            if fed_starts[b] + fed_ends[b] > room[b]:
                start = min(0.5 * room[b], self.travel)  # split_feed of the capped total
                end = room[b] - start
                if floor is not None:
                    start = 0.0 if start <= floor[b][0] else start
                    end = 0.0 if end <= floor[b][1] else end
                fed_starts[b], fed_ends[b] = start, end
            total = starts[b] + ends[b]
            if total > longest[b]:
                messages.append(
                    f"beam {b}: feed {total:.4f} mm capped to {fed_starts[b] + fed_ends[b]:.4f}"
                    f" mm (the longest stable shape through its pixel heights{self._less}; "
                    f"more would collapse the beam)")
        return fed_starts, fed_ends, messages

    @property
    def _less(self) -> str:
        return "" if self.wire is None else (", less the room the boards' whole-us pulses and "
                                             "dead-band need")
