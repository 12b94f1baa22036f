"""Beam networks and the membrane fabric (crs_study.display.network)."""

from __future__ import annotations

import tomllib

import numpy as np
import pytest

from crs_study.display import get_model
from crs_study.display.network import BeamProfiles, Fabric
from crs_study.errors import DisplayModelError
from crs_study.geometry.layout import device_file_path, layout_from_dict, load_layout
from crs_study.rendering.render import Renderer
from crs_study.stimuli.targets import Bump


@pytest.fixture(scope="module")
def layout():
    return load_layout("crs2d")


def random_profiles(layout, seed=0) -> BeamProfiles:
    """Smooth made-up beam shapes, zero at the clamps, equal at shared pixels not required."""
    rng = np.random.default_rng(seed)
    spans = np.array([b.straight_length for b in layout.beams])
    amp = rng.uniform(0.5, 3.0, len(spans))

    def evaluate(beam, s):
        return amp[beam] * np.sin(np.pi * s / spans[beam]) ** 2

    zeros = np.zeros(len(spans))
    return BeamProfiles(spans, evaluate, zeros, zeros, zeros, zeros)


def test_membrane_is_discrete_harmonic_at_free_nodes(layout):
    """Linear FE Laplace on equilateral triangles: 6 z_i = sum of the 6 neighbours."""
    fabric = Fabric(layout, 8)
    z = fabric.node_heights(random_profiles(layout))
    grid = np.full(fabric.shape, np.nan)
    grid[fabric.index >= 0] = z[fabric.index[fabric.index >= 0]]
    q, r = np.nonzero(np.isin(fabric.index, fabric.free))
    neighbours = sum(grid[q + dq, r + dr] for dq, dr in
                     ((1, 0), (-1, 0), (0, 1), (0, -1), (1, -1), (-1, 1)))
    np.testing.assert_allclose(6 * grid[q, r], neighbours, atol=1e-10)


def test_surface_follows_the_beams_and_obeys_the_maximum_principle(layout):
    """Beams consistent at the shared pixels (spline network of random pixel heights)."""
    setpoints = np.zeros(layout.n_actuators)
    setpoints[: layout.n_pixels] = np.random.default_rng(1).uniform(0, 3, layout.n_pixels)
    profiles = get_model("spline", layout).beam_profiles(setpoints)
    fabric = Fabric(layout, 8)
    beam = layout.beams[4]
    s = np.linspace(0.0, beam.straight_length, 257)
    points = np.asarray(beam.start) + s[:, None] * beam.direction
    away = np.min(np.linalg.norm(points[:, None] - layout.pixel_xy[None], axis=2), axis=1)
    s, points = s[away > fabric.h], points[away > fabric.h]  # not within h of a crossing
    np.testing.assert_allclose(fabric.surface(profiles, points),
                               profiles.heights(np.full(len(s), 4), s), atol=1e-9)
    g = np.linspace(-120, 120, 121)
    xx, yy = np.meshgrid(g, g)
    z = fabric.surface(profiles, np.column_stack([xx.ravel(), yy.ravel()]))
    on_beams = np.concatenate([profiles.heights(np.full(400, b), np.linspace(0, sp, 400))
                               for b, sp in enumerate(profiles.spans_mm)])
    assert on_beams.min() - 1e-9 <= z.min() and z.max() <= on_beams.max() + 1e-9


def test_zero_on_and_beyond_the_border(layout):
    profiles = random_profiles(layout, seed=2)
    fabric = Fabric(layout, 8)
    angle = np.linspace(0, 2 * np.pi, 50)
    far = np.column_stack([200 * np.cos(angle), 200 * np.sin(angle)])
    assert np.all(fabric.surface(profiles, far) == 0.0)
    corners = 90.0 * np.column_stack([np.cos(np.arange(6) * np.pi / 3),
                                      np.sin(np.arange(6) * np.pi / 3)])  # hull vertices
    np.testing.assert_allclose(fabric.surface(profiles, corners), 0.0, atol=1e-12)


@pytest.mark.parametrize("name", ["spline", "beam", "reference"])
def test_2d_models_agree_at_the_pixels(layout, name):
    setpoints = Renderer(layout, "crs").render(Bump((10.0, 5.0), 90.0, 3.0)).setpoints
    model = get_model(name, layout)
    np.testing.assert_allclose(model.surface(setpoints, layout.pixel_xy),
                               setpoints[: layout.n_pixels], atol=1e-7)


def test_crs_bump_between_pixels_in_2d(layout):
    """Fig. 4c: a bump at the midpoint of two pixels; with CRS the peak sits between them."""
    bump = Bump((15.0, 0.0), 90.0, 3.0)  # half-way between pixels (0, 0) and (30, 0)
    setpoints = Renderer(layout, "crs").render(bump).setpoints
    x = np.linspace(0.0, 30.0, 301)
    xy = np.column_stack([x, np.zeros_like(x)])
    beam = get_model("beam", layout).surface(setpoints, xy)
    spline = get_model("spline", layout).surface(setpoints, xy)
    assert x[beam.argmax()] == pytest.approx(15.0, abs=0.5)
    assert beam.max() > spline.max() and beam.max() == pytest.approx(3.0, rel=0.05)


def test_subdivisions_that_miss_the_clamps_are_refined_until_they_meet_them():
    """A mesh of 5 misses clamps 1.5 pitches out; the model takes 6, the next that meets them
    (asking for 4 keeps 4: 1.5 * 4 is whole)."""
    data = tomllib.loads(device_file_path("crs2d").read_text())
    data["geometry"]["end_margin_pitch"] = 1.5
    odd = layout_from_dict(data, "odd.toml")
    assert get_model("spline", odd, fabric_subdivisions=5).fabric.h == odd.pitch_mm / 6
    assert get_model("spline", odd, fabric_subdivisions=4).fabric.h == odd.pitch_mm / 4


def test_bad_points_shape(layout):
    with pytest.raises(DisplayModelError, match=r"expected points of shape \(n, 2\), got \(3,\)"):
        get_model("spline", layout).surface(np.zeros(layout.n_actuators), np.zeros(3))


def _dense_correction_weights(fabric: Fabric, xy: np.ndarray) -> np.ndarray:
    """The fade weights c_b prod_{b' != b} (1 - c_b') written out densely, (beams, points)."""
    rel = xy[None, :, :] - fabric.beam_starts[:, None, :]
    s = np.einsum("bnk,bk->bn", rel, fabric.beam_units)
    off = np.abs(rel[..., 0] * fabric.beam_units[:, None, 1]
                 - rel[..., 1] * fabric.beam_units[:, None, 0])
    close = np.where((s > 0) & (s < fabric.beam_spans[:, None]),
                     np.clip(1 - off / (fabric.h * np.sqrt(3) / 2), 0, 1), 0.0)
    return np.stack([close[b] * np.prod(np.delete(1 - close, b, axis=0), axis=0)
                     for b in range(len(close))])


def test_sparse_correction_weights_equal_the_dense_formula(layout):
    """Points at random, on pixels, on beam lines and at crossings (weight 1 on a line)."""
    fabric = get_model("beam", layout).fabric
    rng = np.random.default_rng(11)
    xy = np.vstack([rng.uniform(-100, 100, (2000, 2)), layout.pixel_xy,
                    0.5 * (layout.pixel_xy[:-1] + layout.pixel_xy[1:]),
                    0.3 * layout.pixel_xy[:-1] + 0.7 * layout.pixel_xy[1:]])
    beam, point, *_, weight = fabric._correction_terms(xy)
    sparse = np.zeros((len(layout.beams), len(xy)))
    sparse[beam, point] = weight
    np.testing.assert_allclose(sparse, _dense_correction_weights(fabric, xy), atol=1e-14)


def test_surface_plans_are_reused_and_give_the_same_heights(layout):
    model = get_model("beam", layout)
    setpoints = Renderer(layout, "crs").render(Bump((10.0, 5.0), 90.0, 3.0)).setpoints
    xy = np.random.default_rng(2).uniform(-80, 80, (500, 2))
    first = model.surface(setpoints, xy)
    plans = len(model.fabric._plans)
    again = model.surface(setpoints, xy.copy())
    assert len(model.fabric._plans) == plans
    np.testing.assert_array_equal(first, again)
    # a plan built for a superset gives the same heights on the shared points
    more = model.surface(setpoints, np.vstack([xy, [[0.0, 0.0]]]))
    np.testing.assert_allclose(more[:-1], first, atol=1e-13)


@pytest.mark.parametrize("name", ["beam", "spline"])
def test_prepared_beam_queries_give_the_plain_heights(layout, name):
    """The fabric's prepared fast path against the plain ``heights`` (prepare switched off),
    frame after frame on the same plan (the query is reused across frames)."""
    from dataclasses import replace

    model = get_model(name, layout)
    xy = np.random.default_rng(4).uniform(-90, 90, (800, 2))
    renderer = Renderer(layout, "crs")
    for centre in [(0.0, 0.0), (12.0, -7.0), (-20.0, 15.0)]:
        profiles = model.beam_profiles(renderer.render(Bump(centre, 90.0, 3.0)).setpoints)
        plain = replace(profiles, prepare=None, evaluate_prepared=None, geometry=None)
        np.testing.assert_allclose(model.fabric.surface(profiles, xy),
                                   model.fabric.surface(plain, xy), atol=1e-13)
