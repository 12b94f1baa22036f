"""A protocol against its device, as structured findings (crs_study/protocol/feasibility.py).

The messages of each check are tested where a protocol is loaded (tests/test_protocol.py,
test_levels.py); here: the findings themselves (severity, key, line, the numbers behind a
message) and that a failed check is a finding, not an exception, until it is raised.
"""

from __future__ import annotations

import copy
import json
import math

import pytest
from test_protocol import SHIPPED, edited, shipped_data, write

from crs_study.errors import ProtocolError
from crs_study.protocol import Feasibility, check_feasibility, load_protocol


def line_of(path, key: str) -> int:
    return next(i for i, t in enumerate(path.read_text().splitlines(), 1)
                if t.startswith(f"{key} ="))


def test_the_shipped_protocol_passes_every_check_with_its_numbers():
    protocol = load_protocol(SHIPPED)
    result = check_feasibility(protocol)
    assert isinstance(result, Feasibility) and result.feasible and result.error() is None
    assert result.passed == protocol.checks
    assert {f.severity for f in result.findings} == {"ok"}
    by_key = {f.key_path: f for f in result.findings}
    wire = by_key["stimulus.frame_rate_hz"]
    # 19 servos on the busier board: 3 * 19 + 7 = 64 bytes of 10 bits at 9600 baud
    # (docs/device.md): 66.7 ms, so 15 full frames a second
    assert wire.values["full_frame_wire_ms"] == pytest.approx(64 * 10 / 9600 * 1e3)
    assert wire.values["max_frame_rate_hz"] == pytest.approx(15.0)
    assert wire.line == line_of(SHIPPED, "frame_rate_hz")
    curvature = by_key["stimulus.bump_height_mm"]
    # Eq. 7: 2 pi^2 z_f / l^2 at z_f = 5 mm, l = 90 mm; yield 2 sigma_y / (E t)
    assert curvature.values["curvature_per_mm"] == pytest.approx(2 * math.pi**2 * 5 / 90**2)
    assert curvature.values["yield_curvature_per_mm"] == pytest.approx(2 * 965 / (193e3 * 0.15))
    frame = result.to_frame()
    assert list(frame.columns) == ["severity", "key_path", "line", "message", "values"]
    assert len(frame) == len(result.findings)
    assert json.loads(result.to_json())["feasible"] is True


def test_a_failed_check_is_the_last_finding_and_raises_only_when_asked(tmp_path):
    path = write(tmp_path, edited(stimulus__frame_rate_hz=20.0))
    protocol = load_protocol(path, check_device=False)
    result = check_feasibility(protocol)  # no exception
    assert not result.feasible and len(result.errors) == 1
    failed = result.findings[-1]
    assert failed.severity == "error" and failed.key_path == "stimulus.frame_rate_hz"
    assert failed.line == line_of(path, "frame_rate_hz")
    assert failed.values["frame_rate_hz"] == 20.0
    error = result.error()
    assert isinstance(error, ProtocolError) and error.key_path == "stimulus.frame_rate_hz"
    assert str(error) == f"{path}:{failed.line}: stimulus.frame_rate_hz: {failed.message}"
    assert json.loads(result.to_json())["findings"][-1]["severity"] == "error"
    # checks before the failure passed; nothing after it was checked
    assert [f.severity for f in result.findings[:-1]] == ["ok", "ok"]


@pytest.mark.parametrize("changes, key", [
    pytest.param({"stimulus__bump_diameter_mm": 20.0}, "stimulus.bump_height_mm", id="yield"),
    pytest.param({"stimulus__digit_width_pitch": 4.0}, "stimulus.digit_width_pitch",
                 id="outside-width"),
    pytest.param({"stimulus__bump_height_mm": 9.5}, "stimulus.bump_height_mm", id="travel"),
])
def test_curvature_and_pixel_area_are_checked_once(tmp_path, changes, key):
    # one implementation: the failure is found once, with the key at fault
    result = check_feasibility(load_protocol(write(tmp_path, edited(**changes)),
                                             check_device=False))
    assert [f.key_path for f in result.errors] == [key]
    assert result.findings[-1] is result.errors[0]


def test_a_failed_level_is_named_by_its_level(tmp_path):
    data = copy.deepcopy(shipped_data())
    for key in ("digit_height_pitch", "digit_width_pitch"):
        del data["stimulus"][key]
    data["levels"] = {"parameter": "digit_height_pitch", "values": [0.5, 3.4],
                      "width_to_height": 0.605}
    path = write(tmp_path, data)
    result = check_feasibility(load_protocol(path, check_device=False))
    (failed,) = result.errors
    assert failed.key_path == "levels.values[1]" and failed.line == line_of(path, "values")
    assert failed.message.startswith("at digit_height_pitch = 3.4: stimulus.digit_height_pitch:"
                                     " the bump centre leaves the pixel area")
    # the levels' lines come once every level passed: before the failure, only the device's
    assert [f.key_path for f in result.findings[:-1]] == ["study.device",
                                                          "study.consent_form_version"]


def test_a_device_that_does_not_load_is_a_finding(tmp_path):
    (tmp_path / "device.toml").write_text("name = 1\n")
    protocol = load_protocol(write(tmp_path, edited()), check_device=False)
    from dataclasses import replace

    result = check_feasibility(replace(protocol, device=str(tmp_path / "device.toml")))
    (failed,) = result.findings
    assert failed.severity == "error" and failed.key_path == "study.device"
    assert "device.toml" in failed.message
