"""Eyes, teeth and the mouth's interior (paper §6.3) on the synthetic subject at the ``tiny`` preset:
synth → register → build → render, against path-traced ground truth.

The rendering of these parts is checked end to end here because it needs everything before it:
reference expressions chosen by visibility, their fields cut out at build time, and the target's
part transforms and geometry for the ray-traced visibility of every light.
"""
import numpy as np
import pytest

EXPRESSIONS = ["neutral", "viseme_aa", "teeth_bared", "eyes_closed"]


@pytest.fixture(scope="module")
def built_root(tmp_path_factory):
    """A folder with ``synth/`` (tiny capture + truth, registered) and ``model/`` built from it."""
    from mifacerf.registration import register_capture
    from mifacerf.rendering.build import build_model
    from mifacerf.synthetic.synth import synthesize

    root = tmp_path_factory.mktemp("parts")
    cap = synthesize(root / "synth", preset="tiny", expressions=EXPRESSIONS, progress=False)
    register_capture(cap, progress=False)
    build_model(cap, root / "model")
    return root


@pytest.fixture(scope="module")
def built(built_root):
    import mifacerf as mf
    from mifacerf.synthetic.truth_scene import TruthRenderer

    return mf.load_model(built_root / "model"), TruthRenderer.from_synth(built_root / "synth")


def part_pixels(tr, cam, env, names):
    from mifacerf.evaluation.masks import classify_pixels
    from mifacerf.synthetic.scene import PART_IDS

    classes = classify_pixels(tr.scene(env), cam)
    return np.isin(classes["part"], [PART_IDS[n] for n in names]).all(axis=2)


@pytest.mark.slow
def test_references_are_where_each_part_is_most_visible(built):
    """The paper's one reference per part, and the extra sources a dominant expression may use."""
    face, _ = built
    refs = face.model.references
    assert set(refs) == {"eyes", "teeth", "mouth"}
    assert refs["teeth"] == "teeth_bared"            # lips drawn back
    assert refs["mouth"] == "viseme_aa"              # the open mouth shows the interior
    assert refs["eyes"] != "eyes_closed"
    # other sources: where the part is seen at all (≥ 10 % of the reference's pixels); closed lips hide the teeth
    sources = face.model.part_sources
    assert set(sources["teeth"]) == {"teeth_bared", "viseme_aa"}
    assert refs["mouth"] in sources["mouth"] and refs["eyes"] in sources["eyes"]


@pytest.mark.slow
def test_teeth_and_eyes_against_truth(built):
    """A captured expression (open mouth) from a capture camera: its teeth and mouth come from its own data
    (it dominates the frame and shows them), placed by the registered lower-teeth transform (jaw
    rotation) and shadowed by the target's lips; the eyes with a re-synthesised cornea."""
    from mifacerf.environment import resolve
    from mifacerf.evaluation.metrics import psnr

    face, tr = built
    env = resolve("sky")
    cam = face.model.cameras[1]
    truth = tr.render(tr.expressions["viseme_aa"], cam, env, spp=256, seed=3)
    tr.scene(env).set_pose(tr.subject.pose(tr.expressions["viseme_aa"]))
    img = face.render("viseme_aa", camera=cam, env=env, spp=4)
    assert np.isfinite(img).all()
    teeth = part_pixels(tr, cam, env, ["teeth_upper", "teeth_lower"]) & (img[..., 3] > 0.999)
    eyes = part_pixels(tr, cam, env, ["eye_left", "eye_right"]) & (img[..., 3] > 0.999)
    assert teeth.sum() >= 20 and eyes.sum() >= 20
    # measured 17.5 dB on the teeth (60 px; 12.3 dB from the teeth_bared reference before a captured
    # expression rendered its own teeth) and 20.9 dB on the eyes (29 px) at this size (128 px, 48 lights)
    assert psnr(img, truth, teeth) > 15.5
    assert psnr(img, truth, eyes) > 19.0


def test_frame_reference_picks_a_dominant_source_or_the_reference():
    from mifacerf.rendering.parts import frame_reference

    refs = {"eyes": "wide", "teeth": "bared", "mouth": "open"}
    sources = {"eyes": ["wide", "smile"], "teeth": ["bared", "open"], "mouth": ["open", "bared"]}
    w = {"teeth": {"open": 0.7, "bared": 0.3}, "mouth": {"open": 0.2, "bared": 0.8}, "eyes": {"smile": 0.4}}
    assert frame_reference("teeth_lower", refs, sources, w) == "open"       # dominant and stored
    assert frame_reference("mouth_interior", refs, sources, w) == "bared"
    assert frame_reference("eye_left", refs, sources, w) == "wide"         # no source reaches 1/2
    assert frame_reference("teeth_upper", refs, sources, {"teeth": {"closed": 1.0}}) == "bared"  # not stored
    assert frame_reference("teeth_upper", refs) == "bared"                 # no weights: the paper's choice
    # a model built before the mouth had its own reference: the interior comes from the teeth's
    assert frame_reference("mouth_interior", {"teeth": "bared"}, None, None) == "bared"


@pytest.mark.slow
def test_evaluation_report(built_root, tmp_path):
    """``mifacerf evaluate``'s measurement runs end to end: every case kind, per-case truth noise floors, the
    noise-corrected PSNR never below the plain one when the truth has noise, the picture written."""
    from mifacerf.evaluation.render_cases import evaluate

    root = built_root
    report = evaluate(root / "synth", root / "model", envs=("gradient",), n=1, seed=7, spp_truth=32, size=48,
                      pictures=tmp_path / "cases.png")
    assert [c["case"] for c in report["cases"]] == ["a", "b", "c", "d"]
    for c in report["cases"]:
        assert np.isfinite(c["psnr"]) and np.isfinite(c["truth_noise_psnr"]) and c["psnr"] > 10
        assert c["psnr_noise_corrected"] >= c["psnr"]
        assert c["fields"] > 0 and c["seconds"] > 0
        # what the user sees: composite over the plate, silhouette, the truth's foreground left uncovered
        assert np.isfinite(c["psnr_composite"]) and c["psnr_composite"] > 5
        assert 0 < c["silhouette_iou"] <= 1 and 0 <= c["uncovered"] < 1
    for k in ("psnr_composite", "silhouette_iou", "uncovered"):
        assert report["summary"]["a"][k]["n"] == 1
    assert report["truth_noise_psnr"] == min(c["truth_noise_psnr"] for c in report["cases"])
    assert set(report["summary"]) == {"a", "b", "c", "d"}
    assert (tmp_path / "cases.png").stat().st_size > 1000


@pytest.mark.slow
def test_facerf_direct_starts_part_rays_as_the_exact_path(built_root):
    """facerf_direct's shadow rays from an eye start PART_RAY_OFFSET out along the eye's sphere normal (the
    exact path's rule, PartFrame.shade), snapped towards an environment to the stage light the material
    answers with (the exact path's one ray per light); from the skin as Mitsuba's; ``part_rays`` false:
    Mitsuba's everywhere, and the skin's pixels are the same either way."""
    import drjit as dr

    from mifacerf.camera import Camera
    from mifacerf.evaluation import material as M
    from mifacerf.environment import cache_dir, generated
    from mifacerf.plugins import facerf_direct as FD
    from mifacerf.rendering.parts import PART_RAY_OFFSET
    from mifacerf.variant import ensure_plugins

    mi = ensure_plugins()
    generated("sky")
    emitter = {"type": "envmap", "filename": str(cache_dir() / "environments" / "sky-128.exr")}
    size = 64
    cam = Camera.look_at("eval", [0.02, 0.03, 0.45], [0, 0.03, 0], width=size, height=size, focal=size * 4.0)
    model = built_root / "model"
    scene = M._scene(mi, model, {"type": "facerf_direct"}, emitter, cam, 4, None)
    label, face = M._labels(mi, scene, size)
    eye = np.argwhere(label == 1)                                   # eye_left
    assert len(eye) > 3
    i, j = eye[len(eye) // 2]
    uv = mi.Point2f(mi.Float([(j + 0.5) / size, 0.5]), mi.Float([(i + 0.5) / size, 0.5]))
    ray, _ = scene.sensors()[0].sample_ray(0.0, 0.5, uv, mi.Point2f(0.5, 0.5))
    si = scene.ray_intersect(ray)
    ds, _ = scene.sample_emitter_direction(si, mi.Point2f(0.3, 0.6), False)
    parts = FD._part_faces(scene)
    assert len(parts) == 1
    r = FD.part_ray(si, ds, parts)
    bsdf = parts[0][2]
    centre = np.array([np.asarray(bsdf.parts.eye_centre)[k] for k in range(3)])   # eye_left: PARTS index 0
    p = np.array([np.asarray(si.p.x)[0], np.asarray(si.p.y)[0], np.asarray(si.p.z)[0]])
    o = np.array([np.asarray(r.o.x)[0], np.asarray(r.o.y)[0], np.asarray(r.o.z)[0]])
    n = (p - centre) / np.linalg.norm(p - centre)
    np.testing.assert_allclose(o, p + PART_RAY_OFFSET * n, atol=2e-6)
    np.testing.assert_allclose([np.asarray(r.d.x)[0], np.asarray(r.d.y)[0], np.asarray(r.d.z)[0]],
                               [np.asarray(ds.d.x)[0], np.asarray(ds.d.y)[0], np.asarray(ds.d.z)[0]], atol=1e-6)
    # snapped (towards the environment): along the stage light nearest to ds.d in the eye's reference frame,
    # the light stage turned back into the target (NumPy, from the material's own transform table)
    snapped = FD.part_ray(si, ds, parts, snap=True)
    A = np.asarray(bsdf.parts.table)[:12].reshape(3, 4)[:, :3]      # eye_left's row: target → reference
    d = np.array([np.asarray(ds.d.x)[0], np.asarray(ds.d.y)[0], np.asarray(ds.d.z)[0]])
    import mifacerf as mf

    dirs = mf.load_model(model).model.light_directions
    want = A.T @ dirs[np.argmax(dirs @ (A @ d))]
    got = np.array([np.asarray(snapped.d.x)[0], np.asarray(snapped.d.y)[0], np.asarray(snapped.d.z)[0]])
    np.testing.assert_allclose(got, want / np.linalg.norm(want), atol=1e-5)
    assert np.linalg.norm(got - d) > 1e-4                           # not the sampled direction itself
    np.testing.assert_allclose([np.asarray(snapped.o.x)[0]], [o[0]], atol=1e-7)
    spawned = si.spawn_ray_to(ds.p)                                 # the second ray (background): Mitsuba's own
    assert np.asarray(r.o.x)[1] == np.asarray(spawned.o.x)[1]
    on = np.asarray(mi.render(scene, seed=3))
    off = np.asarray(mi.render(M._scene(mi, model, {"type": "facerf_direct", "part_rays": False}, emitter, cam, 4,
                                        None), seed=3))
    skin = label == 0
    np.testing.assert_array_equal(on[skin], off[skin])
    assert dr.width(si.p) == 2


@pytest.mark.slow
def test_part_views_are_uploaded_once_for_frames_that_read_them(built, monkeypatch):
    """Consecutive frames that read the same part views (here two blends from one camera) share the device
    copies of the views' texels (PartFrame's cache, held by the renderer), and render what they render with the
    copies made anew for every frame (the cache off), bit for bit."""
    from mifacerf.environment import resolve
    from mifacerf.rendering import parts as P

    face, _ = built
    env = resolve("sky")
    cam = face.model.cameras[1]
    made = []
    upload = P.PartFrame._upload_views
    monkeypatch.setattr(P.PartFrame, "_upload_views", staticmethod(lambda *a: made.append(1) or upload(*a)))
    blends = [{"viseme_aa": 0.7, "neutral": 0.3}, {"viseme_aa": 0.6, "neutral": 0.4}]
    cached = [face.render(b, camera=cam, env=env, spp=2) for b in blends]
    assert len(made) == 1, made                       # the second frame's views came from the cache
    monkeypatch.setattr(P, "PART_FRAME_CACHE", 0)
    face.renderer._part_frames.clear()
    fresh = [face.render(b, camera=cam, env=env, spp=2) for b in blends]
    assert len(made) == 3
    for a, b in zip(cached, fresh):
        np.testing.assert_array_equal(a, b)
    assert np.abs(cached[0] - cached[1]).max() > 1e-4  # and the two frames are two frames
