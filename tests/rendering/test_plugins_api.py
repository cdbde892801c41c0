"""Sensors, the Python API, compositing, scene files and the facerf integrator plugin, on the toy model."""
import numpy as np
import pytest

from mifacerf.camera import Camera

from .toy import make_toy


@pytest.fixture(scope="module")
def toy_model(tmp_path_factory, mi):
    from mifacerf.rendering.build import build_model

    root = tmp_path_factory.mktemp("toyapi")
    cap, _ = make_toy(root, names=("neutral", "stretch"), size=40, n_pos=6, n_str=5)
    build_model(cap, root / "model")
    return root / "model"


def test_sensor_round_trip_and_projection(mi):
    from mifacerf.rendering.sensors import camera_from_sensor, sensor_dict

    cam = Camera.look_at("c", [0.3, 0.2, 1.2], [0, 0, 0], width=64, height=48, focal=90.0, principal_offset=(2, -1))
    scene = mi.load_dict({"type": "scene", "sensor": sensor_dict(cam, spp=16),
                          "integrator": {"type": "aov", "aovs": "dd:depth"},
                          "s": {"type": "sphere", "center": [0.05, 0.03, 0.02], "radius": 0.01}})
    back = camera_from_sensor(scene.sensors()[0])
    np.testing.assert_allclose(back.K, cam.K, atol=1e-5)
    np.testing.assert_allclose(back.R, cam.R, atol=1e-6)
    img = np.asarray(mi.render(scene))
    cov = img[..., -1]
    ys, xs = np.nonzero(cov > 0)
    w = cov[cov > 0]
    centroid = np.array([(xs * w).sum() / w.sum(), (ys * w).sum() / w.sum()])
    uv = cam.project(np.array([[0.05, 0.03, 0.02]]))[0][0]
    assert np.abs(centroid - uv).max() < 0.15  # Mitsuba's image lands where our projection says
    with pytest.raises(ValueError, match="distortion"):
        sensor_dict(Camera("d", 8, 8, np.diag([10, 10, 1.0]), dist=[0.1, 0, 0, 0, 0]))


def test_api_weights_and_composite(toy_model):
    import mifacerf as mf

    face = mf.load_model(toy_model)
    with pytest.raises(KeyError, match="unknown expression"):
        face.render("frown")
    with pytest.raises(ValueError, match="non-negative"):
        face.render({"neutral": -1.0, "stretch": 2.0})
    with pytest.raises(ValueError, match="exactly one"):
        face.render()
    rgba = face.render("neutral=1,stretch=1", camera=(10, 0), env="gradient", spp=2, size=32)
    assert rgba.shape == (32, 32, 4) and np.isfinite(rgba).all()
    plate = mf.environment_plate("gradient", face.camera((10, 0), size=32))
    out = mf.composite(rgba, plate)
    bg = rgba[..., 3] == 0
    np.testing.assert_allclose(out[bg], plate[bg])
    fg = rgba[..., 3] == 1
    np.testing.assert_allclose(out[fg], rgba[..., :3][fg])
    with pytest.raises(ValueError, match="plate is"):
        mf.composite(rgba, plate[:10])


def test_integrator_plugin_matches_api(toy_model, mi, tmp_path):
    import mifacerf as mf
    from pathlib import Path

    from mifacerf.rendering.scenefile import load_scene_file
    from mifacerf.rendering.sensors import camera_from_sensor

    xml = Path(__file__).resolve().parents[2] / "scenes" / "face_envmap.xml"
    scene, _ = load_scene_file(xml, {"model": str(toy_model), "expression": "stretch", "envmap": "gradient",
                                     "width": "48", "height": "48", "spp": "4"})
    img = np.asarray(mi.render(scene))
    face = mf.load_model(toy_model)
    ref = face.render("stretch", camera=camera_from_sensor(scene.sensors()[0]), env="gradient", spp=4)
    m = ref[..., 3] > 0.999
    assert m.sum() > 200
    psnr = 10 * np.log10(ref[..., :3][m].max() ** 2 / ((img[..., :3] - ref[..., :3])[m] ** 2).mean())
    assert psnr > 35.0, psnr  # same kernel; differences: sample positions and the emitter's resampling
    # a target mesh of the wrong topology is refused with a clear error
    with pytest.raises(ValueError, match="template has"):
        load_scene_file(xml, {"model": str(toy_model), "envmap": "gradient", "target": str(_write_wrong(tmp_path))})


def _write_wrong(tmp_path):
    p = tmp_path / "wrong.npy"
    np.save(p, np.zeros((5, 3)))
    return p
