"""Import of surface measurements (crs_study.quality.dic_import): the exports of VIC-3D, GOM
Correlate, DICe, plain tables and MATLAB read into millimetres; every bad file one line."""

from __future__ import annotations

import math
import struct
from pathlib import Path

import numpy as np
import pytest
from dic_synthetic import write_capture
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from crs_study.errors import MeasurementError
from crs_study.quality.dic_import import heights_above_reference, read_fiducials, read_surface


def _columns(n: int = 30, seed: int = 1) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    columns = {"X": rng.uniform(-50, 50, n), "Y": rng.uniform(-40, 40, n),
               "Z": rng.uniform(400, 410, n), "W": rng.uniform(-1, 5, n)}
    for values in columns.values():
        values[3] = np.nan  # one point without data
    return columns


@pytest.mark.parametrize("fmt", ["vic3d", "gom", "dice", "plain-m", "mat"])
def test_each_tool_reads_back_to_the_same_points(tmp_path, fmt):
    columns = _columns()
    path = write_capture(tmp_path / "shape-0001", fmt, columns)
    capture = read_surface(path)
    valid = np.isfinite(columns["W"])
    assert capture.valid.tolist() == valid.tolist()  # sigma -1, empty cells, NaN: holes
    assert capture.hole_fraction == pytest.approx(1 / 30)
    np.testing.assert_allclose(capture.x[valid], columns["X"][valid], atol=1e-5)
    np.testing.assert_allclose(capture.y[valid], columns["Y"][valid], atol=1e-5)
    deformed = columns["Z"] + columns["W"]
    np.testing.assert_allclose(capture.z[valid], deformed[valid], atol=1e-5)
    if fmt == "plain-m":  # coordinates only: no displacement to read
        assert capture.w is None
    else:
        np.testing.assert_allclose(capture.w[valid], columns["W"][valid], atol=1e-5)
    assert capture.format == {"vic3d": "vic3d", "gom": "gom", "dice": "dice",
                              "plain-m": "plain", "mat": "mat"}[fmt]


def test_vic3d_pixel_columns_are_never_read_as_millimetres(tmp_path):
    """VIC-3D writes metric X, Y and image x, y (pixels) side by side: X wins."""
    path = tmp_path / "a.csv"
    path.write_text('"x","y","X","Y","Z","W","sigma"\n' +
                    "".join(f"{600 + k},{400 + k},{k * 0.5},{-k * 0.5},1.0,0.2,0.01\n"
                            for k in range(12)))
    capture = read_surface(path)
    assert capture.x[:3].tolist() == [0.0, 0.5, 1.0]
    assert capture.y[:3].tolist() == [0.0, -0.5, -1.0]


@pytest.mark.parametrize(("unit", "scale"), [("mm", 1.0), ("m", 1000.0), ("um", 1e-3),
                                             ("µm", 1e-3), ("in", 25.4), ("cm", 10.0)])
def test_header_units_become_millimetres(tmp_path, unit, scale):
    path = tmp_path / "a.csv"
    path.write_text(f"x [{unit}],y [{unit}],w [{unit}]\n" +
                    "".join(f"{k},{2 * k},{3 * k}\n" for k in range(12)))
    capture = read_surface(path)
    assert capture.x[5] == pytest.approx(5 * scale)
    assert capture.w[5] == pytest.approx(15 * scale)


def test_a_unit_for_the_whole_file(tmp_path):
    path = tmp_path / "a.txt"
    path.write_text("x y z\n" + "".join(f"{k} {k} {k}\n" for k in range(12)))
    assert read_surface(path, units="m").x[2] == pytest.approx(2000.0)


@pytest.mark.parametrize(("text", "message"), [
    pytest.param("x [px],y [px],w [px]\n" + "1,2,3\n" * 12,
                 r"column 'x \[px\]' is in px \(image coordinates\)", id="pixels"),
    pytest.param("x [furlong],y,w\n" + "1,2,3\n" * 12, r"unit 'furlong' is not a length",
                 id="unknown-unit"),
    pytest.param("a,b,c\n" + "1,2,3\n" * 12, r"no header with 'x' and 'y' columns",
                 id="no-columns"),
    pytest.param("x,y,sigma\n" + "1,2,3\n" * 12, r"expected columns .* x, y and z or w",
                 id="no-height"),
    pytest.param("x,y,w\n" + "1,2,3\n" * 5, r"5 point\(s\) with data of 5; expected at "
                 r"least 10", id="too-few"),
    pytest.param("x,y,w\n" + "1,2,3\n" * 11 + "1,abc,3\n", r"row 12 after the header, column "
                 r"'y': expected a number, got 'abc'", id="not-a-number"),
    pytest.param("SUBSET_ID,COORDINATE_X,COORDINATE_Y,DISPLACEMENT_X\n" + "1,2,3,4\n" * 12,
                 r"COORDINATE_X/Y are image pixels", id="dice-2d"),
])
def test_bad_exports_are_one_line_errors(tmp_path, text, message):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(MeasurementError, match=message) as caught:
        read_surface(path)
    assert "\n" not in str(caught.value) and str(path) in str(caught.value)


def test_files_the_reader_cannot_take(tmp_path):
    with pytest.raises(MeasurementError, match=r"expected a DIC export ending in"):
        read_surface(tmp_path / "a.xlsx")
    with pytest.raises(MeasurementError, match="no such file"):
        read_surface(tmp_path / "missing.csv")
    v73 = tmp_path / "new.mat"  # the 128-byte header of a MATLAB v7.3 (HDF5) file
    header = b"MATLAB 7.3 MAT-file, Platform: GLNXA64, HDF5 schema 1.00 .".ljust(116, b" ")
    v73.write_bytes(header + b"\x00" * 8 + struct.pack("<H", 0x0200) + b"IM" + b"\x00" * 64)
    with pytest.raises(MeasurementError, match=r"v7.3 \(HDF5\) file; save it in v7"):
        read_surface(v73)
    with pytest.raises(MeasurementError, match="--units"):
        read_surface(write_capture(tmp_path / "ok", "vic3d", _columns()), units="parsec")


def test_fiducials(tmp_path):
    path = tmp_path / "fiducials.csv"
    path.write_text("pixel,x [mm],y [mm]\n0,1.5,2.5\n3,4.0,5.0\n7,-1,-2\n")
    fiducials = read_fiducials(path)
    assert fiducials.pixels.tolist() == [0, 3, 7]
    assert fiducials.xy.tolist() == [[1.5, 2.5], [4.0, 5.0], [-1.0, -2.0]]
    for body, message in (("0,1,2\n0,3,4\n", "marked twice"), ("0.5,1,2\n", "not a pixel"),
                          ("0,1,\n", "without a position")):
        path.write_text("pixel,x,y\n" + body)
        with pytest.raises(MeasurementError, match=message):
            read_fiducials(path)
    with pytest.raises(MeasurementError, match="no such fiducials file"):
        read_fiducials(tmp_path / "none.csv")


_finite = st.floats(-1e4, 1e4, allow_nan=False, allow_infinity=False, width=32)


@settings(suppress_health_check=[HealthCheck.function_scoped_fixture], max_examples=60)
@given(rows=st.lists(st.tuples(_finite, _finite, _finite), min_size=10, max_size=40),
       delimiter=st.sampled_from([",", ";", "\t", " "]), quote=st.booleans(),
       preamble=st.lists(st.sampled_from(["# exported", "*** DICe", "Project: a",
                                          "// note"]), max_size=3),
       unit=st.sampled_from(["", " [mm]", " (m)", "_um"]))
def test_property_any_table_round_trips(tmp_path, rows, delimiter, quote, preamble, unit):
    """A table written with any delimiter, quoting, preamble and unit reads back to its
    numbers (in mm); decimal commas with ';' too."""
    comma = delimiter == ";"
    scale = {"": 1.0, " [mm]": 1.0, " (m)": 1000.0, "_um": 1e-3}[unit]
    names = [f"x{unit}", f"y{unit}", f"w{unit}"]
    if delimiter == " ":
        names = [n.replace(" ", "") for n in names]
    q = '"' if quote and delimiter != " " else ""
    lines = [*preamble, delimiter.join(f"{q}{n}{q}" for n in names)]
    for row in rows:
        cells = [repr(float(v)) for v in row]
        if comma:
            cells = [c.replace(".", ",") for c in cells]
        lines.append(delimiter.join(f"{q}{c}{q}" for c in cells))
    path = tmp_path / "t.csv"
    path.write_text("\n".join(lines) + "\n")
    if delimiter == " " and unit == " (m)":
        return  # a unit with a space inside cannot sit in a space-separated header
    capture = read_surface(path)
    expected = np.array(rows, dtype=float) * scale
    np.testing.assert_allclose(capture.x, expected[:, 0], rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(capture.w, expected[:, 2], rtol=1e-6, atol=1e-9)


@settings(suppress_health_check=[HealthCheck.function_scoped_fixture], max_examples=80)
@given(st.text(max_size=400))
def test_property_any_text_is_read_or_refused_in_one_line(tmp_path, text):
    path = tmp_path / "fuzz.csv"
    path.write_text(text, encoding="utf-8", errors="surrogatepass")
    try:
        capture = read_surface(path)
    except MeasurementError as error:
        assert "\n" not in str(error)
    else:
        assert capture.n_points >= 10 and np.isfinite(capture.x[capture.valid]).all()
        assert not math.isnan(capture.hole_fraction)


FIXTURES = Path(__file__).parent / "fixtures" / "dic"


def test_a_public_stereo_dic_export_of_a_buckling_surface():
    """Real data (tests/fixtures/dic/README.md: a steel hollow section's face measured by
    stereo DIC, stages 1 and 151, from the public repository GMNIA/viewdic): the exports read
    as a lab's would (a '#' preamble with the units, columns id, x, y, z in mm), and the
    reference subtracted at the loaded stage's points agrees with the displacement the
    export tracks per point (its ids) to 0.06 mm in the median: the in-plane motion (about
    1 mm) over the reference's gentle slopes."""
    import pandas as pd

    reference = read_surface(FIXTURES / "viewdic_VHPS_140_140_3_0001.csv")
    loaded = read_surface(FIXTURES / "viewdic_VHPS_140_140_3_0151.csv")
    assert (reference.format, reference.n_points, loaded.n_points) == ("plain", 4090, 4064)
    assert reference.w is None and reference.hole_fraction == 0.0
    heights = heights_above_reference(loaded, reference)
    assert np.isnan(heights).mean() < 0.005  # only beyond the reference's hull
    assert -6.0 < np.nanmin(heights) < -4.0 and 1.5 < np.nanmax(heights) < 3.5  # the bumps
    before = pd.read_csv(FIXTURES / "viewdic_VHPS_140_140_3_0001.csv", comment="#")
    after = pd.read_csv(FIXTURES / "viewdic_VHPS_140_140_3_0151.csv", comment="#")
    tracked = after.merge(before, on="id", suffixes=("", "_ref"))
    by_point = (tracked["z"] - tracked["z_ref"]).to_numpy()
    ours = pd.Series(heights, index=after["id"]).loc[tracked["id"]].to_numpy()
    keep = np.isfinite(ours)
    assert np.median(np.abs(ours[keep] - by_point[keep])) < 0.1
    with pytest.raises(MeasurementError, match="a reference capture with z"):
        heights_above_reference(loaded, None)
