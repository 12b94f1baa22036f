"""Measurement protocols (crs_study.quality.measurement_protocol): strict TOML, the plan of
captures, bump centres X_i over the region as Eqs. 1 and 5 take their expectation."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from crs_study.errors import ProtocolError
from crs_study.paths import data_dir
from crs_study.quality.measurement_protocol import (
    load_measurement_protocol,
    measurement_protocol_from_text,
    plan_captures,
    plan_sha256,
    region_polygon,
    resolve_measurement_protocol,
    sample_centres,
)

SHIPPED = resolve_measurement_protocol("crs2d").read_text()


def test_the_shipped_protocols_read_and_plan():
    for name, pixels in (("crs1d", 5), ("crs2d", 19)):
        protocol = load_measurement_protocol(name)
        layout = protocol.layout()
        assert layout.n_pixels == pixels
        plan = plan_captures(protocol, layout)
        per_block = 1 + protocol.shapes * len(protocol.diameters_mm)
        assert len(plan) == per_block * len(protocol.conditions)
        assert [c.name for c in plan if c.kind == "reference"] == ["ref-pixel-only", "ref-crs"]
        assert [c.kind for c in plan[:per_block]] == ["reference"] + ["shape"] * (per_block - 1)
        assert [c.name for c in plan if c.kind == "shape"][:2] == ["shape-0001", "shape-0002"]


def test_the_shipped_protocols_ship_in_the_wheel():
    """pyproject's package-data patterns cover the measurement protocols."""
    import tomllib
    from pathlib import Path

    patterns = tomllib.loads((Path(__file__).resolve().parents[1] / "pyproject.toml"
                              ).read_text())["tool"]["setuptools"]["package-data"]["crs_study"]
    for path in (data_dir() / "measurements").iterdir():
        relative = path.relative_to(data_dir().parent)
        assert any(relative.match(p) for p in patterns), f"{relative} would not ship"


def test_the_plan_is_a_pure_function_of_the_protocol():
    protocol = load_measurement_protocol("crs2d")
    layout = protocol.layout()
    first, second = plan_captures(protocol, layout), plan_captures(protocol, layout)
    assert first == second and plan_sha256(first) == plan_sha256(second)
    other = measurement_protocol_from_text(SHIPPED.replace("seed = 29", "seed = 30"), "x.toml")
    assert plan_sha256(plan_captures(other, layout)) != plan_sha256(first)


def test_every_centre_lies_in_the_central_cell():
    """Eq. 5's expectation over one cell: X_i within d/sqrt(3) of the central pixel (hex)."""
    protocol = load_measurement_protocol("crs2d")
    layout = protocol.layout()
    for capture in plan_captures(protocol, layout):
        if capture.kind == "shape":
            assert math.hypot(*capture.centre_mm) <= layout.pitch_mm / math.sqrt(3) + 1e-9
            nearest = np.argmin(np.hypot(*(layout.pixel_xy - capture.centre_mm).T))
            assert np.allclose(layout.pixel_xy[nearest], 0.0)  # the cell of the centre pixel


@pytest.mark.parametrize(("edit", "message"), [
    pytest.param(("seed = 29", "seed = 29\nsede = 1"),
                 r"x.toml:\d+: unknown key 'sede' .*did you mean 'seed'", id="stray-key"),
    pytest.param(("shapes = 15", "shapes = 1"), r"shapes: expected a whole number >= 2",
                 id="one-shape"),
    pytest.param(('crs = "beam"', 'crs = "bem"'), r"models.crs: expected one of", id="model"),
    pytest.param(('crs = "beam"', ''), r"models: missing required key 'crs'",
                 id="model-missing"),
    pytest.param(("[90.0, 120.0]", "[90.0, 20.0]"),
                 r"diameters_mm: 20 mm gives d/l = 1.5 on crs2d", id="d-over-l"),
    pytest.param(("[90.0, 120.0]", "[90.0, 90.0]"), r"expected one or more different",
                 id="same-diameter"),
    pytest.param(('"pixel-only", "crs"]', '"pixel-only", "cr"]'), r"conditions: expected each",
                 id="condition"),
    pytest.param(("height_mm = 5.0", "height_mm = 12.0"),
                 r"height_mm: expected at most the pixels' travel", id="travel"),
    pytest.param(("hold_s = 2.0", "hold_s = 0"), r"timing.hold_s: expected a number > 0",
                 id="hold"),
    pytest.param(('region = "cell"', 'region = "disc"'), r"region: expected one of",
                 id="region"),
    pytest.param(("seed = 29", "seed = 29\n[analysis]\nregistration = \"affine\""),
                 r"analysis.registration: expected one of \['rigid', 'similarity'\]",
                 id="registration"),
    pytest.param(("seed = 29", "seed = 29\n[analysis]\ntolerance_DP = 0.1"),
                 r"analysis: unknown key 'tolerance_DP'", id="analysis-key"),
    pytest.param(('device = "crs2d"', 'device = "nowhere.toml"'),
                 r"x.toml:\d+: device: nowhere.toml", id="device-file"),
])
def test_bad_protocols_are_one_line_errors(edit, message):
    old, new = edit
    assert old in SHIPPED
    with pytest.raises(ProtocolError, match=message) as caught:
        measurement_protocol_from_text(SHIPPED.replace(old, new), "x.toml")
    assert "\n" not in str(caught.value)


def test_a_name_that_is_not_shipped_is_refused():
    with pytest.raises(ProtocolError, match="not a shipped measurement protocol"):
        load_measurement_protocol("crs3d")
    with pytest.raises(ProtocolError, match="cannot read the measurement protocol"):
        load_measurement_protocol("mine/none.toml")


@given(st.integers(2, 40), st.integers(0, 2**32), st.sampled_from(["cell", "hull"]),
       st.sampled_from(["crs1d", "crs2d"]))
def test_random_centres_fall_inside_the_region(n, seed, region, device):
    from scipy.spatial import Delaunay

    from crs_study.geometry.layout import load_layout

    layout = load_layout(device)
    polygon = region_polygon(layout, region)
    centres = sample_centres(polygon, n, "random", np.random.default_rng(seed))
    assert centres.shape == (n, 2)
    if len(polygon) == 2:
        assert np.all((centres[:, 0] >= polygon[:, 0].min()) &
                      (centres[:, 0] <= polygon[:, 0].max()))
    else:
        assert np.all(Delaunay(polygon).find_simplex(centres, tol=1e-9) >= 0)


def test_grid_centres_are_a_midpoint_rule():
    """On a segment the grid's mean of |X - x_c| is the exact d/4 of Eq. 1's pixel-only
    theory (midpoint rule, exact on each linear half)."""
    from crs_study.geometry.layout import load_layout

    layout = load_layout("crs1d")
    polygon = region_polygon(layout, "cell")
    centres = sample_centres(polygon, 20, "grid", np.random.default_rng(0))
    assert np.mean(np.abs(centres[:, 0] - 60.0)) == pytest.approx(30.0 / 4)
    hexagon = sample_centres(region_polygon(load_layout("crs2d"), "cell"), 40, "grid",
                             np.random.default_rng(0))
    assert 30 <= len(hexagon) <= 50
    assert np.allclose(hexagon.mean(axis=0), 0.0, atol=1e-9)
