"""Sensors, the Python API, compositing, scene files and the facerf integrator plugin, on the toy model."""
import numpy as np
import pytest

from mifacerf.camera import Camera

from helpers.toy import make_toy


@pytest.fixture(scope="module")
def toy_model(tmp_path_factory, mi):
    import mifacerf
    from mifacerf.rendering.build import build_model

    mifacerf.register_plugins()  # the tests below load facerf_bsdf by name, as a Mitsuba user does
    root = tmp_path_factory.mktemp("toyapi")
    cap = make_toy(root, names=("neutral", "stretch"), size=40, n_pos=6, n_str=5, truth_registration=True).capture
    build_model(cap, root / "model")
    return root / "model"


def test_sensor_round_trip_and_projection(mi):
    from mifacerf.rendering.sensors import camera_from_sensor, sensor_dict

    cam = Camera.look_at("c", [0.3, 0.2, 1.2], [0, 0, 0], width=64, height=48, focal=90.0, principal_offset=(2, -1))
    scene = mi.load_dict({"type": "scene", "sensor": sensor_dict(cam, spp=64),
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
    with pytest.raises(Exception, match="parameter 'target'.*the template has"):
        load_scene_file(xml, {"model": str(toy_model), "envmap": "gradient", "target": str(_write_wrong(tmp_path))})


def _write_wrong(tmp_path):
    p = tmp_path / "wrong.npy"
    np.save(p, np.zeros((5, 3)))
    return p


@pytest.mark.parametrize("sampling", ["reflectance", "cosine"])
def test_bsdf_sample_pdf_consistent_chi2(toy_model, mi, sampling):
    """Mitsuba's own chi-square harness: facerf_bsdf's sample() follows its pdf().

    Mitsuba's BSDFAdapter uses an all-zero surface interaction and discards samples whose
    weight is 0; this material is legitimately 0 for light from behind (self-shadowed), so
    the adapter here evaluates at a real hit on the face and keeps every sample with pdf > 0.
    """
    import drjit as dr
    from mitsuba.chi2 import ChiSquareTest, SphericalDomain

    bsdf = mi.load_dict({"type": "facerf_bsdf", "model": str(toy_model), "expression": "stretch",
                         "sampling": sampling})
    from mifacerf.rendering.model import Model
    from mifacerf.rendering.scenefile import write_target_mesh
    import tempfile

    m = Model(toy_model)
    ply = write_target_mesh(tempfile.mktemp(suffix=".ply"), m.vertices[m.expression_index("stretch")], m.triangles)
    scene = mi.load_dict({"type": "scene", "face": {"type": "ply", "filename": str(ply)}})
    hit = scene.ray_intersect(mi.Ray3f(mi.Point3f(0.02, 0.03, 1.0), mi.Vector3f(0, 0, -1)))
    assert bool(hit.is_valid()[0])
    for wi in ([0, 0, 1], [0.6, 0.0, 0.8]):
        def make_si(n):
            si = dr.gather(mi.SurfaceInteraction3f, hit, dr.zeros(mi.UInt32, n))
            si.wi = mi.Vector3f(wi)
            return si

        def sample_func(sample):
            n = dr.width(sample)
            bs, weight = bsdf.sample(mi.BSDFContext(), make_si(n), sample[0], mi.Vector2f(sample[1], sample[2]))
            assert np.isfinite(np.asarray(weight)).all()
            return bs.wo, dr.select(bs.pdf > 0, 1.0, 0.0)

        def pdf_func(wo):
            return bsdf.pdf(mi.BSDFContext(), make_si(dr.width(wo)), wo)

        chi2 = ChiSquareTest(domain=SphericalDomain(), sample_func=sample_func, pdf_func=pdf_func,
                             sample_dim=3, sample_count=200_000, res=61, ires=4)
        assert chi2.run(), chi2.messages
        # and eval is not trivially zero: the face is lit from the front
        val = bsdf.eval(mi.BSDFContext(), make_si(1), mi.Vector3f(0, 0, 1))
        assert np.asarray(val).sum() > 0


def test_bsdf_under_a_directional_light_matches_the_olat_image(toy_model, mi, tmp_path):
    """A directional light exactly along a captured light direction reproduces that OLAT image."""
    from mifacerf.rendering.model import Model
    from mifacerf.rendering.scenefile import write_target_mesh
    from mifacerf.rendering.sensors import sensor_dict
    from mifacerf.synthetic.olat import render_olat

    from helpers.toy import deform, scene_for

    m = Model(toy_model)
    cap = m.cameras[1]
    cam = Camera("pin", cap.width, cap.height, [[cap.K[0, 0], 0, (cap.width - 1) / 2], [0, cap.K[0, 0], (cap.height - 1) / 2],
                                                 [0, 0, 1]], np.zeros(5), cap.R, cap.t)
    write_target_mesh(tmp_path / "face.ply", m.vertices[m.expression_index("neutral")], m.triangles)
    key = -cap.forward + np.array([0.0, 0.5, 0.0])  # a light from the camera's side, a little above
    d = m.light_directions[np.argmax(m.light_directions @ (key / np.linalg.norm(key)))]
    scene = mi.load_dict({"type": "scene", "integrator": {"type": "direct"}, "sensor": sensor_dict(cam, spp=4),
                          "face": {"type": "ply", "filename": str(tmp_path / "face.ply"),
                                   "bsdf": {"type": "facerf_bsdf", "model": str(toy_model), "expression": "neutral"}},
                          "sun": {"type": "directional", "direction": (-d).tolist(), "irradiance": 1.0}})
    img = np.asarray(mi.render(scene))[..., :3]
    ref = render_olat(mi.load_dict({"type": "scene", **scene_for(deform("neutral"), mi)}), cam,
                      d[None], spp=4)[0]
    mask = ref.sum(-1) > 1e-3
    assert mask.sum() > 100
    psnr = 10 * np.log10(ref[mask].max() ** 2 / ((img - ref)[mask] ** 2).mean())
    assert psnr > 27.0, psnr  # measured 30.9 dB on this toy (coarse template at the terminator)


def test_integrator_takes_methods_by_name(toy_model, mi):
    """The facerf integrator's method / rank / light_basis choose the renderer's registries' entries by name."""
    import mifacerf.plugins  # noqa: F401  (registers facerf)
    base = {"type": "facerf", "model": str(toy_model)}
    integrator = mi.load_dict(base)
    assert integrator.renderer(integrator.face).basis == "voronoi"
    integrator = mi.load_dict({**base, "light_basis": "hat"})
    chosen = integrator.renderer(integrator.face)
    assert (chosen.basis, chosen.method) == ("hat", "exact")
    with pytest.raises(Exception, match="unknown light basis method 'sh'; choose one of voronoi, hat"):
        mi.load_dict({**base, "light_basis": "sh"})
    with pytest.raises(Exception, match="unknown compression method 'svd'; choose one of exact, pca"):
        mi.load_dict({**base, "method": "svd", "rank": 4})


def test_scene_face_traces_the_renderers_surface(toy_model, mi):
    """``facerf_face`` hands Mitsuba the surface the Python renderer traces: at ``curved`` 3 the Phong surface
    (the template's triangles split 9 ways), mapped back to the template's triangles for shading. Its outline
    and colours then match ``Renderer(curved=3)``'s, and the flat mesh's outline does not (the chords' sag)."""
    import mifacerf as mf
    from mifacerf.rendering.renderer import Renderer
    from mifacerf.rendering.sensors import camera_from_sensor, sensor_dict

    face = mf.load_model(toy_model)
    cam = Camera.look_at("c", [0.25, 0.1, 0.9], [0, 0, 0], width=64, height=64, focal=200.0)
    imgs = {}
    for curved in (1, 3):
        scene = mi.load_dict({"type": "scene", "sensor": sensor_dict(cam, spp=64),
                              "env": {"type": "envmap", "filename": str(_env_file(face, mi))},
                              "face": {"type": "facerf_face", "model": str(toy_model), "expression": "stretch",
                                       "curved": curved},
                              # the background hidden: alpha is the face's coverage (with an environment
                              # showing, Mitsuba counts every ray as valid)
                              "integrator": {"type": "facerf", "nested": {"type": "path", "hide_emitters": True}}})
        shape = [s for s in scene.shapes() if s.id() == "face"][0]
        assert shape.geometry.n_skin_faces == curved ** 2 * len(face.model.triangles)
        imgs[curved] = np.asarray(mi.render(scene))
    cam = camera_from_sensor(scene.sensors()[0])
    face.renderer = Renderer(face.model, curved=3)
    ref = face.render("stretch", camera=cam, env="gradient", spp=64)
    a3, a1, ar = imgs[3][..., 3], imgs[1][..., 3], ref[..., 3]
    off3, off1 = np.abs(a3 - ar).sum(), np.abs(a1 - ar).sum()   # px of coverage, 64 spp each
    # measured: flat 16.8 px off, 16.8 px of area missing (the chords inside the Phong surface); Phong 2.7 px
    # off (sampling noise), 0.3 px of area
    assert a1.sum() - ar.sum() < -8.0 and abs(a3.sum() - ar.sum()) < 2.0, (a3.sum(), a1.sum(), ar.sum())
    assert off3 < 0.3 * off1, (off3, off1)
    m = (ar > 0.999) & (a3 > 0.999)
    psnr = 10 * np.log10(ref[..., :3][m].max() ** 2 / ((imgs[3][..., :3] - ref[..., :3])[m] ** 2).mean())
    assert psnr > 35.0, psnr
    # the material on the Phong surface: shaded at the template triangle of each sub-face, it agrees with the
    # exact path as well as on the flat mesh (a wrong sub-face map shades other triangles' fields)
    agree = {}
    for curved in (1, 3):
        scene = mi.load_dict({"type": "scene", "sensor": sensor_dict(cam, spp=64),
                              "env": {"type": "envmap", "filename": str(_env_file(face, mi))},
                              "integrator": {"type": "direct", "hide_emitters": True},
                              "face": {"type": "facerf_face", "model": str(toy_model), "expression": "stretch",
                                       "curved": curved, "bsdf": {"type": "facerf_bsdf"}}})
        img = np.asarray(mi.render(scene))
        k = (imgs[curved][..., 3] > 0.999) & (img[..., 3] > 0.999)
        agree[curved] = 10 * np.log10(imgs[curved][..., :3][k].max() ** 2
                                      / ((img[..., :3] - imgs[curved][..., :3])[k] ** 2).mean())
    assert agree[3] > agree[1] - 1.0 and agree[3] > 25.0, agree
    with pytest.raises(Exception, match="parameter 'curved'"):
        mi.load_dict({"type": "scene", "face": {"type": "facerf_face", "model": str(toy_model), "curved": 0}})



def _env_file(face, mi):
    """The generated gradient environment's EXR (what ``-D envmap=gradient`` loads)."""
    from mifacerf.environment import cache_dir, generated

    generated("gradient")
    return cache_dir() / "environments" / "gradient-128.exr"


def test_the_scenes_envmap_lights_the_exact_path_as_its_file_does(toy_model, mi, tmp_path):
    """The facerf integrator lit by the scene's envmap emitter renders what it renders reading the same file
    itself (``environment=FILE``): the emitter is sampled in the layout Mitsuba reads the map in. (Sampled at
    latlong_grid's texel centres, as until 2026-12-04, the rows moved up to half a row towards the poles.)"""
    from mifacerf.imageio import write_exr
    from mifacerf.rendering.sensors import sensor_dict

    rng = np.random.default_rng(5)
    data = np.full((64, 128, 3), 0.05, np.float32)
    for _ in range(12):            # bright windows of a few texels near the zenith, as a captured probe's skylights
        r, c = rng.integers(1, 8), rng.integers(0, 126)
        data[r:r + 2, c:c + 2] = rng.uniform(5, 40)
    path = tmp_path / "windows.exr"
    write_exr(path, data, half=False)
    cam = Camera.look_at("c", [0.1, 0.1, 1.0], [0, 0, 0], width=40, height=40, focal=160.0)
    imgs = {}
    for how, integ in (("emitter", {"type": "facerf"}), ("file", {"type": "facerf", "environment": str(path)})):
        scene = mi.load_dict({"type": "scene", "sensor": sensor_dict(cam, spp=4), "integrator": integ,
                              "env": {"type": "envmap", "filename": str(path)},
                              "face": {"type": "facerf_face", "model": str(toy_model)}})
        imgs[how] = np.asarray(mi.render(scene, seed=3))
    a, b = imgs["emitter"], imgs["file"]
    m = (a[..., 3] > 0.999) & (b[..., 3] > 0.999)
    assert m.sum() > 200
    psnr = 10 * np.log10(b[..., :3][m].max() ** 2 / ((a - b)[..., :3][m] ** 2).mean())
    ratio = a[..., :3][m].mean() / b[..., :3][m].mean()
    assert psnr > 50 and abs(ratio - 1) < 0.003, (psnr, ratio)
