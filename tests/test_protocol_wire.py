"""A protocol's stimuli on the wire (crs_study/protocol/wire.py): one function for what
``validate`` and ``device check`` both report, so the two can no longer disagree."""

from __future__ import annotations

import json

import numpy as np
import pytest

from crs_study.cli import main
from crs_study.device.schedule import wire_plan
from crs_study.paths import shipped_file
from crs_study.protocol import load_protocol, wire_budget
from crs_study.rendering.feed_cap import WireSlack
from crs_study.rendering.frames import render_frames
from crs_study.rendering.render import Renderer
from crs_study.stimuli.stimulus import make_stimulus

PILOT = shipped_file("protocols/pilot.toml")
PSYCHOMETRIC = shipped_file("protocols/digit_size_psychometric.toml")


def test_full_frames_are_the_published_frame_sizes():
    budget = wire_budget(load_protocol(PILOT))
    # docs/device.md: SERVO_MOVE is 3 n + 7 bytes; crs2d has 19 channels on A and 18 on B;
    # 10 bits a byte at 9600 baud
    assert budget.full_frame_bytes == (3 * 19 + 7) + (3 * 18 + 7) == 125
    assert budget.full_frame_busiest_controller_ms == pytest.approx(64 * 10 / 9600 * 1e3)
    assert budget.full_frame_max_rate_hz == pytest.approx(15.0)
    assert budget.full_frame_budget_percent == pytest.approx(100.0)  # 15 frames/s exactly
    assert [c.condition for c in budget.conditions] == ["pixel-only", "crs"]


def test_each_condition_sums_the_wire_plans_of_its_stimuli():
    protocol = load_protocol(PILOT)
    layout = protocol.layout()
    budget = wire_budget(protocol, deadband_us=2, refresh_s=0.5)
    crs = budget.condition("crs")
    # the frames a session on a device with this dead-band sends (the cap leaves it room)
    plans = [wire_plan(layout, render_frames(make_stimulus(protocol, layout, d),
                                             Renderer(layout, "crs", wire=WireSlack(2))),
                       protocol.frame_rate_hz, deadband_us=2, refresh_s=0.5)
             for d in protocol.symbols]
    assert crs.frames == sum(p.n_frames for p in plans)
    assert crs.mean_bytes_per_frame == pytest.approx(
        sum(p.changed_bytes.sum() for p in plans) / crs.frames)
    assert crs.busiest_frame_bytes == max(p.changed_bytes[1:].max() for p in plans)
    assert crs.rate_bound_hz == min(p.rate_bound_hz for p in plans)
    assert crs.latency_ms_max == pytest.approx(
        1e3 * max(p.latency_changed_s.max() for p in plans))
    assert (budget.deadband_us, budget.refresh_s) == (2, 0.5)
    frame = budget.to_frame()
    assert list(frame["condition"]) == ["pixel-only", "crs"]
    assert json.loads(budget.to_json())["conditions"][1]["frames"] == crs.frames


def test_the_budget_renders_for_the_dead_band_it_plans():
    # a wider dead-band moves the CRS frames (the cap's room, the feeds' rest floor): the
    # estimate must plan the frames a session on that device sends, not the default's
    protocol = load_protocol(PILOT)
    layout = protocol.layout()
    wide = wire_budget(protocol, deadband_us=30).condition("crs")
    frames = [render_frames(make_stimulus(protocol, layout, d),
                            Renderer(layout, "crs", wire=WireSlack(30))) for d in protocol.symbols]
    default = [render_frames(make_stimulus(protocol, layout, d), Renderer(layout, "crs"))
               for d in protocol.symbols]
    plans = [wire_plan(layout, f, protocol.frame_rate_hz, deadband_us=30) for f in frames]
    others = [wire_plan(layout, f, protocol.frame_rate_hz, deadband_us=30) for f in default]
    bytes_of = [sum(int(p.changed_bytes.sum()) for p in ps) for ps in (plans, others)]
    assert bytes_of[0] != bytes_of[1]  # the two renderings differ on the wire
    assert wide.mean_bytes_per_frame == pytest.approx(bytes_of[0] / wide.frames)


def test_validate_and_device_check_report_the_same_budget(capsys):
    assert main(["validate", str(PILOT), "--json"]) == 0
    validated = json.loads(capsys.readouterr().out)["wire"]["changed_only"]
    assert main(["device", "check", "--device", "sim://", "--protocol", str(PILOT),
                 "--json"]) == 0
    checked = json.loads(capsys.readouterr().out)["protocol"]
    for condition in ("pixel-only", "crs"):
        assert validated[condition]["max_rate_hz"] == checked[condition]["changed_only_rate_hz"]
        assert validated[condition]["median_latency_ms"] == \
            checked[condition]["latency_ms_median"]


def test_every_level_goes_on_the_wire():
    # device check planned the first level only before the two were one function
    protocol = load_protocol(PSYCHOMETRIC)
    layout = protocol.layout()
    frames = sum(make_stimulus(protocol, layout, d, v).n_frames
                 for v in protocol.level_values for d in protocol.symbols)
    budget = wire_budget(protocol)
    assert all(c.frames == frames for c in budget.conditions)
    first_only = sum(make_stimulus(protocol, layout, d, protocol.level_values[0]).n_frames
                     for d in protocol.symbols)
    assert frames > first_only
    assert np.isfinite([c.latency_ms_median for c in budget.conditions]).all()
