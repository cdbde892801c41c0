"""Eyes, teeth and the mouth interior under the image-based material (:class:`mifacerf.rendering.parts.PartMaterial`).

A stand-in model holds one part, the left eye (a sphere), captured by three cameras with a field whose
value for light ``l`` is ``l + 1`` everywhere: under any light direction the material must answer the
value of the stage light nearest to that direction *in the reference's frame* (the target's eye is
turned and moved against the reference's), on every point of the target eye the cameras saw.
"""
from types import SimpleNamespace

import numpy as np

from mifacerf.camera import Camera
from mifacerf.geometry.meshscene import MeshScene
from mifacerf.rendering.parts import PARTS, PartMaterial, sphere_mesh

RADIUS = 0.012


def rotation(axis, deg):
    axis = np.asarray(axis, np.float64) / np.linalg.norm(axis)
    a = np.radians(deg)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K


def stand_in_model(n_lights: int = 12):
    rng = np.random.default_rng(5)
    dirs = rng.normal(size=(n_lights, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    cams = [Camera.look_at(f"cam{i}", [x, 0.02, 0.3], [0, 0, 0], width=48, height=48, focal=48 * 3.0)
            for i, x in enumerate((-0.15, 0.0, 0.15))]
    V, F = sphere_mesh([0.0, 0.0, 0.0], RADIUS)
    scene = MeshScene(V, F)
    fields = {}
    for c, cam in enumerate(cams):
        hits, _ = scene.render_hits(cam, spp=1)
        sel = np.flatnonzero(hits.valid)
        rf = np.broadcast_to((np.arange(n_lights) + 1.0)[None, :, None], (len(sel), n_lights, 3))
        fields[c] = {"pixels": np.stack([sel // cam.width, sel % cam.width], 1), "part": np.zeros(len(sel), np.int8),
                     "depth": hits.t[sel].astype(np.float32), "rf": rf.astype(np.float16)}
    template = {"eyes": {"eye_left": {"centre": [0.0, 0.0, 0.0], "radius": RADIUS}}}
    model = SimpleNamespace(
        n_lights=n_lights, light_directions=dirs, cameras=cams, template=template, expressions=["ref"],
        references={"eyes": "ref"}, part_sources={"eyes": ["ref"]}, expression_index=lambda name: 0,
        eye_centres=np.array([[[0.0, 0.0, 0.0], [np.nan] * 3]]), teeth=np.full((1, 2, 4, 4), np.nan),
        head_pose=np.eye(4)[None], part_field=lambda ref, c: fields[c])
    return model, scene, V


def test_a_part_answers_the_stage_light_nearest_in_the_reference_frame(mi):
    import drjit as dr

    from mifacerf.jitarrays import to_jit
    from mifacerf.rendering.light_interp import LightInterpolator

    model, _, V = stand_in_model()
    lights = LightInterpolator(model.light_directions, method="voronoi").to_device()
    pm = PartMaterial(model, lights)
    R = rotation([0.3, 1.0, 0.1], 25.0)          # the target's eye: turned and moved
    T_t = np.eye(4)
    T_t[:3, :3], T_t[:3, 3] = R, [0.01, -0.02, 0.03]
    pm.update({"eye_left": T_t}, None)
    assert pm.chosen == {"eye_left": "ref"}
    # points on the front of the target eye (seen by the middle camera in the reference frame), turned
    front = V[V[:, 2] > 0.6 * RADIUS]
    p = front @ R.T + T_t[:3, 3]
    view = np.broadcast_to(R @ [0.0, 0.0, 1.0], p.shape)
    rng = np.random.default_rng(2)
    light = rng.normal(size=p.shape)
    light /= np.linalg.norm(light, axis=1, keepdims=True)
    part = to_jit(mi.UInt32, np.full(len(p), PARTS.index("eye_left"), np.uint32))
    out = pm.evaluate(part, to_jit(mi.Point3f, p.T), to_jit(mi.Vector3f, view.T), to_jit(mi.Vector3f, light.T))
    dr.eval(out)
    got = np.stack([np.asarray(out.x), np.asarray(out.y), np.asarray(out.z)], 1)
    nearest = np.argmax((light @ R) @ model.light_directions.T, axis=1)   # R_Δ = Rᵀ: the light in the reference
    assert np.allclose(got, (nearest + 1.0)[:, None], rtol=2e-3)


def test_a_part_no_camera_saw_is_zero_and_an_unused_part_reads_nothing(mi):
    import drjit as dr

    from mifacerf.jitarrays import to_jit
    from mifacerf.rendering.light_interp import LightInterpolator

    model, _, V = stand_in_model()
    pm = PartMaterial(model, LightInterpolator(model.light_directions, method="voronoi").to_device())
    pm.update({"eye_left": np.eye(4)}, None)
    back = V[V[:, 2] < -0.8 * RADIUS]              # the back of the eye: no camera saw it
    n = len(back)
    for part, pts in ((PARTS.index("eye_left"), back), (PARTS.index("teeth_upper"), V[:n])):
        out = pm.evaluate(to_jit(mi.UInt32, np.full(n, part, np.uint32)), to_jit(mi.Point3f, pts.T),
                          to_jit(mi.Vector3f, np.tile([0.0, 0.0, 1.0], (n, 1)).T),
                          to_jit(mi.Vector3f, np.tile([0.0, 0.0, 1.0], (n, 1)).T))
        dr.eval(out)
        assert np.allclose(np.asarray(out.x), 0.0) and np.isfinite(np.asarray(out.y)).all()


def test_the_cornea_lobe_is_sampled_as_its_pdf_and_peaks_at_the_mirror_direction(mi):
    """The eyes' cornea lobe (PartMaterial.cornea): Mitsuba's chi-square harness on its sampling against its
    density (a wider lobe than the material's, so the harness's grid resolves it), the density integrates to 1,
    and the lobe's value is F_schlick(n·ω_o) × that density about reflect(−ω_o, n) on the eye (0 off it)."""
    import drjit as dr
    from mitsuba.chi2 import ChiSquareTest, SphericalDomain

    from mifacerf.jitarrays import to_jit
    from mifacerf.rendering.light_interp import LightInterpolator
    from mifacerf.rendering.parts import CORNEA_F0, CORNEA_KAPPA, vmf_pdf, vmf_sample

    mean = mi.Vector3f(*[float(x) for x in np.array([0.3, 0.5, 0.8]) / np.linalg.norm([0.3, 0.5, 0.8])])
    chi2 = ChiSquareTest(domain=SphericalDomain(), sample_func=lambda s: vmf_sample(mean, s, 40.0),
                         pdf_func=lambda d: vmf_pdf(mean, d, 40.0), sample_dim=2, sample_count=200_000, res=61, ires=4)
    assert chi2.run(), chi2.messages
    rng = np.random.default_rng(4)
    d = rng.normal(size=(400_000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    dens = np.asarray(vmf_pdf(mean, to_jit(mi.Vector3f, d.T), 40.0))
    assert abs(dens.mean() * 4 * np.pi - 1) < 0.02
    model, _, V = stand_in_model()
    pm = PartMaterial(model, LightInterpolator(model.light_directions, method="voronoi").to_device())
    pm.update({"eye_left": np.eye(4)}, None)
    p = np.array([[0.0, 0.0, RADIUS], [0.0, RADIUS * 0.6, RADIUS * 0.8]])
    view = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    n = p / RADIUS
    mirror = 2 * (n * view).sum(1, keepdims=True) * n - view
    for part, expect_zero in ((PARTS.index("eye_left"), False), (PARTS.index("teeth_upper"), True)):
        val = pm.cornea(to_jit(mi.UInt32, np.full(2, part, np.uint32)), to_jit(mi.Point3f, p.T),
                        to_jit(mi.Vector3f, view.T), to_jit(mi.Vector3f, mirror.T))
        dr.eval(val)
        cos = (n * view).sum(1)
        peak = (CORNEA_F0 + (1 - CORNEA_F0) * (1 - cos) ** 5) * CORNEA_KAPPA / (2 * np.pi)
        np.testing.assert_allclose(np.asarray(val), 0.0 if expect_zero else peak, rtol=2e-3)
