"""Scene files as a Mitsuba user loads them: every ``scenes/*.xml`` with plain ``mi.load_file`` (after
``import mifacerf``) on the toy model, rendered small; the face as a ``facerf_face`` shape in a dict
scene; animation through ``mi.traverse`` without reloading or recompiling; bad input named."""
from pathlib import Path

import numpy as np
import pytest

SCENES = sorted((Path(__file__).resolve().parents[2] / "scenes").glob("*.xml"))


@pytest.fixture(scope="module")
def plugins(mi):
    import mifacerf

    return mifacerf.register_plugins()


def test_there_are_scene_examples():
    names = {p.stem for p in SCENES}
    assert {"face_envmap", "face_with_objects", "face_spot", "face_turntable"} <= names
    for p in SCENES:   # each documented in a comment at its top
        assert p.read_text().lstrip().startswith("<!--"), p


@pytest.mark.parametrize("xml", SCENES, ids=[p.stem for p in SCENES])
def test_every_scene_loads_with_plain_mitsuba_and_renders(xml, toy_model, plugins):
    mi = plugins
    scene = mi.load_file(str(xml), model=str(toy_model.root), width=32, height=32, spp=4)
    img = np.asarray(mi.render(scene))
    assert img.shape[:2] == (32, 32) and np.isfinite(img).all()
    # the face is there: rays through the image centre hit the facerf_face shape
    from mifacerf.plugins.facerf_shape import FaceShape

    faces = [s for s in scene.shapes() if isinstance(s, FaceShape)]
    assert len(faces) == 1
    sensor = scene.sensors()[0]
    ray, _ = sensor.sample_ray(0.0, 0.5, mi.Point2f(0.5, 0.5), mi.Point2f(0.5, 0.5))
    hit = scene.ray_intersect(ray)
    assert bool(hit.is_valid()[0]) and hit.shape == mi.ShapePtr(faces[0])
    assert img[12:20, 12:20, :3].mean() > 1e-3   # and it is lit


def test_a_dict_scene_needs_only_the_model_folder(toy_model, plugins):
    mi = plugins
    from mifacerf.rendering.sensors import sensor_dict

    cam = _camera(32)
    scene = mi.load_dict({"type": "scene", "integrator": {"type": "facerf"}, "sensor": sensor_dict(cam, spp=4),
                          "sky": {"type": "constant", "radiance": 1.0},
                          "face": {"type": "facerf_face", "model": str(toy_model.root), "expression": "stretch",
                                   "bsdf": {"type": "facerf_bsdf"}}})
    img = np.asarray(mi.render(scene))
    import mifacerf as mf
    from mifacerf.rendering.sensors import camera_from_sensor

    ref = mf.load_model(toy_model.root).render("stretch", camera=camera_from_sensor(scene.sensors()[0]),
                                               env=_constant_env(), spp=4)
    from scipy.ndimage import binary_erosion

    m = binary_erosion(ref[..., 3] > 0.999)   # away from the limb (other sample positions, the sky behind)
    assert m.sum() > 100
    psnr = 10 * np.log10(ref[..., :3][m].max() ** 2 / ((img[..., :3] - ref[..., :3])[m] ** 2).mean())
    assert psnr > 35.0, psnr


def _camera(size):
    from mifacerf.camera import Camera

    return Camera.look_at("c", [0.1, 0.15, 1.0], [0, 0, 0], width=size, height=size, focal=size * 4.5)


def _constant_env():
    from mifacerf.environment import Environment

    return Environment(np.ones((32, 64, 3), np.float32), "constant")


def _kernels_compiled(history) -> int:
    import drjit as dr

    return sum(1 for k in history if k.get("type") == dr.KernelType.JIT and not k.get("cache_hit", False))


@pytest.mark.parametrize("integrator,curved", [("facerf", 1), ("direct", 1), ("direct", 3)])
def test_animation_through_traverse_reuses_compiled_kernels(toy_model, plugins, integrator, curved):
    """Expression weights, a target mesh and the head's pose set through mi.traverse; every frame after the
    first launches kernels but compiles none (Dr.Jit's kernel history), on the flat and the Phong skin."""
    import drjit as dr

    mi = plugins
    from mifacerf.rendering.sensors import sensor_dict

    m = toy_model
    cam = _camera(24)
    scene = mi.load_dict({"type": "scene", "integrator": {"type": integrator}, "sensor": sensor_dict(cam, spp=2),
                          "sky": {"type": "constant", "radiance": 1.0},
                          "face": {"type": "facerf_face", "model": str(m.root), "curved": curved,
                                   "bsdf": {"type": "facerf_bsdf"}}})
    params = mi.traverse(scene)
    assert {"face.expression", "face.target", "face.to_world"} <= set(params.keys())
    shape = [s for s in scene.shapes() if s.id() == "face"][0]
    stretch = m.vertices[m.expression_index("stretch")]
    rng = np.random.default_rng()   # new numbers every run: Dr.Jit's on-disk kernel cache cannot hide a baked one
    a, b, c = rng.uniform(0.1, 0.9, 3)
    turn = [shape.transform(mi.ScalarTransform4f().rotate([0, 1, 0], x)) for x in rng.uniform(5, 15, 2) * [1, -1]]
    frames = [("expression", shape.weights({"neutral": a, "stretch": 1 - a}), None),
              ("expression", shape.weights({"stretch": 1.0}), None),
              ("target", (b * stretch + (1 - b) * m.vertices[0]).reshape(-1).tolist(), None),
              ("to_world", None, turn[0]),
              ("expression", shape.weights({"neutral": c, "stretch": 1 - c}), turn[1])]
    images, compiled, launched = [], [], []
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        for key, value, pose in frames:
            dr.kernel_history()   # clears it
            if value is not None:
                params[f"face.{key}"] = value
            if pose is not None:
                params["face.to_world"] = pose
            params.update()
            images.append(np.asarray(mi.render(scene, seed=0)))
            hist = dr.kernel_history()
            compiled.append(_kernels_compiled(hist))
            launched.append(sum(1 for k in hist if k.get("type") == dr.KernelType.JIT))
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    assert all(n > 0 for n in launched), launched
    assert compiled[1:] == [0] * (len(frames) - 1), compiled
    # and the frames differ as the pose does: stretch vs neutral, turned vs not
    assert np.abs(images[1] - images[0]).max() > 1e-3
    assert np.abs(images[3] - images[2]).max() > 1e-3
    # the mesh follows: the target set is the shape's skin
    v = np.asarray(params["face.vertex_positions"]).reshape(-1, 3)[: m.n_vertices]
    R = np.asarray(turn[1].matrix).reshape(4, 4)[:3, :3]
    blend = c * m.vertices[m.expression_index("neutral")] + (1 - c) * stretch
    np.testing.assert_allclose(v, blend @ R.T, atol=1e-5)


def test_bad_input_names_the_parameter(toy_model, plugins, tmp_path):
    mi = plugins
    xml = SCENES[0]
    with pytest.raises(Exception, match="model folder .*nowhere.* not found"):
        mi.load_file(str(xml), model=str(tmp_path / "nowhere"))
    with pytest.raises(Exception, match="parameter 'expression'.*unknown expression.*frown"):
        mi.load_file(str(xml), model=str(toy_model.root), expression="frown")
    np.save(tmp_path / "wrong.npy", np.zeros((5, 3)))
    with pytest.raises(Exception, match="parameter 'target'.*5 vertices; the template has"):
        mi.load_file(str(xml), model=str(toy_model.root), target=str(tmp_path / "wrong.npy"))
    scene = mi.load_file(str(xml), model=str(toy_model.root), width=16, height=16)
    params = mi.traverse(scene)
    with pytest.raises(ValueError, match="'face.target'.*template has"):
        params["face.target"] = mi.Float(np.zeros(30, np.float32))
        params.update()
    params = mi.traverse(scene)
    with pytest.raises(ValueError, match="'face.expression'.*3 values given, the model has 2"):
        params["face.expression"] = [0.2, 0.3, 0.5]
        params.update()
    params = mi.traverse(scene)
    with pytest.raises(ValueError, match="face.to_world.*rigid"):
        params["face.to_world"] = mi.ScalarTransform4f().scale(2.0)
        params.update()


def test_bad_emitters_and_plugin_parameters_name_themselves(toy_model, plugins):
    """An emitter the exact path cannot evaluate (point, directional) in a facerf scene: one line naming it and
    the material to use instead; beside an environment, a RenderWarning that the face ignores it. Bad values of
    the plugins' method and skip parameters: one line naming the parameter."""
    from mifacerf.camera import Camera
    from mifacerf.rendering.renderer import RenderWarning
    from mifacerf.rendering.sensors import sensor_dict

    mi = plugins
    cam = Camera.look_at("e", [0.12, 0.1, 1.0], [0, 0, 0], width=8, height=8, focal=32.0)
    face = {"type": "facerf_face", "model": str(toy_model.root), "bsdf": {"type": "facerf_bsdf"}}
    lamp = {"type": "point", "position": [0, 0, 2], "intensity": 1.0}

    def scene(integrator, **emitters):
        return mi.load_dict({"type": "scene", "integrator": integrator, "sensor": sensor_dict(cam, spp=1),
                             "face": face, **emitters})

    with pytest.raises(RuntimeError) as info:
        mi.render(scene({"type": "facerf"}, lamp=lamp, sun={"type": "directional", "direction": [0, 0, -1]}))
    message = str(info.value.__cause__)
    assert "needs an environment" in message and "'lamp' (PointLight)" in message and "facerf_bsdf" in message
    assert "\n" not in message
    with pytest.warns(RenderWarning, match="'lamp' \\(PointLight\\) light the rest of the scene but not the face"):
        mi.render(scene({"type": "facerf"}, lamp=lamp, sky={"type": "constant"}))
    for integrator, bsdf, match in (
            ({"type": "facerf", "light_epsilon": -1.0}, {}, "parameter 'light_epsilon' must be >= 0"),
            ({"type": "facerf", "depth_tolerance": 0.0}, {}, "parameter 'depth_tolerance' must be > 0"),
            ({"type": "facerf", "lights": "0,x"}, {}, "parameter 'lights': light indices"),
            ({"type": "direct"}, {"light_basis": "nearest"}, "nearest.*voronoi"),
            ({"type": "direct"}, {"depth_tolerance": -1.0}, "depth_tolerance must be > 0"),
            ({"type": "direct"}, {"visibility_rule": "beam"}, "parameter 'visibility_rule': 'beam' is not one of"),
            ({"type": "direct"}, {"sampling": "fancy"}, "parameter 'sampling': 'fancy' is not one of")):
        with pytest.raises(Exception, match=match):
            mi.load_dict({"type": "scene", "integrator": integrator, "sensor": sensor_dict(cam, spp=1),
                          "face": {**face, "bsdf": {"type": "facerf_bsdf", **bsdf}}, "sky": {"type": "constant"}})


def test_the_integrator_takes_the_renderers_skips_by_name(toy_model, plugins):
    """light_epsilon, depth_tolerance from the scene reach the integrator's Renderer (the Python API's names)."""
    from mifacerf.camera import Camera
    from mifacerf.rendering.sensors import sensor_dict

    mi = plugins
    cam = Camera.look_at("e", [0.12, 0.1, 1.0], [0, 0, 0], width=8, height=8, focal=32.0)
    sc = mi.load_dict({"type": "scene", "sensor": sensor_dict(cam, spp=1), "sky": {"type": "constant"},
                       "integrator": {"type": "facerf", "light_epsilon": 0.0, "depth_tolerance": 0.002},
                       "face": {"type": "facerf_face", "model": str(toy_model.root)}})
    img = np.asarray(mi.render(sc))
    r = sc.integrator().renderer(sc.integrator().face)
    assert r.light_epsilon == 0.0 and r.depth_tolerance == 0.002 and np.isfinite(img).all()
    assert sc.integrator().stats.lights_skipped == 0


@pytest.mark.parametrize("xml", SCENES, ids=[p.stem for p in SCENES])
def test_every_scene_is_well_formed_xml_and_renders_through_mifacerf_render(xml, toy_model, tmp_path):
    """Each scene file is strict XML (a "--" in a comment is not; two of them had "--spp N" there, and
    ``mifacerf render``, the command their own header gives, refused them) and renders through that command."""
    import xml.etree.ElementTree as ET

    from click.testing import CliRunner

    from mifacerf.rendering.cli import render_cmd

    ET.parse(xml)
    out = tmp_path / f"{xml.stem}.exr"
    r = CliRunner().invoke(render_cmd, [str(xml), "-D", f"model={toy_model.root}", "-D", "width=12", "-D", "height=12",
                                        "--spp", "1", "-o", str(out)])
    assert r.exit_code == 0, r.output
    assert out.exists()


def test_a_comment_mitsuba_accepts_does_not_stop_mifacerf_render(tmp_path):
    """Mitsuba's parser takes a "--" inside a comment; reading the scene's defaults does too (the comments
    are set aside), and a file that is broken elsewhere is still named."""
    from mifacerf.rendering.scenefile import SceneError, scene_defaults

    ok = tmp_path / "ok.xml"
    ok.write_text('<!-- render with --spp 16 -->\n<scene version="3.0.0"><default name="spp" value="4"/></scene>\n')
    assert scene_defaults(ok) == {"spp": "4"}
    bad = tmp_path / "bad.xml"
    bad.write_text('<scene version="3.0.0"><default name="spp" value="4"></scene>\n')
    with pytest.raises(SceneError, match="bad.xml: not a well-formed scene file"):
        scene_defaults(bad)
    both = tmp_path / "both.xml"      # a "--" comment over two lines and a broken tag: named at the tag's line
    both.write_text('<!-- a\n -- b -->\n<scene version="3.0.0">\n<default name="spp" value="4">\n</scene>\n')
    with pytest.raises(SceneError, match=r"both.xml: not a well-formed scene file \(mismatched tag: line 5"):
        scene_defaults(both)


def test_mifacerf_render_takes_the_familiar_options(toy_model, tmp_path):
    from click.testing import CliRunner

    from mifacerf.rendering.cli import render_cmd

    out = tmp_path / "f.exr"
    r = CliRunner().invoke(render_cmd, [str(SCENES[0]), "-D", f"model={toy_model.root}", "-D", "width=16",
                                        "-D", "height=16", "-D", "envmap=gradient", "--spp", "1", "-t", "2",
                                        "-o", str(out)])
    assert r.exit_code == 0, r.output
    assert out.exists() and out.with_suffix(".png").exists()
    r = CliRunner().invoke(render_cmd, [str(SCENES[0]), "-D", "modle=x"])
    assert r.exit_code != 0 and "no parameter 'modle'" in r.output


def test_material_agrees_with_the_exact_path_under_an_environment(toy_model, plugins):
    """facerf_bsdf under Mitsuba's direct integrator against the facerf integrator under a broad environment
    (sky): with the same light rule (voronoi) and the captured self-visibility divided out inside each triangle
    they agree to within 2 % (measured 04:30: 29.0 dB against a 24.5 dB floor, mean 1.006 — the material's own
    evaluation, without shadow rays, is 0.7 % brighter on this toy). Under the 'interior' environment (small
    bright sources) this toy's 30 light cells, 37° wide, are too coarse: the shadow rays resolve which part of a
    cell the bright source sits in, the exact path only the cell's sum, and the material comes out 2.8 % brighter
    (docs/rendering.md); until 2026-12-02 this test used 'interior' and passed with the per-vertex visibility,
    whose double shadowing (2 %) offset that. Before the material took the exact path's rule (the 'hat' rule)
    this toy scored 25 dB and 6 % darker under 'interior' (measured 22:59 with --exact-basis hat)."""
    from mifacerf.evaluation.material import compare

    rows = compare(toy_model.root, "sky", ["direct"], size=32, spp=64)
    r = rows[1]
    assert r["psnr"] >= min(30.0, r["noise_floor"] - 1.0), rows
    assert abs(r["brightness"] - 1.0) < 0.02, rows


def test_light_rules_of_the_material(mi):
    """The material's light rule by name: voronoi = the nearest light (exact at and near every light), hat =
    barycentric; an unknown name lists the choices."""
    from mifacerf.rendering.light_interp import LightInterpolator

    rng = np.random.default_rng(3)
    dirs = rng.normal(size=(40, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    q = rng.normal(size=(2000, 3))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    vor = LightInterpolator(dirs, method="voronoi")
    idx, w = vor.weights(q)
    np.testing.assert_array_equal(idx[:, 0], np.argmax(q @ dirs.T, axis=1))
    assert (w[:, 0] == 1).all()
    ids, wj = vor.to_device().weights_jit(mi.Vector3f(q.T.astype(np.float32)))
    np.testing.assert_array_equal(np.asarray(ids[0]), idx[:, 0])
    hat_idx, hat_w = LightInterpolator(dirs, method="hat").weights(dirs)
    np.testing.assert_allclose(hat_w.max(axis=1), 1.0, atol=1e-9)
    with pytest.raises(ValueError, match="unknown light basis method 'sh'; choose one of voronoi, hat"):
        LightInterpolator(dirs, method="sh")


def test_the_integrator_plans_once_per_frame_and_rebuilds_the_basis_only_when_the_emitter_changes(
        toy_model, plugins, monkeypatch):
    """One ``mi.render`` plans and lights the frame once (Mitsuba's base render calls the Python override
    again; it had planned twice), and the rotated light basis of the scene's environment is built once for
    an animation, again when the emitter's parameters change (and the image follows them)."""
    mi = plugins
    from mifacerf.plugins.facerf_integrator import FaceRFIntegrator
    from mifacerf.rendering import lighting
    from mifacerf.rendering.sensors import sensor_dict

    scene = mi.load_dict({"type": "scene", "integrator": {"type": "facerf"}, "sensor": sensor_dict(_camera(24), spp=2),
                          "sky": {"type": "constant", "radiance": 1.0},
                          "face": {"type": "facerf_face", "model": str(toy_model.root), "bsdf": {"type": "facerf_bsdf"}}})
    calls = {"prepare": 0, "basis": 0}
    prepare, basis_init = FaceRFIntegrator.prepare, lighting.RotatedLightBasis.__init__

    def counted_prepare(self, *a):
        calls["prepare"] += 1
        return prepare(self, *a)

    def counted_basis(self, *a, **k):
        calls["basis"] += 1
        return basis_init(self, *a, **k)

    monkeypatch.setattr(FaceRFIntegrator, "prepare", counted_prepare)
    monkeypatch.setattr(lighting.RotatedLightBasis, "__init__", counted_basis)
    params = mi.traverse(scene)
    face = [s for s in scene.shapes() if s.id() == "face"][0]
    images = []
    for a in (1.0, 0.5, 0.0):
        params["face.expression"] = face.weights({"neutral": a, "stretch": 1 - a})
        params.update()
        images.append(np.asarray(mi.render(scene)))
    assert calls == {"prepare": 3, "basis": 1}, calls
    params["sky.radiance.value"] = 2.0     # the emitter changed: a new basis, and twice the light
    params.update()
    brighter = np.asarray(mi.render(scene))
    assert calls == {"prepare": 4, "basis": 2}, calls
    m = images[-1][..., 3] > 0.999
    assert m.sum() > 50
    np.testing.assert_allclose(brighter[..., :3][m].mean() / images[-1][..., :3][m].mean(), 2.0, rtol=1e-3)


def test_the_material_reads_each_source_once_and_keeps_it(toy_model, mi):
    """A source added by a later pose is uploaded beside the ones already read, to the same arrays and
    sampling table as a state made with all of them at once (before, every source was read again and its
    response per light, the sampling table's, summed in once more each time)."""
    from mifacerf.rendering.material import MaterialState

    m = toy_model
    T, S = m.n_vertices, len(m.expressions)
    n, s = m.expression_index("neutral"), m.expression_index("stretch")
    only = np.zeros((T, S)); only[:, n] = 1
    both = np.zeros((T, S)); both[:, n] = 0.5; both[:, s] = 0.5
    later = MaterialState(m, m.vertices[n], only, self_visibility=False)
    reads = []
    field = type(m).field
    try:
        type(m).field = lambda self, *a: (reads.append(a), field(self, *a))[1]
        later.update(m.vertices[s], both)
        later.update(m.vertices[n], only)
        later.update(m.vertices[s], both)
    finally:
        type(m).field = field
    assert sorted({a[0] for a in reads}) == [s]           # only the new source's fields were read, once each
    assert len(reads) == sum(m.has_field(s, c) for c in range(len(m.cameras)))
    fresh = MaterialState(m, m.vertices[s], both, self_visibility=False)
    for name in ("texel_index", "field_offset", "texel_depth", "texel_outline", "rf"):
        np.testing.assert_array_equal(np.asarray(getattr(later, name)), np.asarray(getattr(fresh, name)), name)
    for k in (n, s):
        np.testing.assert_allclose(later._lum[k], fresh._lum[k], rtol=1e-6)
    np.testing.assert_allclose(np.asarray(later.sampling.prob), np.asarray(fresh.sampling.prob), rtol=1e-5)
