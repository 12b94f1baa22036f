"""When a frame will be in place, known before it is handed over: the device's own write policy,
shadowed.

Late binding (:mod:`crs_study.live.predict`) renders a frame for the time its servos will be
in place, so that time must be known for the very setpoints about to be handed over, not
guessed from earlier frames. :class:`FrameTiming` keeps its own copy of the device's write
policy (:class:`~crs_study.device.writes.PortWrites`, one per controller, with the device's
dead-band, refresh and baud rate: the pure code that decides what the device writes and when)
and feeds it every frame the session hands over, at the same time, with the same pulses. So
for candidate setpoints ``s`` handed over at ``t`` it tells, without writing anything:

* ``done(s)``: when the frame's last byte arrives, the latest board that gets one:
  ``max_b (max(t, free_b) + bytes_b(s) * 10 / baud)``, ``bytes_b = 3 n_b + 7`` for the
  ``n_b`` channels of board ``b`` that moved past the dead-band (a full write when the refresh
  rides on it); ``t`` when no channel changes (nothing lands: the display already shows it);
* ``travel(s)``: the servos' travel for the frame's largest move, ``max |s - s_prev| *
  0.08 s/cm`` (the layout's servo speed; ``s_prev`` the setpoints last handed over), or the
  SERVO_MOVE time when that is longer; 0 when nothing is written.

``done(s)`` is a lower bound of when the frame can be in place: its servos start moving when
their board has the frame's last byte. The device's own report (``FrameReport.wire_done_at``)
is checked against the shadow for every frame handed over (:attr:`FrameTiming.disagreed`
counts the frames where they differ by more than a microsecond: another writer on the port).
A device without a write policy (``policy`` and ``split``) gets the conservative figure:
every frame lands at its hand-over (``done = t``).
"""

from __future__ import annotations

import numpy as np

#: The shadow and the device's report agree within this (s).
AGREE_S = 1e-6
#: Late binding: renders per frame at most, and when a target time has settled (s).
PASSES = 3
SETTLED_S = 0.001


class FrameTiming:
    """The device's write policy, shadowed (module docstring)."""

    def __init__(self, device, move_ms: int = 0) -> None:
        policy, split = getattr(device, "policy", None), getattr(device, "split", None)
        pulse_map = getattr(device, "pulse_map", None)
        self.exact = policy is not None and split is not None and pulse_map is not None
        self.ports = split.ports(policy) if self.exact else []
        self.members = split.members if self.exact else ()
        self.pulse_map = pulse_map
        self.move_ms = move_ms
        self.speed_s_per_mm = device.layout.servo_speed_s_per_mm
        self.last = device.layout.neutral_setpoints()
        self.disagreed = 0
        self.guess = 0.0  # the last frame's target time after its hand-over (s)

    def _want(self, t: float, setpoints: np.ndarray) -> None:
        pulses = self.pulse_map.to_pulses(setpoints)
        for port, members in zip(self.ports, self.members, strict=True):
            port.want(t, pulses[members], self.move_ms)

    def landing(self, t: float, setpoints: np.ndarray) -> tuple[float, float]:
        """(done, travel) of the frame ``setpoints`` if handed over at ``t`` (module
        docstring): when its last byte is on its boards (``t``: nothing would be written) and
        its servos' time for the largest move (0 when nothing would be written)."""
        if not self.exact:
            return t, self._travel(setpoints)
        self._want(t, setpoints)
        done = t
        for port in self.ports:
            _, n_bytes, port_done = port.predict(t)
            if n_bytes:
                done = max(done, port_done)
        return done, (self._travel(setpoints) if done > t else 0.0)

    def _travel(self, setpoints: np.ndarray) -> float:
        move = float(np.max(np.abs(setpoints - self.last))) if setpoints.size else 0.0
        return max(move * self.speed_s_per_mm, self.move_ms / 1000.0)

    def handed(self, t: float, setpoints: np.ndarray, reported_done: float) -> None:
        """The frame ``setpoints`` went to the device at ``t`` and the device expects its last
        byte at ``reported_done``: the shadow books it as the device did."""
        if self.exact:
            self._want(t, setpoints)
            # the device reports max(t, each port's write end), a port writing nothing ending
            # when its wire frees
            done = max([t] + [port.take(t).done for port in self.ports])
            self.disagreed += abs(done - reported_done) > AGREE_S
        self.last = setpoints

    def bind(self, now: float, predictor, raw: tuple[float, float, float], render
             ) -> tuple[tuple, float, tuple]:
        """Late binding: the frame handed over at ``now`` rendered for when it will be in place.

        ``render(position) -> (kind, setpoints, ...)`` renders a finger position. Each pass
        renders for a target time ``T`` and asks the shadow when that frame lands:
        ``T' = done + min(travel, max_lead_s)``; it stops when ``|T' - T| <=``
        :data:`SETTLED_S` and ``T <= done + max_lead_s``, after :data:`PASSES` at most. A frame
        still rendered for later than its ``done + max_lead_s`` is rendered once more for
        ``now + max_lead_s``. So no frame is rendered for more than ``max_lead_s`` after the
        earliest time it can be in place (``done``; ``now`` for one that writes nothing):
        the lead bound, by construction. Returns (position, rendered for, render's result).
        """
        bound = predictor.config.max_lead_s
        target = now + self.guess
        for _ in range(PASSES):
            position, rendered_for = predictor.at(target, raw)
            rendering = render(position)
            if rendering[0] != "finger":  # flat: nothing under the finger to time
                return position, rendered_for, rendering
            done, travel = self.landing(now, rendering[1])
            expected = done + min(travel, bound)
            if rendered_for <= done + bound and abs(expected - target) <= SETTLED_S:
                break
            target = expected
        if rendered_for > done + bound:
            position, rendered_for = predictor.at(now + bound, raw)
            rendering = render(position)
        self.guess = max(target - now, 0.0)
        return position, rendered_for, rendering
