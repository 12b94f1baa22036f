"""A measurement analysed end to end (crs_study.quality.measured_analysis, measured_result,
measured_report): synthetic DIC exports made from the display model with a known
misregistration, noise, holes and faulty servos (tests/dic_synthetic.py) are registered,
measured and compared; the registration recovers the transform, a faulty servo is named on
the residual map, and D_P and D_S equal the model's within their intervals."""

from __future__ import annotations

import json
import math
import shutil

import numpy as np
import pytest
from dic_synthetic import Rig, fill_measurement
from test_quality_measure_session import small_protocol

from crs_study.errors import MeasurementError
from crs_study.quality.measured_analysis import analyze_measurement
from crs_study.quality.measured_report import write_report
from crs_study.session.measurement import MeasurementSpec, run_measurement


@pytest.fixture(scope="module")
def shown_1d(tmp_path_factory):
    """A measurement of crs1d shown on the simulated device, no captures yet."""
    base = tmp_path_factory.mktemp("m1d")
    protocol = small_protocol(base, shapes=10)
    text = protocol.read_text().replace("[90.0]", "[90.0, 150.0]")
    protocol.write_text(text)
    run = run_measurement(MeasurementSpec(protocol, base / "meas", "sim://", "timed"),
                          prompt=lambda message: None)
    assert run.status == "complete"
    return base / "meas"


def _copy(shown, tmp_path, name="meas"):
    return shutil.copytree(shown, tmp_path / name)


@pytest.mark.parametrize("fmt", ["vic3d", "gom", "dice", "plain-m", "mat"])
def test_a_clean_device_measures_as_its_model(shown_1d, tmp_path, fmt):
    folder = _copy(shown_1d, tmp_path)
    rig = Rig()
    fill_measurement(folder, rig, fmt, seed=1)
    result = analyze_measurement(folder)
    reg = result.registration
    assert reg.rotation_deg == pytest.approx(-rig.rotation_deg, abs=0.1)
    assert reg.rms_mm < 0.1 and reg.scale == 1.0
    back = reg.to_display(rig.to_dic(np.array([[0.0, 0.0], [120.0, 0.0]])))
    np.testing.assert_allclose(back, [[0.0, 0.0], [120.0, 0.0]], atol=0.1)
    assert [v.verdict for v in result.verdicts] == ["as predicted", "as predicted"]
    assert not result.residual_map.flagged
    for row in result.rows:
        for quantity in ("D_P", "D_S"):
            measured, model = getattr(row, quantity), getattr(row, f"model_{quantity}")
            assert measured.low - 1e-9 <= model.estimate <= measured.high + 1e-9, \
                (row.condition, row.d_over_l, quantity)
        if row.condition == "pixel-only":  # the paper's lines beside: Eq. 1 theory, Eq. 2 fit
            assert row.paper_D_P == pytest.approx(0.25 * row.d_over_l)
            assert row.paper_D_S == pytest.approx(1.545 * row.d_over_l**2)  # linear model
        else:
            assert row.paper_D_P is None
    assert len(result.shapes) == 40 and result.lattice == "1d"


def test_a_faulty_servo_is_named_and_its_calibration_corrected(shown_1d, tmp_path):
    """Pixel 2 sits 0.4 mm high at every stroke, pixel 4 strokes 1.2 mm per mm: the map names
    channels A:3 and A:5 alone, with their offset and gain."""
    folder = _copy(shown_1d, tmp_path)
    fill_measurement(folder, Rig(faults={2: (0.4, 1.0), 4: (0.0, 1.2)}), "vic3d", seed=2)
    result = analyze_measurement(folder)
    named = {p.channel: p for p in result.residual_map.flagged}
    assert sorted(named) == ["A:3", "A:5"]
    assert named["A:3"].offset_mm == pytest.approx(0.4, abs=0.05)
    assert named["A:5"].gain == pytest.approx(1.2, abs=0.02)
    assert named["A:5"].why.startswith("gain 1.2")
    assert named["A:3"].why.startswith(("offset +0.4", "offset +0.3"))
    from crs_study.geometry.layout import load_layout

    endpoints = result.residual_map.corrected_endpoints(load_layout("crs1d"))
    assert endpoints["A:5"][1] == pytest.approx(1000 + 1000 / 1.2, abs=15)
    # the pixel-only display shows linear surfaces: heights relative to the neutral are
    # those of the model even with a pixel offset, so that condition still measures as
    # predicted; the offset does change what the skeleton shows
    assert result.verdicts[0].verdict == "as predicted"


def test_a_similarity_fit_recovers_a_unit_the_export_did_not_state(shown_1d, tmp_path):
    folder = _copy(shown_1d, tmp_path)
    fill_measurement(folder, Rig(scale=1.03), "vic3d", seed=3)
    with pytest.raises(MeasurementError, match=r"the rigid fit of 5 fiducials misses by "
                                               r"[\d.]+ mm RMS, beyond the protocol's 0.5 mm"):
        analyze_measurement(folder)
    record = json.loads((folder / "measurement.json").read_text())
    record["protocol_text"] += '\n[analysis]\nregistration = "similarity"\n'
    (folder / "measurement.json").write_text(json.dumps(record))
    result = analyze_measurement(folder)
    assert result.registration.scale == pytest.approx(1 / 1.03, rel=1e-3)
    assert [v.verdict for v in result.verdicts] == ["as predicted", "as predicted"]


def test_missing_and_damaged_captures_are_one_line_errors(shown_1d, tmp_path):
    folder = _copy(shown_1d, tmp_path)
    with pytest.raises(MeasurementError, match=r"no export of 40 capture\(s\), first "
                                               r"'shape-0001'"):
        analyze_measurement(folder)
    blob = Rig(blob=(60.0, 0.0, 14.0))  # the fabric's speckle lost over the central pixel
    fill_measurement(folder, blob, "vic3d", seed=4)
    with pytest.raises(MeasurementError, match=r"shape-0001.csv: .* has no measured point "
                                               r"within .* beyond the protocol's "
                                               r"max_hole_fraction of 0.05"):
        analyze_measurement(folder)
    shutil.rmtree(folder / "captures")
    fill_measurement(folder, Rig(), "vic3d", seed=4)
    (folder / "captures" / "fiducials.csv").unlink()
    with pytest.raises(MeasurementError, match="no fiducials.csv"):
        analyze_measurement(folder)
    (folder / "captures" / "shape-0003.mat").write_bytes(b"")
    with pytest.raises(MeasurementError, match="two exports of capture 'shape-0003'"):
        analyze_measurement(folder, fiducials=tmp_path / "none.csv")
    record = json.loads((folder / "measurement.json").read_text())
    record["status"] = "interrupted"
    (folder / "measurement.json").write_text(json.dumps(record))
    with pytest.raises(MeasurementError, match="the measurement is interrupted at capture"):
        analyze_measurement(folder)


def test_the_2d_display_report(tmp_path):
    """crs2d, a few shapes, a servo with a gain fault: the report, results.json, the chart
    and the residual map are written; the servo is named."""
    protocol = small_protocol(tmp_path, shapes=4, device="crs2d")
    folder = tmp_path / "meas"
    run_measurement(MeasurementSpec(protocol, folder, "sim://", "timed"),
                    prompt=lambda message: None)
    fill_measurement(folder, Rig(spacing_mm=1.5, faults={9: (0.0, 1.25)}), "gom", seed=5)
    result = analyze_measurement(folder)
    assert [p.channel for p in result.residual_map.flagged] == ["A:10"]
    assert result.registration.rms_mm < 0.1 and len(result.registration.pixels) == 19
    import matplotlib
    import matplotlib.pyplot as plt

    backend = matplotlib.get_backend()
    matplotlib.use("svg")             # the user's own choice, which the report must keep
    try:
        figures = plt.get_fignums()
        files = write_report(result, folder / "derivatives")
        charts = [result.plot(), result.plot()[1], result.plot_residual_map()]   # as a notebook
        # drawn without pyplot: no figure is left behind, and each chart displays as a
        # picture with no magic
        assert (matplotlib.get_backend(), plt.get_fignums()) == ("svg", figures)
    finally:
        matplotlib.use(backend)
    for ax in charts:
        assert ax._repr_png_()[:8] == b"\x89PNG\r\n\x1a\n"
    for key in ("report", "results", "shapes", "chart", "residual_map"):
        assert files[key].is_file()
    assert files["chart"].read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    data = json.loads(files["results"].read_text())
    assert {"rows", "verdicts", "registration", "residual_map", "shapes"} <= set(data)
    assert data["residual_map"]["flagged"] == ["A:10"]
    row = next(r for r in data["rows"] if r["condition"] == "pixel-only")
    assert row["paper_D_P"] == pytest.approx(0.3510 / 3)  # Eq. 5, hexagonal pixels
    report = files["report"].read_text()
    assert "## Verdicts" in report and "A:10" in report and "Eq. 5" in report
    frame = result.to_frame()
    assert list(frame["condition"]) == ["pixel-only", "crs"]
    assert math.isfinite(frame["D_S_low"].iloc[0])
