"""Calibration: mm <-> pulse width per channel, limits that never reach the wire, calibrated copies.

The linear map is the device file's (layout.py ``Calibration``; docs/device.md "Linear PWM servos":
1000 us retracted, 2000 us extended in the shipped default); PulseMap.to_pulses is the one
place it is computed.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from _pty_helpers import STALLED_S
from hypothesis import given, settings
from hypothesis import strategies as st

from crs_study.device import codec, decoder
from crs_study.device.calibration import PulseMap, write_calibrated_copy
from crs_study.errors import DeviceError, DeviceFileError
from crs_study.geometry.layout import Calibration, device_file_path, load_layout


def test_default_calibration_maps_travel_onto_1000_to_2000_us(layout2d):
    pm = PulseMap.from_layout(layout2d)
    n = layout2d.n_actuators
    assert pm.to_pulses(np.zeros(n)).tolist() == [1000] * n
    assert pm.to_pulses(np.full(n, 9.0)).tolist() == [2000] * n
    assert pm.to_pulses(np.full(n, 4.5)).tolist() == [1500] * n
    # 1 us is 9 mm / 1000 us = 0.009 mm: 0.0046 mm rounds up to 1001 us
    assert pm.to_pulses(np.full(n, 0.0046))[0] == 1001


def test_reversed_servo_runs_from_zero_us_down_to_full_us(layout1d):
    acts = list(layout1d.actuators)
    travel = acts[2].calibration.travel_mm
    acts[2] = replace(acts[2], calibration=Calibration(2100.0, 1100.0, travel))
    pm = PulseMap.from_layout(replace(layout1d, actuators=tuple(acts)))
    setpoints = np.zeros(layout1d.n_actuators)
    setpoints[2] = travel
    assert pm.to_pulses(setpoints)[2] == 1100
    setpoints[2] = 0.25 * travel
    assert pm.to_pulses(setpoints)[2] == 1850
    assert pm.to_mm(pm.to_pulses(setpoints))[2] == pytest.approx(0.25 * travel)


@pytest.mark.parametrize(
    ("index", "value", "match"),
    [
        pytest.param(2, 9.5, r"channel A:3 pixel 2: setpoint 9\.5 mm is outside its calibrated "
                     r"range 0\.\.9 mm", id="above-travel"),
        pytest.param(0, -0.01, r"channel A:1 pixel 0: setpoint -0\.01 mm", id="below-zero"),
        pytest.param(19, np.nan, r"channel A:11 beam 0 start: setpoint nan mm", id="nan"),
        pytest.param(36, np.inf, r"channel B:18 beam 8 end: setpoint inf", id="inf"),
    ],
)
def test_setpoint_outside_range_names_channel_value_and_range(layout2d, index, value, match):
    setpoints = np.zeros(layout2d.n_actuators)
    setpoints[index] = value
    with pytest.raises(DeviceError, match=match):
        PulseMap.from_layout(layout2d).to_pulses(setpoints)


def test_frames_name_the_frame_and_shape_is_checked(layout2d):
    pm = PulseMap.from_layout(layout2d)
    frames = np.zeros((5, layout2d.n_actuators))
    frames[3, 4] = 12.0
    with pytest.raises(DeviceError, match=r"A:5 pixel 4: setpoint 12\.0 mm in frame 3"):
        pm.to_pulses(frames)
    with pytest.raises(DeviceError, match=r"expected 37 values per frame.*\(36,\)"):
        pm.to_pulses(np.zeros(36))


def test_float_noise_within_tolerance_is_clipped_not_refused(layout2d):
    pm = PulseMap.from_layout(layout2d)
    setpoints = np.zeros(layout2d.n_actuators)
    setpoints[0], setpoints[1] = -1e-9, 9.0 + 1e-9
    assert pm.to_pulses(setpoints)[:2].tolist() == [1000, 2000]


def test_pulse_outside_calibrated_range_is_refused_on_the_way_back(layout2d):
    pm = PulseMap.from_layout(layout2d)
    pulses = np.full(layout2d.n_actuators, 1500)
    pulses[10] = 2001
    with pytest.raises(DeviceError, match=r"B:1 pixel 10: pulse width 2001\.0 us is outside "
                       r"its calibrated range 1000\.\.2000 us"):
        pm.to_mm(pulses)


calibrations = st.tuples(
    st.integers(500, 2500), st.integers(500, 2500), st.floats(0.5, 20.0),
).filter(lambda c: abs(c[0] - c[1]) >= 10)


@settings(max_examples=150, deadline=None)
@given(cals=st.lists(calibrations, min_size=7, max_size=7),
       stimulus=st.lists(st.floats(-2.0, 25.0) | st.just(float("nan")), min_size=7, max_size=7),
       shifts=st.lists(st.floats(-0.49, 0.49), min_size=7, max_size=7))
def test_no_setpoint_outside_limits_is_ever_encoded(layout1d, cals, stimulus, shifts):
    # random calibrations (fractional endpoints included) and random stimuli, in and out of range
    acts = tuple(
        replace(a, calibration=Calibration(min(max(zero + dz, 500), 2500),
                                           min(max(full - dz, 500), 2500), travel))
        for a, (zero, full, travel), dz in zip(layout1d.actuators, cals, shifts, strict=True)
    )
    pm = PulseMap.from_layout(replace(layout1d, actuators=acts))
    setpoints = np.array(stimulus)
    low = np.minimum(pm.zero_us, pm.full_us)
    high = np.maximum(pm.zero_us, pm.full_us)
    tol = pm.tolerance_mm
    in_range = bool(np.all((setpoints >= -tol) & (setpoints <= pm.travel_mm + tol)))
    try:
        pulses = pm.to_pulses(setpoints)
    except DeviceError:
        assert not in_range
        return
    assert in_range
    assert np.all((pulses >= low) & (pulses <= high))
    assert np.all((pulses >= codec.PULSE_MIN_US) & (pulses <= codec.PULSE_MAX_US))
    frame = codec.servo_move(zip(pm.servo_id, pulses, strict=True), 50)
    decoded = decoder.decode_frame(frame)
    assert [p for _, p in decoded.positions] == pulses.tolist()
    # quantisation: at most half a microsecond (plus the clip onto a fractional endpoint) off
    fraction = np.clip(setpoints, 0, pm.travel_mm) / pm.travel_mm
    exact = pm.zero_us + (pm.full_us - pm.zero_us) * fraction
    assert np.all(np.abs(pulses - exact) <= 1.0)


@pytest.mark.parametrize("name", ["crs2d", "crs1d"])
def test_the_shipped_device_files_map_travel_onto_their_published_endpoints(name):
    # docs/device.md, "Linear PWM servos": 1000 us fully retracted, 2000 us fully extended; the
    # device files publish that per channel (their [calibration] table), and travel 0 and
    # full travel must land on those very pulse widths, half travel half way
    layout = load_layout(name)
    pm = PulseMap.from_layout(layout)
    cals = [a.calibration for a in layout.actuators]
    travel = np.array([c.travel_mm for c in cals])
    assert {(c.zero_us, c.full_us) for c in cals} == {(1000, 2000)}
    assert pm.to_pulses(np.zeros(len(cals))).tolist() == [c.zero_us for c in cals]
    assert pm.to_pulses(travel).tolist() == [c.full_us for c in cals]
    assert pm.to_pulses(travel / 2).tolist() == [1500] * len(cals)


def test_a_calibrated_copys_endpoints_are_what_its_channels_reach(tmp_path):
    # the endpoints an experimenter found (one fractional, one reversed) are the pulses the
    # channel gets at 0 mm and full travel; a fractional endpoint rounds inside the range
    out = tmp_path / "dev.toml"
    layout = write_calibrated_copy(device_file_path("crs1d"), out,
                                   {"A:1": (1010, 1985), "A:3": (2010.5, 1020)})
    pm = PulseMap.from_layout(layout)
    travel = pm.travel_mm
    assert pm.to_pulses(np.zeros(7))[[0, 2]].tolist() == [1010, 2010]
    assert pm.to_pulses(travel)[[0, 2]].tolist() == [1985, 1020]


def test_every_user_converts_millimetres_through_the_one_map(layout2d, monkeypatch):
    # one mm-to-pulse map (PulseMap.to_pulses): both devices and the wire estimate call it,
    # and the device file's Calibration and the Layout hold no second copy of the formula
    from crs_study.benchmarks.device import PacedPort
    from crs_study.clock import VirtualClock
    from crs_study.device.schedule import wire_plan
    from crs_study.device.serial_device import SerialDevice
    from crs_study.device.serial_port import SerialOptions
    from crs_study.device.simulated import SimulatedDevice
    from crs_study.geometry.layout import Layout

    calls = []
    original = PulseMap.to_pulses

    def counted(self, setpoints_mm):
        calls.append(np.shape(setpoints_mm))
        return original(self, setpoints_mm)

    monkeypatch.setattr(PulseMap, "to_pulses", counted)
    frame = np.full(layout2d.n_actuators, 2.0)
    ports = [PacedPort(c.name, 0.0) for c in layout2d.controllers]
    for device in (SimulatedDevice(layout2d, VirtualClock()),
                   SerialDevice(layout2d, ports, VirtualClock(),
                                SerialOptions(check_battery=False, pace=False))):
        with device:
            calls.clear()
            device.send(frame)
            assert calls == [frame.shape], type(device).__name__
    calls.clear()
    wire_plan(layout2d, np.array([frame, frame]), 15.0)
    assert (2, layout2d.n_actuators) in calls
    for cls, name in ((Calibration, "pulse_us"), (Calibration, "mm"), (Layout, "pulse_us")):
        assert not hasattr(cls, name), f"{cls.__name__}.{name}: a second map"


@settings(max_examples=150, deadline=None)
@given(cal=calibrations, fractions=st.lists(st.floats(0.0, 1.0), min_size=2, max_size=12))
def test_pulses_follow_the_setpoint_and_map_back_within_half_a_microsecond(layout1d, cal,
                                                                             fractions):
    # monotone in the setpoint (rising for zero_us < full_us, falling when reversed), and the
    # inverse map returns each setpoint to within half a microsecond's worth of stroke
    zero, full, travel = cal
    acts = tuple(replace(a, calibration=Calibration(zero, full, travel))
                 for a in layout1d.actuators)
    pm = PulseMap.from_layout(replace(layout1d, actuators=acts))
    mm = np.sort(np.array(fractions)) * travel
    pulses = pm.to_pulses(np.repeat(mm[:, None], 7, axis=1))[:, 0]
    steps = np.diff(pulses) * np.sign(full - zero)
    assert np.all(steps >= 0)
    back = pm.to_mm(np.repeat(pulses[:, None], 7, axis=1))[:, 0]
    assert np.all(np.abs(back - mm) <= 0.5 * travel / abs(full - zero) + 1e-9)


def test_calibrated_copy_replaces_only_the_calibration_table(tmp_path):
    source = device_file_path("crs2d")
    out = tmp_path / "my-crs2d.toml"
    layout = write_calibrated_copy(source, out, {"A:3": (1010, 1985), "B:10": (2010.5, 1020)})
    by_channel = {f"{a.controller}:{a.channel}": a.calibration for a in layout.actuators}
    assert (by_channel["A:3"].zero_us, by_channel["A:3"].full_us) == (1010, 1985)
    assert (by_channel["B:10"].zero_us, by_channel["B:10"].full_us) == (2010.5, 1020)
    assert (by_channel["A:4"].zero_us, by_channel["A:4"].full_us) == (1000, 2000)
    original = load_layout("crs2d")
    assert layout.pixel_xy.tolist() == original.pixel_xy.tolist()
    assert [b.pixels for b in layout.beams] == [b.pixels for b in original.beams]
    text = out.read_text()
    assert text.count("[calibration]") == 1
    assert source.read_text().split("[calibration]")[0] in text


def test_calibrated_copy_never_overwrites_silently(tmp_path):
    out = tmp_path / "dev.toml"
    out.write_text("keep me")
    with pytest.raises(DeviceFileError, match="already exists"):
        write_calibrated_copy(device_file_path("crs1d"), out, {})
    assert out.read_text() == "keep me"
    write_calibrated_copy(device_file_path("crs1d"), out, {"A:1": (990, 2010)}, overwrite=True)
    with pytest.raises(DeviceFileError, match="refusing to overwrite the device file"):
        write_calibrated_copy(out, out, {}, overwrite=True)


def test_calibrated_copy_with_an_impossible_endpoint_is_refused_and_not_left_behind(tmp_path):
    out = tmp_path / "dev.toml"
    with pytest.raises(DeviceFileError, match="full_us"):
        write_calibrated_copy(device_file_path("crs1d"), out, {"A:1": (1000, 2600)})
    assert not out.exists() and list(tmp_path.iterdir()) == []


def _reference_to_pulses(pm: PulseMap, mm: np.ndarray) -> np.ndarray:
    """to_pulses as first written (np.clip and the formula term by term): the fast version
    must agree bit for bit, rounding ties included, or a byte on the wire would change."""
    mm = np.clip(mm, 0.0, pm.travel_mm)
    pulses = np.rint(pm.zero_us + (pm.full_us - pm.zero_us) * mm / pm.travel_mm)
    return np.clip(pulses, pm.pulse_low, pm.pulse_high).astype(np.int64)


@settings(max_examples=150, deadline=None)
@given(cals=st.lists(calibrations, min_size=7, max_size=7),
       shifts=st.just([0.0] * 7) | st.lists(st.floats(-0.49, 0.49), min_size=7, max_size=7),
       fractions=st.lists(st.lists(st.floats(0.0, 1.0) | st.sampled_from([0.0, 0.5, 1.0]),
                                   min_size=7, max_size=7), min_size=1, max_size=4),
       halves=st.booleans())
def test_fast_to_pulses_matches_the_reference_arithmetic(layout1d, cals, shifts, fractions,
                                                         halves):
    acts = tuple(
        replace(a, calibration=Calibration(min(max(zero + dz, 500), 2500),
                                           min(max(full - dz, 500), 2500), travel))
        for a, (zero, full, travel), dz in zip(layout1d.actuators, cals, shifts, strict=True)
    )
    pm = PulseMap.from_layout(replace(layout1d, actuators=acts))
    mm = np.array(fractions) * pm.travel_mm
    if halves:  # aim at rounding ties: setpoints whose exact pulse is k + 0.5 us
        target = np.floor(pm.zero_us + (pm.full_us - pm.zero_us) * np.array(fractions)) + 0.5
        mm = (target - pm.zero_us) * pm.travel_mm / (pm.full_us - pm.zero_us)
        mm = np.clip(mm, -pm.tolerance_mm / 2, pm.travel_mm + pm.tolerance_mm / 2)
    np.testing.assert_array_equal(pm.to_pulses(mm), _reference_to_pulses(pm, mm))
    np.testing.assert_array_equal(pm.to_pulses(mm[0]), _reference_to_pulses(pm, mm[0]))


@settings(max_examples=25, deadline=None)
@given(cals=st.lists(calibrations, min_size=7, max_size=7),
       frames=st.lists(st.lists(st.floats(-2.0, 25.0) | st.just(float("nan")), min_size=7,
                                max_size=7), min_size=1, max_size=6))
def test_no_pulse_outside_limits_reaches_either_devices_wire(layout1d, cals, frames):
    # the whole path, not only PulseMap: SerialDevice's writer thread (bytes captured) and
    # SimulatedDevice's boards (bytes decoded) under random, reversed calibrations; every
    # SERVO_MOVE that reaches a wire, the neutral pose on close included, stays in range
    from crs_study.benchmarks.device import PacedPort
    from crs_study.clock import VirtualClock
    from crs_study.device.serial_device import SerialDevice
    from crs_study.device.serial_port import SerialOptions
    from crs_study.device.simulated import SimulatedDevice

    acts = tuple(replace(a, calibration=Calibration(zero, full, travel))
                 for a, (zero, full, travel) in zip(layout1d.actuators, cals, strict=True))
    layout = replace(layout1d, actuators=acts)
    low = {a.channel: min(a.calibration.zero_us, a.calibration.full_us) for a in acts}
    high = {a.channel: max(a.calibration.zero_us, a.calibration.full_us) for a in acts}
    port = PacedPort("capture", 0.0)  # keeps the bytes, no wire time
    serial_device = SerialDevice(layout, [port], VirtualClock(), SerialOptions(
        check_battery=False, pace=False, refresh_s=0.0))
    sim_device = SimulatedDevice(layout, VirtualClock(), record=True)
    for device in (serial_device, sim_device):
        with device:
            for setpoints in frames:
                try:
                    device.send(np.array(setpoints))
                except DeviceError:
                    pass  # refused: nothing of it may reach the wire (checked below)
                device.clock.sleep(0.07)
                if device is serial_device:
                    assert device.wait_sent(STALLED_S)  # every accepted frame written, none merged
    wire, skipped = decoder.decode_all(bytes(port.data))
    received = [f.message for f in wire] + [r.message for r in sim_device.boards[0].received]
    moves = [m for m in received if isinstance(m, codec.ServoMove)]
    assert skipped == [] and sum(m.time_ms == 500 for m in moves) == 2  # both went to neutral
    for move in moves:
        for channel, pulse in move.positions:
            assert low[channel] <= pulse <= high[channel], (channel, pulse)
