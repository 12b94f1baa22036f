"""Tests for crs_study.geometry.layout: the shipped device files, one-line errors for bad ones."""

from __future__ import annotations

import copy
import tomllib
from collections import Counter

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from crs_study.errors import DeviceFileError
from crs_study.geometry.layout import device_file_path, layout_from_dict, load_layout


def _data(name: str) -> dict:
    return tomllib.loads(device_file_path(name).read_text(encoding="utf-8"))


def test_published_2d_device(layout2d):
    assert layout2d.n_pixels == 19 and len(layout2d.beams) == 9
    assert layout2d.n_actuators == 37 and len(layout2d.boundary_actuators) == 18
    assert [c.name for c in layout2d.controllers] == ["A", "B"]
    assert sorted(Counter(len(b.pixels) for b in layout2d.beams).items()) == [(4, 6), (5, 3)]
    # 4-5-4 lines in each of the three directions
    directions = Counter(round(float(np.degrees(np.arctan2(b.direction[1], b.direction[0]))) % 180)
                         for b in layout2d.beams)
    assert set(directions) == {0, 60, 120}
    assert sorted(directions.values()) == [3, 3, 3]
    for beam in layout2d.beams:
        steps = np.diff(layout2d.pixel_xy[list(beam.pixels)], axis=0)
        np.testing.assert_allclose(np.hypot(*steps.T), 30.0)
        # clamps one pitch beyond the end pixels
        assert beam.straight_length == pytest.approx(30.0 * (len(beam.pixels) - 1 + 2))
    channels = [(a.controller, a.channel) for a in layout2d.actuators]
    assert len(set(channels)) == 37
    assert layout2d.travel_mm == 9.0 and layout2d.beam_section.width_mm == 1.0
    assert layout2d.beam_section.youngs_modulus_mpa == 193e3


def test_published_1d_device(layout1d):
    assert layout1d.n_pixels == 5 and len(layout1d.beams) == 1 and layout1d.n_actuators == 7
    np.testing.assert_allclose(layout1d.pixel_xy[:, 0], [0, 30, 60, 90, 120])
    assert layout1d.beams[0].start == (-30.0, 0.0) and layout1d.beams[0].end == (150.0, 0.0)
    assert layout1d.beam_section.thickness_mm == 0.1 and layout1d.beam_section.width_mm == 4.0


def _mutated(name, change):
    data = copy.deepcopy(_data(name))
    change(data)
    return data


def _set(path, value):
    def change(data):
        node = data
        for key in path[:-1]:
            node = node[key]
        node[path[-1]] = value
    return change


@pytest.mark.parametrize(("change", "message"), [
    pytest.param(_set(["geometry", "pich_mm"], 30.0),
                 r"crs2d: geometry: unknown key 'pich_mm' \(valid keys: ", id="unknown-key"),
    pytest.param(_set(["geometry", "pitch_mm"], "30"),
                 r"crs2d: geometry.pitch_mm: expected a number, got '30'", id="wrong-type"),
    pytest.param(_set(["geometry", "pitch_mm"], -3.0),
                 r"geometry.pitch_mm: expected a number >= 1, got -3.0", id="negative-pitch"),
    pytest.param(_set(["geometry", "pitch_mm"], 1e300),
                 r"geometry.pitch_mm: expected a number <= 1000, got 1e\+300", id="huge-pitch"),
    pytest.param(_set(["beam", "thickness_mm"], 1e-300),
                 r"beam.thickness_mm: expected a number >= 0.001, got 1e-300", id="thin-beam"),
    pytest.param(_set(["geometry", "end_margin_pitch"], 0.123),
                 r"geometry.end_margin_pitch: on a hexagonal display the clamps must fall on "
                 r"the fabric's mesh", id="margin-off-mesh"),
    pytest.param(lambda d: d["geometry"]["beams"].__setitem__(1, [6, 5, 4, 3]),
                 r"geometry.beams\[1\]: the same pixels as beams\[0\]", id="duplicate-beam"),
    pytest.param(_set(["calibration", "A:03"], {"zero_us": 1000, "full_us": 1900}),
                 None, id="padded-calibration-key"),
    pytest.param(_set(["calibration", "A:24"], {"zero_us": 1000, "full_us": 1900}),
                 r"calibration.A:24: no pixel or boundary servo is on channel A:24",
                 id="calibration-of-an-unused-channel"),
    pytest.param(lambda d: d["geometry"]["pixels"].__setitem__(1, [0, -2]),
                 r"geometry.pixels\[1\]: duplicate pixel \[0, -2\] \(same as pixels\[0\]\)",
                 id="duplicate-pixel"),
    pytest.param(lambda d: d["geometry"]["beams"].__setitem__(0, [3, 99]),
                 r"geometry.beams\[0\]: expected pixel indices 0..18, got 99",
                 id="beam-through-no-pixel"),
    pytest.param(lambda d: d["geometry"]["beams"].__setitem__(0, [3, 5]),
                 r"geometry.beams\[0\]: pixels \[3, 5\] are not consecutive neighbours",
                 id="beam-non-neighbours"),
    pytest.param(lambda d: d["geometry"]["beams"].__setitem__(0, [3]),
                 r"geometry.beams\[0\]: expected a list of at least 2 pixel indices, got \[3\]",
                 id="beam-one-pixel"),
    pytest.param(lambda d: d["channels"]["pixels"].__setitem__(0, "C:1"),
                 r"channels.pixels\[0\]: unknown controller 'C' in 'C:1'", id="bad-controller"),
    pytest.param(lambda d: d["channels"]["pixels"].__setitem__(0, "A1"),
                 r"channels.pixels\[0\]: expected \"CONTROLLER:CHANNEL\" like \"A:1\", got 'A1'",
                 id="bad-channel-ref"),
    pytest.param(lambda d: d["channels"]["pixels"].__setitem__(0, "A:25"),
                 r"channels.pixels\[0\]: channel 25 is outside controller 'A''s channels 1..24",
                 id="channel-out-of-range"),
    pytest.param(lambda d: d["channels"]["pixels"].__setitem__(1, "A:1"),
                 r"channels.pixels\[1\]: channel 'A:1' is already used by pixel 0",
                 id="duplicate-channel"),
    pytest.param(_set(["calibration", "default"], {"zero_us": 400, "full_us": 2000}),
                 r"calibration.default.zero_us: expected a number >= 500, got 400",
                 id="pulse-below-500"),
    pytest.param(_set(["calibration", "A:3"], {"zero_us": 1000, "full_us": 2600}),
                 r"calibration.A:3.full_us: expected a number <= 2500, got 2600",
                 id="pulse-above-2500"),
    pytest.param(lambda d: d["channels"].__setitem__("pixels", d["channels"]["pixels"][:-1]),
                 r"channels.pixels: expected 19 channels \(one per pixel\), got 18",
                 id="missing-channel"),
    pytest.param(lambda d: d.pop("skin"), r"crs2d: missing required key 'skin'", id="missing"),
])
def test_malformed_device_file_is_a_one_line_error(change, message):
    if message is None:  # accepted
        layout_from_dict(_mutated("crs2d", change), source="crs2d")
        return
    with pytest.raises(DeviceFileError, match=message) as info:
        layout_from_dict(_mutated("crs2d", change), source="crs2d")
    assert "\n" not in str(info.value)


def test_errors_name_the_file(tmp_path):
    path = tmp_path / "mine.toml"
    text = device_file_path("crs1d").read_text().replace("pitch_mm = 30.0", "pitch_mm = 'wide'")
    path.write_text(text)
    with pytest.raises(DeviceFileError, match=rf"{path}: geometry.pitch_mm: expected a number, "
                                              r"got 'wide'"):
        load_layout(path)
    with pytest.raises(DeviceFileError, match=r"nothere.toml: no such file"):
        load_layout(tmp_path / "nothere.toml")
    path.write_text("name = ")
    with pytest.raises(DeviceFileError, match=r"mine.toml: not valid TOML"):
        load_layout(path)


def _paths(node, prefix=()):
    """Every (path, value) of leaves and containers in a parsed TOML document."""
    yield prefix, node
    if isinstance(node, dict):
        for key, value in node.items():
            yield from _paths(value, (*prefix, key))
    elif isinstance(node, list):
        for i, value in enumerate(node):
            yield from _paths(value, (*prefix, i))


ANY_VALUE = st.one_of(
    st.none(), st.booleans(), st.integers(-5, 3000), st.floats(allow_nan=True),
    st.text(max_size=6), st.lists(st.integers(-3, 30), max_size=4),
    st.dictionaries(st.text(max_size=4), st.integers(), max_size=2),
)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(name=st.sampled_from(["crs2d", "crs1d"]), data=st.data())
def test_random_mutations_load_or_raise_device_file_error(name, data):
    document = copy.deepcopy(_data(name))
    for _ in range(data.draw(st.integers(1, 3))):
        paths = [p for p, _ in _paths(document) if p]
        path = data.draw(st.sampled_from(paths))
        parent = document
        for key in path[:-1]:
            parent = parent[key]
        action = data.draw(st.sampled_from(["replace", "delete", "add"]))
        if action == "delete":
            del parent[path[-1]]
        elif action == "add" and isinstance(parent, dict):
            parent[data.draw(st.text(min_size=1, max_size=6))] = data.draw(ANY_VALUE)
        else:
            parent[path[-1]] = data.draw(ANY_VALUE)
    try:
        layout_from_dict(document, source=name)
    except DeviceFileError as exc:
        assert "\n" not in str(exc)


@pytest.mark.parametrize("key", ["A:03", "A:3"])
def test_a_calibration_override_reaches_its_channel_however_it_is_written(key):
    """'A:03' passed the check but the lookup used 'A:3': the channel kept the default."""
    layout = layout_from_dict(
        _mutated("crs2d", _set(["calibration", key], {"zero_us": 1100, "full_us": 1900})),
        source="crs2d")
    pixel = next(a for a in layout.actuators if (a.controller, a.channel) == ("A", 3))
    assert (pixel.calibration.zero_us, pixel.calibration.full_us) == (1100, 1900)


def test_the_same_channel_calibrated_twice_is_refused():
    def change(d):
        d["calibration"]["A:3"] = {"zero_us": 1100, "full_us": 1900}
        d["calibration"]["A:03"] = {"zero_us": 1200, "full_us": 1900}

    with pytest.raises(DeviceFileError, match="channel A:3 is calibrated twice"):
        layout_from_dict(_mutated("crs2d", change), source="crs2d")


@pytest.mark.parametrize("margin, mesh", [(1.0, 8), (0.5, 8), (0.3, 10), (1 / 3, 9), (0.35, 20)])
def test_the_fabric_meshes_any_clamp_margin_on_the_lattice(margin, mesh):
    """Clamps off the fabric's mesh made every 2D beam model fail (and a dry-run guess)."""
    from crs_study.display import get_model
    from crs_study.geometry.layout import fabric_mesh_for_margin

    assert fabric_mesh_for_margin(margin) == mesh
    layout = layout_from_dict(_mutated("crs2d", _set(["geometry", "end_margin_pitch"], margin)),
                              source="crs2d")
    model = get_model("beam", layout)
    assert model.fabric.h == pytest.approx(layout.pitch_mm / mesh)
    heights = model.surface(layout.neutral_setpoints(), layout.pixel_xy)
    assert np.allclose(heights, 0.0)
