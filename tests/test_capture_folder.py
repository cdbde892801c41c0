import json

import numpy as np
import pytest

from mifacerf.formats.capture import Capture, CaptureError, CaptureWriter, ExpressionEntry, Radiometry
from mifacerf.imageio import ImageFileError, read_exr, write_exr
from mifacerf.rig import LightStage, Rig, camera_ring


@pytest.fixture
def small_rig():
    lights = LightStage.semicircular_arm(2, 3, irradiance_spread=0.1, seed=3)
    cams = camera_ring([(-20, 0), (20, 0)], width=8, height=6)
    return Rig(lights, cams)


def _write_capture(root, rig, rng, radiometry=None):
    exprs = [ExpressionEntry("neutral", "neutral"), ExpressionEntry("smile", "emotion")]
    w = CaptureWriter(root, rig, exprs, radiometry=radiometry)
    truth = {}
    for e in exprs:
        for c in rig.cameras:
            for l in range(len(rig.lights)):
                radiance = rng.random((6, 8, 3)).astype(np.float32)
                truth[e.name, c.name, l] = radiance
                w.write_image(e.name, c.name, l, radiance * rig.lights.irradiance[l])
    w.finish()
    return truth


def test_exr_round_trip_half(tmp_path, rng):
    img = rng.random((5, 7, 4)).astype(np.float32)
    write_exr(tmp_path / "a.exr", img)
    back = read_exr(tmp_path / "a.exr")
    assert back.shape == (5, 7, 4)
    np.testing.assert_allclose(back, img, rtol=1e-3, atol=1e-3)


def test_exr_errors_name_the_file(tmp_path, rng):
    with pytest.raises(ImageFileError, match="missing"):
        read_exr(tmp_path / "nope.exr")
    (tmp_path / "junk.exr").write_bytes(b"not an exr at all")
    with pytest.raises(ImageFileError, match="junk.exr: not an OpenEXR"):
        read_exr(tmp_path / "junk.exr")
    write_exr(tmp_path / "t.exr", rng.random((32, 32, 3)))
    data = (tmp_path / "t.exr").read_bytes()
    (tmp_path / "t.exr").write_bytes(data[: len(data) // 2])
    with pytest.raises(ImageFileError, match="t.exr: truncated or corrupt"):
        read_exr(tmp_path / "t.exr")
    with pytest.raises(ValueError, match="NaN"):
        write_exr(tmp_path / "n.exr", np.full((2, 2, 3), np.nan))
    assert not (tmp_path / "n.exr").exists()
    assert not list(tmp_path.glob(".*tmp*"))  # no temporary left behind
    with pytest.raises(ValueError, match="overflow half"):
        write_exr(tmp_path / "big.exr", np.full((2, 2, 3), 1e6))


def test_capture_round_trip_calibrated(tmp_path, small_rig, rng):
    truth = _write_capture(tmp_path / "cap", small_rig, rng)
    cap = Capture(tmp_path / "cap")
    assert cap.expression_names == ["neutral", "smile"]
    assert cap.n_lights == 6
    img = cap.image("smile", "cam1", 4)
    np.testing.assert_allclose(img, truth["smile", "cam1", 4], rtol=2e-3, atol=2e-3)
    f = cap.field("neutral", "cam0", lights=[5, 1])
    np.testing.assert_allclose(f[0], truth["neutral", "cam0", 5], rtol=2e-3, atol=2e-3)
    assert cap.verify() == []


def test_field_reads_only_requested_files(tmp_path, small_rig, rng):
    _write_capture(tmp_path / "cap", small_rig, rng)
    cap = Capture(tmp_path / "cap")
    (tmp_path / "cap/images/smile/cam0/L003.exr").unlink()
    cap.field("smile", "cam0", lights=[0, 1, 2])  # fine: L003 is not needed
    with pytest.raises(CaptureError, match="L003.exr: missing"):
        cap.field("smile", "cam0")


def test_packed_cache_is_used_and_invalidated(tmp_path, small_rig, rng):
    truth = _write_capture(tmp_path / "cap", small_rig, rng)
    cap = Capture(tmp_path / "cap")
    cap.build_cache("smile", "cam1")
    assert cap._cache_current("smile", "cam1")
    np.testing.assert_allclose(cap.field("smile", "cam1", lights=[2])[0], truth["smile", "cam1", 2],
                               rtol=3e-3, atol=3e-3)
    # rewriting a source image makes the cache stale; the EXR is read again
    p = cap.image_path("smile", "cam1", 2)
    write_exr(p, np.zeros((6, 8, 3)))
    assert not cap._cache_current("smile", "cam1")


def test_radiometry_applied_on_load(tmp_path, small_rig, rng):
    M = np.array([[1.1, -0.05, 0.0], [0.02, 0.95, 0.03], [0.0, -0.1, 1.2]])
    rad = {"cam0": Radiometry(2.0, M, {"x": [0, 0.5, 100], "y": [0, 0.25, 99.75]}), "cam1": Radiometry()}
    exprs = [ExpressionEntry("neutral", "neutral")]
    w = CaptureWriter(tmp_path / "cap", small_rig, exprs, radiometry=rad)
    recorded = np.full((6, 8, 3), 0.4, np.float32)
    for c in small_rig.cameras:
        for l in range(len(small_rig.lights)):
            w.write_image("neutral", c.name, l, recorded)
    w.finish()
    cap = Capture(tmp_path / "cap")
    got = cap.image("neutral", "cam0", 0)[0, 0]
    lin = 0.4 * 0.25 / 0.5
    expect = M @ np.full(3, lin / 2.0) / small_rig.lights.irradiance[0]
    np.testing.assert_allclose(got, expect, rtol=2e-3)


def test_incomplete_or_inconsistent_captures(tmp_path, small_rig, rng):
    root = tmp_path / "cap"
    w = CaptureWriter(root, small_rig, [ExpressionEntry("neutral", "neutral")])
    w.write_image("neutral", "cam0", 0, np.zeros((6, 8, 3)))
    with pytest.raises(CaptureError, match="incomplete"):
        w.finish()
    with pytest.raises(CaptureError, match="manifest.json: missing"):
        Capture(root)
    _write_capture(tmp_path / "ok", small_rig, rng)
    m = json.loads((tmp_path / "ok/manifest.json").read_text())
    m["expressions"].append({"name": "smile", "category": "emotion"})
    (tmp_path / "ok/manifest.json").write_text(json.dumps(m))
    with pytest.raises(CaptureError, match="duplicate expression"):
        Capture(tmp_path / "ok")
    m["expressions"].pop()
    m["rig"]["lights"]["lights"][2]["index"] = 7
    (tmp_path / "ok/manifest.json").write_text(json.dumps(m))
    with pytest.raises(CaptureError, match="invalid rig"):
        Capture(tmp_path / "ok")
    _write_capture(tmp_path / "ok2", small_rig, rng)
    with pytest.raises(CaptureError, match="already holds a complete capture"):
        CaptureWriter(tmp_path / "ok2", small_rig, [])


def test_wrong_image_size_and_checksum(tmp_path, small_rig, rng):
    _write_capture(tmp_path / "cap", small_rig, rng)
    cap = Capture(tmp_path / "cap")
    p = cap.image_path("neutral", "cam1", 0)
    write_exr(p, np.zeros((5, 8, 3)))
    with pytest.raises(CaptureError, match="checksum mismatch"):
        cap.raw_image("neutral", "cam1", 0)
    cap.checksums.clear()
    with pytest.raises(CaptureError, match="expected 8x6"):
        cap.raw_image("neutral", "cam1", 0)


def test_per_channel_response_curves():
    r = Radiometry(1.0, np.eye(3), {"x": [0, 1], "y": [[0, 2], [0, 1], [0, 0.5]]})
    np.testing.assert_allclose(r.apply(np.full((1, 1, 3), 0.5))[0, 0], [1.0, 0.5, 0.25])
    with pytest.raises(ValueError, match="shape"):
        Radiometry(1.0, np.eye(3), {"x": [0, 1], "y": [[0, 2], [0, 1]]})
