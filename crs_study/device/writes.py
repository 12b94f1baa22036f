"""The host's write policy: what goes on each controller's wire, and when. Pure: no I/O, no clock.

One :class:`PortWrites` per controller port decides every SERVO_MOVE the host writes. Its
three users drive it with their own notion of time and their own bytes:
:class:`~crs_study.device.serial_device.SerialDevice`'s writer thread (a real port, a real
clock), :class:`~crs_study.device.simulated.SimulatedDevice`'s event model (virtual boards,
any clock) and :func:`~crs_study.device.schedule.simulate_port` (the estimate behind
``validate``, ``device check`` and the bench). So the three put the same bytes on the wire at
the same times for the same frames (tests/test_write_policy.py proves it on random frame
sequences).

The calls
    ``want(t, pulses, move_ms)``: the host wants this controller's channels at ``pulses``
    (whole us) from ``t`` on. ``next_write_at()``: the earliest time the next write may start
    (``inf``: nothing to write). ``take(t)``: the write handed to the port at ``t`` (it starts
    on the wire at ``max(t, free)``); the caller encodes and writes it. ``written(t, n)``: ``n``
    other bytes (a battery query) went on this wire at ``t``. ``predict(t)``: what the waiting
    frame's write will be (what a device reports for a frame it hands over).

The policy (LSC protocol: 9600 baud, 10 bits a byte, 1.0417 ms; a SERVO_MOVE for n servos is
3 n + 7 bytes)
    * Merging, never queueing: a frame wanted while the wire is busy waits; a newer one
      replaces it; when the wire frees, one write carries the newest wanted frame. Latency
      stays bounded (one write waited for plus its own) however fast frames come.
    * Changed-only: a write carries the channels whose wanted pulse differs by more than
      ``deadband_us`` from what was last sent on them (none changed: nothing is written).
    * Full writes carry every channel: the first write, one wanted with ``full=True`` (the
      neutral pose on close), and the refresh.
    * The refresh (every ``refresh_s``; 0: never) repairs what the board lost or garbled (an
      LSC frame has no checksum and a PWM servo gives no feedback, so a wrong position would
      otherwise stay until its channel changes again). It rides on a frame: the first write
      that starts ``refresh_s`` or more after the last full write carries every channel. So
      while frames flow every channel is on the wire at least every ``refresh_s`` plus one
      frame period, and the first frame after a pause of ``refresh_s`` (a stimulus onset after
      the response phase) is full. A wire with no frame to carry is not written.

Why the refresh rides on a frame rather than going out on its own when due (the serial
device's writer sent it on its own, also on an idle wire; the simulated device and the
estimate with the next frame; the decision, with its arithmetic and measurements)
    The shipped 2D device at the default protocol's 15 frames/s (a 66.7 ms period): board A's
    full frame is 19 servos, 64 bytes, 66.7 ms; a CRS digit's changed-only frame on A is a
    median 22 bytes (5 channels, 23 ms). Riding, the refresh turns one frame's 22 bytes into
    64: that frame's latency is 66.7 ms and the wire carries 42 bytes more. On its own, the
    refresh falls due somewhere in the period after frame k's write; it carries frame k's
    pulses (not the newest) in 64 bytes, and frame k + 1 then waits behind it for up to
    66.7 ms before its own 22 bytes: up to 89.6 ms, more where the next frames queue up behind
    it, and 64 bytes more on the wire. Measured over the ten CRS digits (``crs-study bench
    writes``): the largest latency is 66.7 ms riding and 108 ms on its own (99th percentile
    66.7 against 99 ms), and riding sends 5 % fewer bytes.
    A refresh of an idle wire (the neutral pose held between trials) would cost no latency, and
    the serial device's writer sent one; it was dropped too, for what it breaks (measured with
    it in place): it moves the refresh to another frame of every stimulus, so repeated
    presentations of a digit no longer reach the skin identically. Dry-runs then gave other
    simulated responses than before (20 and 25 of 120 trials for the default protocol's first
    two participants; a session resumed across versions would mix the two), and the observer's
    cache of sensed frames stopped hitting: a default-protocol dry-run took half as much CPU
    time again (1.19 s against 0.81 s, medians of five). What it would repair (a frame garbled
    while a pose is held) the next stimulus's first frame repairs, full, before anything is
    presented, and ``close`` sends a full neutral pose.

Ties: at a time ``t`` where a write falls due and a frame is wanted, the write goes first
(the frame then waits for it), in all three users.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from crs_study.device.base import BAUD_RATE, BITS_PER_BYTE, servo_move_bytes
from crs_study.device.codec import servo_move_arrays
from crs_study.errors import DeviceError
from crs_study.geometry.layout import Layout

#: Default dead-band (us): a channel is resent when its pulse moved by more than this. 1 us is
#: 0.009 mm on a 9 mm / 1000 us servo, far below feel, and it stops a slowly drifting channel
#: (typically a boundary servo's feed, sub-micron per frame) from costing 3 bytes every frame;
#: the full refresh puts the exact value on the wire at its interval.
DEFAULT_DEADBAND_US = 1

#: Default full-refresh interval (s): the first frame this long after the last full write
#: carries every channel (0: never).
DEFAULT_REFRESH_S = 1.0

#: Frames remembered by each :class:`ChannelSplit`'s encoder (cleared when full).
ENCODE_CACHE_SIZE = 1 << 15


@dataclass(frozen=True)
class WritePolicy:
    """How a port's writes are chosen (module docstring).

    ``send_all``: every write carries every channel (the estimate's send-everything baseline).
    """

    deadband_us: int = DEFAULT_DEADBAND_US
    refresh_s: float = DEFAULT_REFRESH_S
    baud: int = BAUD_RATE
    send_all: bool = False

    def __post_init__(self) -> None:
        if not (isinstance(self.deadband_us, int | np.integer)
                and not isinstance(self.deadband_us, bool) and self.deadband_us >= 0):
            raise DeviceError(f"dead-band: expected a whole number of us >= 0, "
                              f"got {self.deadband_us!r}")
        if not (isinstance(self.refresh_s, int | float | np.floating)
                and not isinstance(self.refresh_s, bool)
                and math.isfinite(self.refresh_s) and self.refresh_s >= 0):
            raise DeviceError(f"refresh interval: expected a number of seconds >= 0 (0: none), "
                              f"got {self.refresh_s!r}")
        if not (isinstance(self.baud, int | np.integer) and not isinstance(self.baud, bool)
                and self.baud > 0):
            raise DeviceError(f"baud rate: expected a whole number > 0, got {self.baud!r}")

    @property
    def byte_s(self) -> float:
        """Seconds a byte takes on the wire (8N1: 10 bits)."""
        return BITS_PER_BYTE / self.baud


def changed_channels(pulses: np.ndarray, last_sent: np.ndarray, deadband_us: int) -> np.ndarray:
    """Indices of the channels whose pulse differs from ``last_sent`` by more than the
    dead-band (both whole-us vectors of one controller's channels)."""
    diff = pulses - last_sent
    np.abs(diff, out=diff)
    return (diff > deadband_us).nonzero()[0]


class Write(NamedTuple):
    """One write the policy put on a port (:meth:`PortWrites.take`)."""

    start: float  # when its first byte goes on the wire (s)
    done: float  # when its last byte has left (s); ``start`` when nothing is written
    local: np.ndarray  # the channels it carries: indices into the controller's channels
    pulses: np.ndarray  # the controller's wanted pulses, every channel (whole us)
    move_ms: int
    full: bool  # carries every channel
    n_bytes: int  # 3 len(local) + 7, or 0: nothing changed, nothing is written


class PortWrites:
    """The write policy of one controller's port (module docstring). Not thread-safe: the
    serial device calls it under the port's lock.

    Parameters
    ----------
    n_channels : channels of this controller (the length of every ``pulses``).
    policy : dead-band, refresh and baud rate.
    last_sent : pulses the board already has (None: unknown, the first write is full).
    last_full_at : when every channel was last written (-inf: never).
    """

    __slots__ = ("policy", "byte_s", "refresh_s", "deadband_us", "send_all", "every", "wanted",
                 "move_ms", "pending", "force_full", "wanted_at", "last_sent", "last_full_at",
                 "free_at")

    def __init__(self, n_channels: int, policy: WritePolicy,
                 last_sent: np.ndarray | None = None, last_full_at: float = -math.inf) -> None:
        self.policy = policy
        self.byte_s = policy.byte_s
        self.refresh_s = float(policy.refresh_s)
        self.deadband_us = int(policy.deadband_us)
        self.send_all = bool(policy.send_all)
        self.every = np.arange(n_channels)  # ``local`` of a full write (shared, read-only)
        self.every.setflags(write=False)
        self.wanted: np.ndarray | None = None  # the newest wanted pulses
        self.move_ms = 0
        self.pending = False  # ``wanted`` has not been taken yet
        self.force_full = False
        self.wanted_at = -math.inf  # when ``wanted`` was handed over
        self.last_sent = None if last_sent is None else np.array(last_sent, dtype=np.int64)
        self.last_full_at = float(last_full_at)
        self.free_at = -math.inf  # when the bytes booked so far have left the wire

    # -- the three calls ----------------------------------------------------------------------

    def want(self, t: float, pulses: np.ndarray, move_ms: int, full: bool = False) -> bool:
        """The host wants ``pulses`` (this controller's channels, whole us) from ``t`` on.

        The port keeps ``pulses`` (do not change it afterwards). ``full``: the next write
        carries every channel. Returns True when an earlier wanted frame was still waiting
        (this one replaces it: merged).
        """
        merged = self.pending
        self.wanted = pulses
        self.move_ms = move_ms
        self.wanted_at = t
        self.pending = True
        self.force_full |= full
        return merged

    def next_write_at(self) -> float:
        """Earliest time the next write may start: when the wire frees for a waiting frame;
        ``inf`` when no frame waits."""
        return max(self.free_at, self.wanted_at) if self.pending else math.inf

    def take(self, t: float) -> Write | None:
        """The write of the waiting frame, handed to the port at ``t``: it starts on the wire
        at ``max(t, free)`` and is booked there. None when no frame waits."""
        if not self.pending:
            return None
        start = t if t > self.free_at else self.free_at
        full = (self.force_full or self.last_sent is None or self.send_all
                or (self.refresh_s > 0 and start - self.last_full_at >= self.refresh_s))
        wanted = self.wanted
        if full:
            local = self.every
            self.last_sent = wanted.copy()
            self.last_full_at = start
        else:  # changed_channels, inline: this runs for every frame of a dry-run
            diff = wanted - self.last_sent
            np.abs(diff, out=diff)
            local = (diff > self.deadband_us).nonzero()[0]
            self.last_sent[local] = wanted[local]
        n = len(local)
        n_bytes = 3 * n + 7 if n else 0  # servo_move_bytes
        done = start + n_bytes * self.byte_s
        self.free_at = done
        self.pending = self.force_full = False
        # Write(...) without its keyword-handling constructor: once per frame and port
        return tuple.__new__(Write, (start, done, local, wanted, self.move_ms, full, n_bytes))

    def written(self, t: float, n_bytes: int) -> float:
        """``n_bytes`` other bytes were written to this port at ``t`` (a battery query): the
        wire is busy with them from ``max(t, free)``. Returns when they have left."""
        self.free_at = max(t, self.free_at) + n_bytes * self.byte_s
        return self.free_at

    # -- what a waiting frame will cost ---------------------------------------------------------

    def predict(self, t: float) -> tuple[int, int, float]:
        """(channels, bytes, done) of the waiting frame if its write starts as early as it may
        (``max(t, free)``), as :meth:`take` would then decide; (0, 0, t) with nothing waiting.
        """
        if not self.pending:
            return 0, 0, t
        start = t if t > self.free_at else self.free_at
        if (self.force_full or self.last_sent is None or self.send_all
                or (self.refresh_s > 0 and start - self.last_full_at >= self.refresh_s)):
            n = len(self.every)
        else:
            n = len(changed_channels(self.wanted, self.last_sent, self.deadband_us))
        n_bytes = servo_move_bytes(n) if n else 0
        return n, n_bytes, start + n_bytes * self.byte_s


class ChannelSplit:
    """Which actuators sit on which controller, and the SERVO_MOVE bytes of a write.

    ``members[c]`` are the actuator indices on controller ``c`` (device-file order), ``ids[c]``
    their servo ids. The channel of each actuator is pinned by the device file (the decision:
    :mod:`~crs_study.device.serial_device`, "Which channel goes on which controller").
    Encoded frames are remembered by content (``cache=True``): a dry-run replays each digit's
    stimulus many times, and a look-up costs less than checking and packing a frame again.
    """

    def __init__(self, layout: Layout, cache: bool = False) -> None:
        acts = layout.actuators
        self.layout = layout
        self.names = tuple(c.name for c in layout.controllers)
        self.members = tuple(np.array([a.index for a in acts if a.controller == name],
                                      dtype=np.intp) for name in self.names)
        self.ids = tuple(np.array([acts[i].channel for i in m], dtype=np.int64)
                         for m in self.members)
        self._encoded: dict[tuple[int, int, bytes, bytes], bytes] | None = {} if cache else None

    def ports(self, policy: WritePolicy) -> list[PortWrites]:
        """A fresh :class:`PortWrites` per controller."""
        return [PortWrites(len(m), policy) for m in self.members]

    def changed(self, controller: int, pulses: np.ndarray, last_sent: np.ndarray | None,
                deadband_us: int = DEFAULT_DEADBAND_US) -> np.ndarray:
        """Local indices (into ``members[controller]``) of channels to send.

        ``pulses`` is the full actuator vector; ``last_sent`` this controller's last sent
        pulses (None: unknown, send all).
        """
        mine = pulses[self.members[controller]]
        if last_sent is None:
            return np.arange(len(mine))
        return changed_channels(mine, last_sent, deadband_us)

    def frame(self, controller: int, pulses: np.ndarray, local: np.ndarray, move_ms: int
              ) -> bytes:
        """SERVO_MOVE bytes moving channels ``local`` of ``controller`` to ``pulses`` (the full
        actuator vector); b"" when none."""
        return self.encode(controller, pulses[self.members[controller]], local, move_ms)

    def encode(self, controller: int, mine: np.ndarray, local: np.ndarray, move_ms: int
               ) -> bytes:
        """SERVO_MOVE bytes moving channels ``local`` of ``controller`` to ``mine[local]``
        (``mine``: that controller's pulses, every channel); b"" when none."""
        if not len(local):
            return b""
        full = len(local) == len(mine)  # local is then every channel, in order
        values = mine if full else mine[local]
        cache = self._encoded
        if cache is None:
            return servo_move_arrays(self.ids[controller] if full else
                                     self.ids[controller][local], values, move_ms)
        key = (controller, move_ms, local.tobytes(), values.tobytes())
        data = cache.get(key)
        if data is None:
            data = servo_move_arrays(self.ids[controller] if full else
                                     self.ids[controller][local], values, move_ms)
            if len(cache) >= ENCODE_CACHE_SIZE:
                cache.clear()
            cache[key] = data
        return data

    def write_bytes(self, controller: int, write: Write) -> bytes:
        """The bytes of ``write`` on ``controller``'s port (b"" when it carries nothing)."""
        return self.encode(controller, write.pulses, write.local, write.move_ms)

    def clear_cache(self) -> None:
        """Forget remembered encodings (benchmarks of a first presentation)."""
        if self._encoded is not None:
            self._encoded.clear()
