"""Radiometric calibration: response curves (Debevec & Malik, from a lit grey chart or exposures),
ColorChecker colour matrices against colour-science's reference data, applied to captures on load."""
import json

import numpy as np
import pytest
from click.testing import CliRunner

from helpers.capture import new_session, run_lab, tiny_rig
from mifacerf.capture.calibration.apply import apply_to_capture
from mifacerf.capture.calibration.charts import ChartLayout, colorchecker_reference, grey_reference, patch_means
from mifacerf.capture.calibration.colour_correction import delta_e2000, factor_exposure, fit_colour_matrix
from mifacerf.capture.calibration.debevec1997 import ResponseError, curve_error, recover_response
from mifacerf.capture.calibration.radiometric import RadiometryError, calibrate_radiometry, to_json
from mifacerf.capture.simulation.cameras import SensorModel
from mifacerf.capture.simulation.charts import write_chart_dataset
from mifacerf.capture.simulation.lab import LabOptions
from mifacerf.formats.capture import Capture, Radiometry
from mifacerf.cli import main


@pytest.fixture(scope="module")
def charts(tmp_path_factory):
    rig = tiny_rig(6, 6, 2, 82)   # grey chart ~38x27 px, colour checker ~71x49 px
    sensors = {c.name: SensorModel.realistic(seed=i) for i, c in enumerate(rig.cameras)}
    root = tmp_path_factory.mktemp("charts")
    write_chart_dataset(root, rig, sensors)
    return root, rig, sensors


def test_reference_data_from_colour_science():
    names, rgb = colorchecker_reference()
    assert len(names) == 24 and names[18].startswith("white") and names[23].startswith("black")
    assert rgb[18] == pytest.approx([0.88, 0.885, 0.834], abs=0.01)       # white 9.5
    grey_names, grey = grey_reference()
    assert len(grey) == 6 and np.all(np.diff(grey) < 0) and 0.02 < grey[-1] < 0.04
    neutral = rgb[19:23]
    assert np.all(np.ptp(neutral, axis=1) < 0.012)                         # the greys are grey
    assert (colorchecker_reference(clip=False)[1] < 0).any() and (rgb >= 0).all()


def test_debevec_recovers_a_known_curve():
    s = SensorModel(gamma=2.2, toe=0.02)
    rng = np.random.default_rng(0)
    a = np.exp(rng.uniform(np.log(0.02), np.log(2.0), 60))       # unknown irradiances
    b = np.array([0.9, 0.59, 0.36, 0.19, 0.09, 0.031])            # known reflectances
    z = s.response(a[:, None] * b[None])
    z[z >= 1] = np.nan
    curve = recover_response(z, np.log(b))
    assert curve_error(curve, s.inverse_response)["max"] < 0.01
    assert np.all(np.diff(curve["y"]) > 0) and curve["y"][0] == pytest.approx(0, abs=1e-6)
    with pytest.raises(ResponseError, match="usable"):
        recover_response(z[:1, :2], np.log(b[:2]))


@pytest.mark.parametrize("method", ["grey_olat", "exposures"])
def test_response_colour_and_exposure_against_truth(charts, method):
    root, rig, sensors = charts
    res = calibrate_radiometry(root, method=method)
    for cam, r in res.items():
        s = sensors[cam]
        err = curve_error(r.radiometry.response, s.inverse_response)
        assert err["rms"] < 0.01 and err["max"] < 0.05, err
        # the full linear map (colour matrix / exposure) is the sensor's, up to the response's normalisation
        scale = s.inverse_response(np.array([0.5]))[0] / np.interp(0.5, r.radiometry.response["x"],
                                                                     r.radiometry.response["y"])
        M_est = r.radiometry.colour_matrix / r.radiometry.exposure / scale
        np.testing.assert_allclose(M_est, s.colour_matrix / s.exposure, atol=0.03 * np.abs(s.colour_matrix).max() / s.exposure)
        assert r.delta_e.mean() < 1.0 and r.delta_e.max() < 2.5
    assert to_json(res, str(root), method)["report"][rig.cameras[0].name]["delta_e2000_mean"] < 1.0


def test_colour_fit_and_delta_e_basics():
    _, ref = colorchecker_reference()
    M = np.array([[1.6, -0.4, -0.2], [-0.3, 1.5, -0.2], [0.0, -0.5, 1.5]])
    cam = ref @ np.linalg.inv(M).T
    fit = fit_colour_matrix(cam, ref)
    np.testing.assert_allclose(fit, M, atol=1e-9)
    exposure, cm = factor_exposure(fit)
    np.testing.assert_allclose(cm / exposure, M, atol=1e-12)
    assert np.allclose(delta_e2000(ref, ref), 0) and delta_e2000(ref * [1.1, 1, 1], ref).mean() > 1
    with pytest.raises(ValueError):
        fit_colour_matrix(np.full((24, 3), np.nan), ref)


def test_patch_means_reads_the_right_patches():
    layout = ChartLayout(2, 3, patch=10, gap=2, margin=1)  # in pixels, for the test
    w, h = layout.size
    img = np.zeros((int(h) + 1, int(w) + 1, 1))
    for p, (x, y) in enumerate(layout.centres()):
        img[int(y) - 4:int(y) + 5, int(x) - 4:int(x) + 5] = p + 1
    corners = layout.corners() - 0.5
    means, counts = patch_means(img, corners, layout)
    np.testing.assert_allclose(means[:, 0], np.arange(1, 7))
    assert np.all(counts > 5)


def test_calibration_applied_on_load_gives_radiance(tmp_path, charts):
    """A session recorded through realistic sensors, calibrated from charts taken by the same cameras,
    reads back as the renderer's radiance per unit irradiance."""
    rig = tiny_rig(3, 3, 2, 64)
    s = new_session(tmp_path / "cap", rig, 1)
    _, lab = run_lab(s, LabOptions(sensor="realistic", seed=0))
    sensors = {c.name: SensorModel.realistic(seed=i) for i, c in enumerate(rig.cameras)}  # the lab's seeds
    croot = write_chart_dataset(tmp_path / "charts", rig, sensors)
    res = calibrate_radiometry(croot)
    backup = apply_to_capture(tmp_path / "cap", radiometry=to_json(res, str(croot), "grey_olat"))
    assert backup.exists()
    cap = Capture(tmp_path / "cap")
    cam = rig.cameras[0]
    light = int(np.argmax(rig.lights.directions[:, 2]))
    truth = lab.renderer.render(lab.subject.expressions["neutral"], cam, np.array([light]))[0]
    got = cap.image("neutral", cam.name, light)
    lit = truth.mean(axis=2) > 0.03
    # the calibration's scale is fixed by the chart (absolute), so values match, not just up to a factor
    rel = np.abs(got[lit] - truth[lit]) / truth[lit]
    assert np.median(rel) < 0.03
    raw = cap.raw_image("neutral", cam.name, light)
    assert np.median(np.abs(raw[lit] - truth[lit]) / truth[lit]) > 0.2  # uncalibrated data is far off


def test_cli_response_and_bad_input(tmp_path, charts):
    root, rig, sensors = charts
    out = tmp_path / "radiometry.json"
    (root / "truth.json").write_text(json.dumps({"cameras": {c: s.true_radiometry().to_dict()
                                                             for c, s in sensors.items()}}))
    r = CliRunner().invoke(main, ["calibrate", "response", str(root), "--out", str(out), "--truth",
                                  str(root / "truth.json")])
    assert r.exit_code == 0, r.output
    assert "ΔE2000" in r.output and "response error" in r.output
    data = json.loads(out.read_text())
    for c in data["cameras"].values():
        Radiometry.from_dict(c)  # valid for the capture reader
    with pytest.raises(RadiometryError, match="charts.json"):
        calibrate_radiometry(tmp_path)
    r = CliRunner().invoke(main, ["calibrate", "response", str(tmp_path)])
    assert r.exit_code == 1 and "not a chart-capture folder" in r.output
