"""The image-based material (``facerf_bsdf`` under Mitsuba's integrators) against the exact path (``facerf``).

The same scene — a ``facerf_face`` shape of the model, a camera, one emitter — rendered twice:
by the ``facerf`` integrator (the exact environment-lit sum over the light stage, noise-free
apart from anti-aliasing) and by a standard Mitsuba integrator (``direct``, ``path``) through the
material, in two independent passes of ``spp`` samples. Reported per integrator: PSNR of the
passes' mean against the exact image and the noise floor (PSNR of pass 1 against pass 2, i.e. what
two independent material renders agree to; both with the exact image's peak — before 2026-12-02 the
floor's peak was pass 2's brightest pixel, so a material with bright outliers had a higher floor), over
the face's pixels away from its outline (eroded coverage); the mean brightness ratio material / exact;
seconds per pass. A bias-free material scores about 6 dB above its floor (the mean of two passes has a
quarter of the variance of their difference).

Run: ``python -m mifacerf.evaluation.material MODEL [--size 48] [--spp 256] [--env sky]``;
``--parts EXPRESSION``: eyes, teeth and mouth under the material, per part (:func:`parts`);
``--hat SYNTH``: the shadow of a hat on the face against the path-traced truth (:func:`hat_shadow`);
``--regions [--integrators unshadowed]``: where the error lies, per pixel class (:func:`regions`);
``--emitters``: every kind of emitter against its reference (:func:`emitters`);
``--integrators facerf_direct --near-occluders 0.015``: the near-field shadow rule (``facerf_direct``);
``--animation [--integrators facerf,direct] [--size 32]``: an animation loop through ``mi.traverse``
(expression and pose per frame), kernels compiled / launched and seconds per frame (:func:`animation`).
"""
from __future__ import annotations

import time

import numpy as np


def _scene(mi, model, integrator: dict, emitter: dict, camera, spp: int, expression: str | None, bsdf=None):
    from ..rendering.sensors import sensor_dict

    face = {"type": "facerf_face", "model": str(model), "bsdf": {"type": "facerf_bsdf", **(bsdf or {})}}
    if expression:
        face["expression"] = expression
    return mi.load_dict({"type": "scene", "integrator": integrator, "sensor": sensor_dict(camera, spp=spp),
                         "light": emitter, "face": face})


def psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray, peak: np.ndarray | None = None) -> float:
    """PSNR (dB) of ``a`` against ``b`` over ``mask``, the peak being ``b``'s maximum there (or ``peak``'s)."""
    err = ((a - b)[mask] ** 2).mean()
    top = (b if peak is None else peak)[mask].max()
    return float(10 * np.log10(top ** 2 / max(err, 1e-30)))


def compare(model, env: str = "sky", integrators=("direct", "path"), size: int = 48, spp: int = 256,
            expression: str | None = None, camera=None, exact_basis: str = "voronoi", bsdf=None,
            eye=(0.12, 0.1, 1.0)) -> list[dict]:
    """Rows {integrator, psnr, noise_floor, brightness, seconds} of the material against the exact path
    under the environment ``env`` (a generated name or a lat-long file), seen from ``eye`` (metres, the
    model's frame) towards the origin unless ``camera`` is given."""
    from ..camera import Camera
    from ..environment import GENERATORS, cache_dir, generated
    from ..variant import ensure_plugins

    mi = ensure_plugins()
    if env in GENERATORS:
        generated(env)
        env = str(cache_dir() / "environments" / f"{env}-128.exr")
    emitter = {"type": "envmap", "filename": str(env)}
    if camera is None:
        camera = Camera.look_at("eval", list(eye), [0, 0, 0], width=size, height=size, focal=size * 4.0)
    exact_scene = _scene(mi, model, {"type": "facerf", "light_basis": exact_basis}, emitter, camera, 16, expression)
    ref, mask, t_exact = _reference(mi, exact_scene)
    rows = [{"integrator": "facerf (exact)", "psnr": None, "noise_floor": None, "brightness": 1.0,
             "seconds": round(t_exact, 2), "spp": 16}]
    for name in integrators:
        integ = {"type": name} if name != "path" else {"type": "path", "max_depth": 3}
        passes, seconds = _passes(mi, _scene(mi, model, integ, emitter, camera, spp, expression, bsdf), spp)
        mean = passes.mean(0)
        rows.append({"integrator": name, "psnr": round(psnr(mean, ref, mask), 2),
                     "noise_floor": round(psnr(passes[0], passes[1], mask, peak=ref), 2),
                     "brightness": round(float(mean[mask].mean() / ref[mask].mean()), 4),
                     "seconds": round(float(np.mean(seconds)), 2), "spp": f"2 x {spp}"})
    return rows


def directional_oracle(model, lights=None, size: int = 48, spp: int = 64, integrator: str = "direct",
                       bsdf=None, height: int = 128) -> list[dict]:
    """The material under a directional emitter exactly along light-stage light ``l`` against a closed form:
    the fields are the response to that light, so the exact answer is the model's own relighting with light
    ``l`` alone at unit weight — the ``facerf`` integrator under an environment that is non-zero only on
    ``l``'s Voronoi cell, scaled so the cell's integral is 1 — times the emitter's irradiance (1). Both
    render the neutral expression, unposed (the rotations into the source are the identity). Rows
    {light, direction, psnr, brightness} over the face's pixels away from its outline; ``lights``: indices
    (default: the five lights most frontal to the camera)."""
    import tempfile
    from pathlib import Path

    from scipy.ndimage import binary_erosion

    from ..camera import Camera
    from ..environment import latlong_grid
    from ..imageio import write_exr
    from ..rendering.scene_assets import open_model
    from ..variant import ensure_plugins

    mi = ensure_plugins()
    m = open_model(model).model
    D = m.light_directions
    eye = np.array([0.12, 0.1, 1.0])
    camera = Camera.look_at("eval", eye, [0, 0, 0], width=size, height=size, focal=size * 4.0)
    if lights is None:
        lights = np.argsort(-(D @ (eye / np.linalg.norm(eye))))[:5].tolist()
    dirs, solid = latlong_grid(height)
    nearest = np.argmax(dirs.reshape(-1, 3) @ D.T, axis=1).reshape(height, 2 * height)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for l in lights:
            cell = nearest == l
            env = np.zeros((height, 2 * height, 3), np.float32)
            env[cell] = 1.0 / solid[cell].sum()
            path = Path(tmp) / f"cell{l}.exr"
            write_exr(path, env, half=False)
            exact = np.asarray(mi.render(_scene(mi, model, {"type": "facerf", "environment": str(path)},
                                                {"type": "constant", "radiance": 0.0}, camera, 16, None)))
            emitter = {"type": "directional", "direction": (-D[l]).tolist(), "irradiance": 1.0}
            mat = np.asarray(mi.render(_scene(mi, model, {"type": integrator}, emitter, camera, spp, None, bsdf)))
            mask = binary_erosion(exact[..., 3] > 0.999, iterations=1)
            ref = exact[..., :3]
            lit = mask & (ref.sum(-1) > 1e-3 * ref[mask].sum(-1).max())
            rows.append({"light": int(l), "direction": np.round(D[l], 3).tolist(),
                         "psnr": round(psnr(mat[..., :3], ref, lit), 2),
                         "brightness": round(float(mat[..., :3][lit].mean() / ref[lit].mean()), 4),
                         "lit_pixels": int(lit.sum())})
    return rows


def _reference(mi, scene):
    """The reference image (H, W, 3), the face's pixels away from its outline (eroded full coverage of the face
    shape's pixels: before 2026-12-02 the eroded alpha alone, which under an environment is 1 on the background
    too — the envmap rows then averaged 40–60 % background pixels into the PSNR and the brightness) and seconds."""
    from scipy.ndimage import binary_erosion

    t0 = time.perf_counter()
    exact = np.asarray(mi.render(scene))
    seconds = time.perf_counter() - t0
    face = _labels(mi, scene, exact.shape[0])[0] >= 0 if exact.shape[0] == exact.shape[1] else True
    return exact[..., :3], binary_erosion((exact[..., 3] > 0.999) & face, iterations=1), seconds


def _passes(mi, scene, spp: int):
    """Two independent passes of ``scene`` (seeds 0, 1): (pass images (2, H, W, 3), seconds per pass)."""
    passes, seconds = [], []
    for seed in (0, 1):
        t0 = time.perf_counter()
        passes.append(np.asarray(mi.render(scene, seed=seed))[..., :3])
        seconds.append(time.perf_counter() - t0)
    return np.stack(passes), float(np.mean(seconds))


def _cell_environment(path, light_direction, directions, height: int = 128) -> None:
    """A lat-long EXR non-zero only on the stage light's spherical-Voronoi cell, of integral 1 (the exact
    path's response to unit irradiance from that light)."""
    from ..environment import latlong_grid
    from ..imageio import write_exr

    dirs, solid = latlong_grid(height)
    nearest = np.argmax(dirs.reshape(-1, 3) @ directions.T, axis=1).reshape(height, 2 * height)
    l = int(np.argmax(directions @ light_direction))
    cell = nearest == l
    env = np.zeros((height, 2 * height, 3), np.float32)
    env[cell] = 1.0 / solid[cell].sum()
    write_exr(path, env, half=False)


def _patch_environment(path, centre, size: float, radiance: float, height: int = 256, sub: int = 4) -> float:
    """A lat-long EXR of a square area light seen from the origin: ``radiance`` where a ray from the origin meets
    the ``size`` x ``size`` square at ``centre`` facing the origin (``sub``² rays per texel, so edge texels hold
    the covered fraction); returns the square's irradiance at the origin along its axis (Σ radiance × solid angle)."""
    from ..environment import latlong_grid, uv_to_direction
    from ..imageio import write_exr

    c = np.asarray(centre, np.float64)
    dist = np.linalg.norm(c)
    n = -c / dist
    a = np.cross(n, [0.0, 1.0, 0.0])
    a = a / np.linalg.norm(a) if np.linalg.norm(a) > 1e-9 else np.array([1.0, 0, 0])
    b = np.cross(n, a)
    H, W = height, 2 * height
    cover = np.zeros((H, W))
    for dy in range(sub):
        for dx in range(sub):
            yy, xx = np.mgrid[0:H, 0:W]
            uv = np.stack([(xx + (dx + 0.5) / sub) / W, (yy + (dy + 0.5) / sub) / H], -1)
            d = uv_to_direction(uv)
            t = (c @ n) / np.minimum(d @ n, -1e-12)          # ray o + t d meets the plane n·x = n·c
            q = d * t[..., None] - c
            hit = (t > 0) & (np.abs(q @ a) <= size / 2) & (np.abs(q @ b) <= size / 2)
            cover += hit
    cover /= sub * sub
    env = np.repeat((radiance * cover)[..., None], 3, axis=2).astype(np.float32)
    write_exr(path, env, half=False)
    dirs, solid = latlong_grid(height)
    return float((radiance * cover * solid * np.maximum(-(dirs @ n), 0)).sum())


def emitters(model, size: int = 48, spp: int = 64, integrators=("direct", "path"), env: str = "interior",
             distance: float = 20.0, bsdf=None) -> list[dict]:
    """The material under every kind of Mitsuba emitter, each against a reference rendered by the exact
    ``facerf`` path from the same captured fields (neutral expression, the camera of :func:`compare`):

    * ``envmap`` (``env``): the exact path under that environment;
    * ``directional`` along the stage light most frontal to the camera, irradiance 1: the exact path under an
      environment that is non-zero only on that light's Voronoi cell, of integral 1 (the closed form: the
      fields are the response to unit irradiance from that light);
    * ``point`` and ``spot`` (cutoff 20°) ``distance`` m away along that light, intensity distance²
      (irradiance 1 at the origin): the same reference (the head's ±0.1 m make the irradiance vary by ±1 %);
    * ``area``: a 4 m × 4 m ``rectangle`` 10 m away along that light, radiance 1 / (its solid angle × cos):
      the exact path under the environment that is that square as seen from the origin (a far light: the
      same directions and radiance), supersampled on a 256-row lat-long map.

    Rows {emitter, integrator, psnr, noise_floor, brightness, seconds, spp} over the face's lit pixels away
    from its outline (PSNR of the two passes' mean against the reference; noise floor: pass 1 against 2)."""
    import tempfile
    from pathlib import Path

    from ..camera import Camera
    from ..environment import GENERATORS, cache_dir, generated
    from ..rendering.scene_assets import open_model
    from ..variant import ensure_plugins

    mi = ensure_plugins()
    m = open_model(model).model
    D = m.light_directions
    eye = np.array([0.12, 0.1, 1.0])
    camera = Camera.look_at("eval", eye, [0, 0, 0], width=size, height=size, focal=size * 4.0)
    l = int(np.argmax(D @ (eye / np.linalg.norm(eye))))
    d = D[l]
    if env in GENERATORS:
        generated(env)
        env = str(cache_dir() / "environments" / f"{env}-128.exr")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        cell = Path(tmp) / "cell.exr"
        _cell_environment(cell, d, D)
        side, far = 4.0, 10.0
        patch = Path(tmp) / "patch.exr"
        E = _patch_environment(patch, d * far, side, 1.0)
        dark = {"type": "constant", "radiance": 0.0}
        to_world = mi.ScalarTransform4f().look_at(origin=(d * far).tolist(), target=[0, 0, 0], up=[0, 1, 0])
        cases = [
            ("envmap", {"type": "envmap", "filename": str(env)}, None),
            ("directional", {"type": "directional", "direction": (-d).tolist(), "irradiance": 1.0}, str(cell)),
            ("point", {"type": "point", "position": (d * distance).tolist(), "intensity": distance ** 2}, str(cell)),
            ("spot", {"type": "spot", "cutoff_angle": 20.0, "beam_width": 15.0, "intensity": distance ** 2,
                      "to_world": mi.ScalarTransform4f().look_at(origin=(d * distance).tolist(), target=[0, 0, 0],
                                                                 up=[0, 1, 0])}, str(cell)),
            ("area", {"type": "rectangle", "to_world": to_world @ mi.ScalarTransform4f().scale([side / 2, side / 2, 1]),
                      "emitter": {"type": "area", "radiance": 1.0 / E}}, str(patch)),
        ]
        for name, emitter, reference in cases:
            if reference is None:
                ref_scene = _scene(mi, model, {"type": "facerf"}, emitter, camera, 16, None)
            else:
                ref_scene = _scene(mi, model, {"type": "facerf", "environment": reference}, dark, camera, 16, None)
            ref, mask, t_ref = _reference(mi, ref_scene)
            if name == "area":
                ref = ref / E   # the patch environment's irradiance is E; the area light's 1
            lit = mask & (ref.sum(-1) > 1e-3 * ref[mask].sum(-1).max())
            rows.append({"emitter": name, "integrator": "facerf (reference)", "psnr": None, "noise_floor": None,
                         "brightness": 1.0, "seconds": round(t_ref, 2), "spp": 16})
            for integ in integrators:
                spec = {"type": integ} if integ != "path" else {"type": "path", "max_depth": 3}
                scene = _scene(mi, model, spec, emitter, camera, spp, None, bsdf)
                passes, seconds = _passes(mi, scene, spp)
                mean = passes.mean(0)
                rows.append({"emitter": name, "integrator": integ, "psnr": round(psnr(mean, ref, lit), 2),
                             "noise_floor": round(psnr(passes[0], passes[1], lit), 2),
                             "brightness": round(float(mean[lit].mean() / ref[lit].mean()), 4),
                             "seconds": round(seconds, 2), "spp": f"2 x {spp}"})
    return rows


def format_emitter_rows(rows: list[dict]) -> str:
    out = ["| emitter | integrator | spp | PSNR vs reference (dB) | noise floor (dB) | mean material / reference "
           "| s / pass |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        out.append(f"| {r['emitter']} | {r['integrator']} | {r['spp']} | "
                   f"{r['psnr'] if r['psnr'] is not None else '—'} | "
                   f"{r['noise_floor'] if r['noise_floor'] is not None else '—'} | {r['brightness']:.4f} | "
                   f"{r['seconds']} |")
    return "\n".join(out)


def _labels(mi, scene, size: int) -> np.ndarray:
    """(size, size) per pixel centre: -1 background or another shape, 0 the face's skin, k + 1 part ``PARTS[k]``."""
    import drjit as dr

    face = [sh for sh in scene.shapes() if sh.id() == "face"][0]
    idx = dr.arange(mi.UInt32, size * size)
    uv = mi.Point2f((mi.Float(idx % size) + 0.5) / size, (mi.Float(idx // size) + 0.5) / size)
    ray, _ = scene.sensors()[0].sample_ray(0.0, 0.5, uv, mi.Point2f(0.5, 0.5))
    si = scene.ray_intersect(ray)
    on = np.asarray(si.is_valid()) & (np.asarray(si.shape) == np.asarray(mi.ShapePtr(face)))
    prim = np.minimum(np.asarray(si.prim_index), len(face.label) - 1)
    return np.where(on, face.label[prim].astype(np.int64), -1).reshape(size, size), face


def parts(model, expression: str, env: str = "interior", size: int = 128, spp: int = 64,
          integrator: str = "direct") -> list[dict]:
    """Eyes, teeth and mouth interior under the material against the ``facerf`` integrator (which shades them
    from their reference expressions with ray-traced visibility and a re-synthesised cornea highlight), per
    part and for the skin: pixels, PSNR and mean material / exact (``integrator="unshadowed"``: the material
    without shadow rays, :func:`regions`). The camera looks at the head's centre from
    half way along the direction of the model's middle capture camera (``size``², focal 2.5 ``size``)."""
    from ..camera import Camera
    from ..environment import GENERATORS, cache_dir, generated
    from ..rendering.parts import PARTS
    from ..rendering.scene_assets import open_model
    from ..variant import ensure_plugins

    mi = ensure_plugins()
    m = open_model(model).model
    centre = m.vertices[m.expression_index(m.neutral)].mean(0)
    c0 = m.cameras[len(m.cameras) // 2]
    camera = Camera.look_at("parts", centre + 0.5 * (c0.centre - centre), centre, width=size, height=size,
                            focal=2.5 * size)
    if env in GENERATORS:
        generated(env)
        env = str(cache_dir() / "environments" / f"{env}-128.exr")
    emitter = {"type": "envmap", "filename": str(env)}
    exact_scene = _scene(mi, model, {"type": "facerf"}, emitter, camera, 16, expression)
    ref, _, t_ref = _reference(mi, exact_scene)
    name = _register_unshadowed(mi) if integrator == "unshadowed" else integrator
    passes, seconds = _passes(mi, _scene(mi, model, {"type": name}, emitter, camera, spp, expression), spp)
    mean = passes.mean(0)
    label, _ = _labels(mi, exact_scene, size)
    rows = []
    for k, name in enumerate(("skin",) + PARTS):
        sel = label == k
        if sel.sum() < 3:
            continue
        rows.append({"part": name, "pixels": int(sel.sum()), "psnr": round(psnr(mean, ref, sel), 2),
                     "brightness": round(float(mean[sel].mean() / max(ref[sel].mean(), 1e-9)), 4),
                     "seconds_exact": round(t_ref, 1), "seconds_material": round(seconds, 1), "spp": f"2 x {spp}"})
    return rows


#: the hat of scenes/face_with_objects.xml: a brim 16 cm in radius at y = 0.125 m, a crown and its top
HAT_COLOUR = [0.25, 0.18, 0.12]


def hat_objects(mi) -> dict:
    """The hat of ``scenes/face_with_objects.xml`` as scene-dict entries (model / capture frame, metres)."""
    diffuse = {"type": "twosided", "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": HAT_COLOUR}}}
    T = mi.ScalarTransform4f
    return {"hat_brim": {"type": "disk", "bsdf": diffuse,
                         "to_world": T().translate([0, 0.125, 0]) @ T().scale(0.16) @ T().rotate([1, 0, 0], -90)},
            "hat_crown": {"type": "cylinder", "p0": [0, 0.125, 0], "p1": [0, 0.21, 0], "radius": 0.085, "bsdf": diffuse},
            "hat_top": {"type": "disk", "bsdf": diffuse,
                        "to_world": T().translate([0, 0.21, 0]) @ T().scale(0.085) @ T().rotate([1, 0, 0], -90)}}


def hat_shadow(synth, model, size: int = 96, spp: int = 64, spp_truth: int = 64, sun: float = 3.0,
               sky: float = 0.2, integrators=("direct", "path"), pictures=None) -> list[dict]:
    """The shadow a hat casts on the face: the material (``facerf_bsdf`` on the model's neutral expression)
    against a path-traced ground truth of the synthetic subject (``synth``: a ``mifacerf synth`` output)
    wearing the same hat (:func:`hat_objects`), under a sun from above and in front (irradiance ``sun``, the
    direction of ``scenes/face_with_objects.xml``) and the ``sky`` environment scaled by ``sky``.

    Each is rendered with and without the hat; the shadow factor is hat / no hat per pixel (luminance) over
    the face's skin pixels (the material's skin triangles, the truth's foreground). Rows per integrator:
    shadow IoU (factor < 0.5 in both against either), the mean factor inside the truth's shadow (material,
    truth), PSNR of the factor images (peak 1) and of the hat renders (over skin), mean brightness ratio of the
    hat renders, seconds. ``pictures``: a PNG path for the first integrator: truth and material with the hat,
    then the two shadow factors (grey 1, black 0), skin pixels only."""
    import tempfile
    from pathlib import Path

    from scipy.ndimage import binary_erosion

    from ..camera import Camera
    from ..environment import Environment, resolve
    from ..imageio import write_exr
    from ..rendering.sensors import sensor_dict
    from ..synthetic.truth_scene import TruthRenderer
    from ..variant import ensure_plugins

    mi = ensure_plugins()
    camera = Camera.look_at("hat", [0.35, 0.15, 1.3], [0, -0.05, 0.0], width=size, height=size,
                            focal=(size / 2) / np.tan(np.radians(14.0)))
    sun_dict = {"type": "directional", "direction": [-0.25, -1.0, -0.45], "irradiance": sun}
    env = Environment(resolve("sky").data * sky, f"sky-x{sky:g}")
    tr = TruthRenderer.from_synth(synth)
    params = tr.expressions[tr.truth.get("neutral", "neutral")] if "neutral" in tr.expressions \
        else next(iter(tr.expressions.values()))
    hat = hat_objects(mi)
    t0 = time.perf_counter()
    truth = {k: tr.render(params, camera, env, spp=spp_truth, seed=1, objects={"sun": sun_dict, **objs})
             for k, objs in (("hat", hat), ("bare", {}))}
    t_truth = time.perf_counter() - t0
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        env_path = Path(tmp) / "sky.exr"
        write_exr(env_path, env.data.astype(np.float32), half=False)
        for integ in integrators:
            spec = {"type": integ} if integ != "path" else {"type": "path", "max_depth": 3}
            images, seconds = {}, 0.0
            for k, objs in (("hat", hat), ("bare", {})):
                scene = mi.load_dict({"type": "scene", "integrator": spec, "sensor": sensor_dict(camera, spp=spp),
                                      "sky": {"type": "envmap", "filename": str(env_path)}, "sun": sun_dict,
                                      "face": {"type": "facerf_face", "model": str(model),
                                               "bsdf": {"type": "facerf_bsdf"}}, **objs})
                t0 = time.perf_counter()
                images[k] = np.asarray(mi.render(scene, seed=2))
                seconds += time.perf_counter() - t0
            skin = _labels(mi, scene, size)[0] == 0
            mask = binary_erosion(skin & (truth["bare"][..., 3] > 0.999) & (images["bare"][..., 3] > 0.999),
                                  iterations=1)
            lum = {k: v[..., :3].mean(-1) for k, v in images.items()}
            tl = {k: v[..., :3].mean(-1) for k, v in truth.items()}
            ok = mask & (lum["bare"] > 1e-4) & (tl["bare"] > 1e-4)
            f_mat = np.clip(lum["hat"] / np.maximum(lum["bare"], 1e-6), 0, 2)
            f_truth = np.clip(tl["hat"] / np.maximum(tl["bare"], 1e-6), 0, 2)
            sh_mat, sh_truth = ok & (f_mat < 0.5), ok & (f_truth < 0.5)
            union = (sh_mat | sh_truth).sum()
            err = ((f_mat - f_truth)[ok] ** 2).mean()
            ref = truth["hat"][..., :3]
            rows.append({"integrator": integ, "pixels": int(ok.sum()), "shadow_pixels_truth": int(sh_truth.sum()),
                         "shadow_pixels_material": int(sh_mat.sum()),
                         "shadow_iou": round(float((sh_mat & sh_truth).sum() / max(union, 1)), 3),
                         "factor_in_shadow_material": round(float(f_mat[sh_truth].mean()), 3) if sh_truth.any() else None,
                         "factor_in_shadow_truth": round(float(f_truth[sh_truth].mean()), 3) if sh_truth.any() else None,
                         "factor_psnr": round(float(10 * np.log10(1.0 / max(err, 1e-30))), 2),
                         "psnr_hat": round(psnr(images["hat"][..., :3], ref, ok), 2),
                         "brightness_hat": round(float(images["hat"][..., :3][ok].mean() / ref[ok].mean()), 4),
                         "seconds_material": round(seconds, 1), "seconds_truth": round(t_truth, 1),
                         "spp": spp, "spp_truth": spp_truth})
            if integ == integrators[0] and pictures is not None:
                from ..imageio import write_png

                peak = max(float(ref[ok].max()) if ok.any() else 1.0, 1e-6)
                tiles = [np.clip(truth["hat"][..., :3] / peak, 0, 1), np.clip(images["hat"][..., :3] / peak, 0, 1),
                         np.repeat(np.where(ok, np.clip(f_truth, 0, 1), 0.3)[..., None], 3, 2),
                         np.repeat(np.where(ok, np.clip(f_mat, 0, 1), 0.3)[..., None], 3, 2)]
                write_png(pictures, np.concatenate([t ** (1 / 2.2) for t in tiles], axis=1).astype(np.float32))
    return rows


def animation(model, integrator: str = "facerf", frames: int = 10, size: int = 32, spp: int = 4) -> list[dict]:
    """Render ``frames`` frames of one scene, changing the expression weights and the head's pose through
    ``mi.traverse`` before each; per frame the kernels launched and compiled (Dr.Jit's kernel history) and
    the seconds of update + render."""
    import drjit as dr

    from ..camera import Camera
    from ..variant import ensure_plugins

    mi = ensure_plugins()
    camera = Camera.look_at("eval", [0.12, 0.1, 1.0], [0, 0, 0], width=size, height=size, focal=size * 4.0)
    from ..rendering.sensors import sensor_dict

    scene = mi.load_dict({"type": "scene", "integrator": {"type": integrator}, "sensor": sensor_dict(camera, spp=spp),
                          "light": {"type": "constant", "radiance": 1.0},
                          "face": {"type": "facerf_face", "model": str(model), "bsdf": {"type": "facerf_bsdf"}}})
    params = mi.traverse(scene)
    shape = [s for s in scene.shapes() if s.id() == "face"][0]
    names = shape.face.model.expressions
    rows = []
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        for k in range(frames):
            dr.kernel_history()
            t0 = time.perf_counter()
            a = k / max(frames - 1, 1)
            w = np.zeros(len(names))
            w[0], w[-1] = 1 - a, a
            params["face.expression"] = shape.weights(w)
            params["face.to_world"] = shape.transform(mi.ScalarTransform4f().rotate([0, 1, 0], 20.0 * a - 10.0))
            params.update()
            img = mi.render(scene, seed=k)
            dr.eval(img)
            seconds = time.perf_counter() - t0
            hist = [h for h in dr.kernel_history() if h.get("type") == dr.KernelType.JIT]
            rows.append({"frame": k, "launched": len(hist), "compiled": sum(1 for h in hist if not h.get("cache_hit")),
                         "seconds": round(seconds, 3)})
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    return rows


def _register_unshadowed(mi) -> str:
    """A ``facerf_unshadowed`` integrator: at the camera ray's hit, the BSDF against one emitter sample with no
    shadow ray (the material's own evaluation, apart from visibility); background black."""
    import drjit as dr

    class Unshadowed(mi.SamplingIntegrator):
        def sample(self, scene, sampler, ray, medium=None, active=True):
            si = scene.ray_intersect(ray, active)
            valid = si.is_valid()
            ds, weight = scene.sample_emitter_direction(si, sampler.next_2d(), False, valid)
            value = si.bsdf(ray).eval(mi.BSDFContext(), si, si.to_local(ds.d), valid)
            return dr.select(valid, value * weight, 0.0), valid, []

    mi.register_integrator("facerf_unshadowed", lambda props: Unshadowed(props))
    return "facerf_unshadowed"


def _facet_blocked(mi, scene, model, size: int, env_path: str, expression=None) -> np.ndarray:
    """(size, size): per pixel centre on the skin, the share of the environment's light in front of the smooth
    surface (the barycentric blend of the vertex normals) that lies *below* the hit triangle's plane — light
    the integrator's shadow rays cannot pass (they start below the surface) although the captured field,
    whose real surface follows the smooth normal, holds it. NaN off the skin."""
    import drjit as dr

    from ..environment import Environment, latlong_grid
    from ..geometry.visibility import vertex_normals

    face = [sh for sh in scene.shapes() if sh.id() == "face"][0]
    idx = dr.arange(mi.UInt32, size * size)
    uv = mi.Point2f((mi.Float(idx % size) + 0.5) / size, (mi.Float(idx // size) + 0.5) / size)
    ray, _ = scene.sensors()[0].sample_ray(0.0, 0.5, uv, mi.Point2f(0.5, 0.5))
    si = scene.ray_intersect(ray)
    tri = np.asarray(si.prim_index).astype(np.int64)
    skin = np.asarray(si.is_valid()) & (np.asarray(si.shape) == np.asarray(mi.ShapePtr(face))) \
        & (tri < face.geometry.n_skin_faces)
    tri = face.geometry.parent[np.where(skin, tri, 0)]   # the template's triangle (of a Phong sub-face)
    X, F = face.pose_state.target, model.triangles
    t = np.where(skin, tri, 0)
    ng = np.cross(X[F[:, 1]] - X[F[:, 0]], X[F[:, 2]] - X[F[:, 0]])
    ng /= np.maximum(np.linalg.norm(ng, axis=1, keepdims=True), 1e-30)
    A = X[F[t]]
    p = np.asarray(si.p).T
    e0, e1, d = A[:, 1] - A[:, 0], A[:, 2] - A[:, 0], p - A[:, 0]
    d00, d01, d11 = (e0 * e0).sum(1), (e0 * e1).sum(1), (e1 * e1).sum(1)
    d20, d21 = (d * e0).sum(1), (d * e1).sum(1)
    den = np.maximum(d00 * d11 - d01 ** 2, 1e-30)
    b1, b2 = (d11 * d20 - d01 * d21) / den, (d00 * d21 - d01 * d20) / den
    b = np.stack([1 - b1 - b2, b1, b2], 1)
    ns = (b[:, :, None] * vertex_normals(X, F)[F[t]]).sum(1)
    ns /= np.maximum(np.linalg.norm(ns, axis=1, keepdims=True), 1e-30)
    env = Environment.load(env_path).data.mean(-1)          # .exr or .hdr
    dirs, solid = latlong_grid(env.shape[0])
    w, D = (env * solid).reshape(-1), dirs.reshape(-1, 3)
    front = (ns @ D.T) > 0
    below = (ng[t] @ D.T) < 0
    share = ((front & below) * w).sum(1) / np.maximum((front * w).sum(1), 1e-30)
    return np.where(skin, share, np.nan).reshape(size, size)


def regions(model, env: str = "interior", size: int = 96, spp: int = 64, integrator: str = "direct",
            bsdf=None, facet_share: float = 0.2, eye=(0.12, 0.1, 1.0)) -> dict:
    """Where the material's error against the exact path lies (the camera of :func:`compare`, two passes of
    ``spp``). Per pixel class over the pixels of :func:`compare` — the skin, each part, the outline band (the
    face's pixels within 2 of the background), the *facet-blocked* skin (:func:`_facet_blocked` ≥ ``facet_share``) —:
    pixels, share of the squared error, share of the squared *bias* (error less the passes' noise), mean
    material / exact; and the share of the squared error in the worst 1 % / 5 % of pixels. ``integrator``
    ``"unshadowed"``: the material against emitter samples without shadow rays (its evaluation alone)."""
    from scipy.ndimage import binary_erosion

    from ..camera import Camera
    from ..environment import GENERATORS, cache_dir, generated
    from ..rendering.parts import PARTS
    from ..rendering.scene_assets import open_model
    from ..variant import ensure_plugins

    mi = ensure_plugins()
    if env in GENERATORS:
        generated(env)
        env = str(cache_dir() / "environments" / f"{env}-128.exr")
    emitter = {"type": "envmap", "filename": str(env)}
    camera = Camera.look_at("eval", list(eye), [0, 0, 0], width=size, height=size, focal=size * 4.0)
    exact_scene = _scene(mi, model, {"type": "facerf"}, emitter, camera, 16, None)
    ref, mask, _ = _reference(mi, exact_scene)
    label, _ = _labels(mi, exact_scene, size)
    integrator, options = _integrator_options(integrator)
    name = _register_unshadowed(mi) if integrator == "unshadowed" else integrator
    spec = {"type": name, **options} if name != "path" else {"type": "path", "max_depth": 3, **options}
    passes, seconds = _passes(mi, _scene(mi, model, spec, emitter, camera, spp, None, bsdf), spp)
    mean = passes.mean(0)
    if integrator == "unshadowed":   # no background on this integrator: the face only
        mask &= label >= 0
    err = ((mean - ref) ** 2).sum(-1)
    bias = err - (((passes[0] - passes[1]) / 2) ** 2).sum(-1)
    tot, tot_b = err[mask].sum(), max(bias[mask].sum(), 1e-30)
    facet = _facet_blocked(mi, exact_scene, open_model(model).model, size, str(env))
    classes = {"skin": label == 0, **{p: label == k + 1 for k, p in enumerate(PARTS)},
               "outline band": (label >= 0) & ~binary_erosion(label >= 0, iterations=2),
               f"facet-blocked skin (≥ {facet_share:g})": np.nan_to_num(facet, nan=0.0) >= facet_share}
    rows = []
    for k, sel in classes.items():
        sel = sel & mask
        if sel.sum() < 1:
            continue
        rows.append({"class": k, "pixels": int(sel.sum()), "error_share": round(float(err[sel].sum() / tot), 3),
                     "bias_share": round(float(bias[sel].sum() / tot_b), 3),
                     "brightness": round(float(mean[sel].mean() / max(ref[sel].mean(), 1e-9)), 4)})
    worst = np.sort(err[mask])[::-1].cumsum() / tot
    n = mask.sum()
    return {"psnr": round(psnr(mean, ref, mask), 2), "noise_floor": round(psnr(passes[0], passes[1], mask, ref), 2),
            "brightness": round(float(mean[mask].mean() / ref[mask].mean()), 4),
            "worst_1pc": round(float(worst[max(int(0.01 * n) - 1, 0)]), 3),
            "worst_5pc": round(float(worst[max(int(0.05 * n) - 1, 0)]), 3), "rows": rows,
            "seconds": round(seconds, 1), "spp": f"2 x {spp}"}


def _integrator_options(integrator: str) -> tuple[str, dict]:
    """``NAME[:key=value,...]`` → (NAME, {key: value}); values true/false, numbers or strings
    (``facerf_direct:part_rays=false``)."""
    name, _, opts = integrator.partition(":")
    out = {}
    for item in filter(None, opts.split(",")):
        key, eq, value = item.partition("=")
        if not eq:
            raise ValueError(f"integrator option {item!r}: expected key=value (e.g. {name}:part_rays=false)")
        low = value.lower()
        if low in ("true", "false"):
            out[key] = low == "true"
        else:
            try:
                out[key] = int(value) if value.lstrip("-").isdigit() else float(value)
            except ValueError:
                out[key] = value
    return name, out


def format_rows(rows: list[dict]) -> str:
    out = ["| integrator | spp | PSNR vs exact (dB) | noise floor (dB) | mean material / exact | s / pass |",
           "|---|---|---|---|---|---|"]
    for r in rows:
        out.append(f"| {r['integrator']} | {r['spp']} | {r['psnr'] if r['psnr'] is not None else '—'} | "
                   f"{r['noise_floor'] if r['noise_floor'] is not None else '—'} | {r['brightness']:.4f} | "
                   f"{r['seconds']} |")
    return "\n".join(out)


def parse_eye(text: str) -> tuple:
    """``"X,Y,Z"`` (metres) → a camera position away from the origin; ValueError saying what was expected."""
    try:
        eye = tuple(float(v) for v in str(text).split(","))
        if len(eye) != 3 or not np.all(np.isfinite(eye)) or np.linalg.norm(eye) < 1e-6:
            raise ValueError
    except ValueError:
        raise ValueError(f"expected three finite numbers X,Y,Z away from the origin, got {text!r}") from None
    return eye


def material_options(self_visibility: bool = True, visibility_rule=None, visibility_grid=None, near_occluders=None,
                     visibility_emitter: bool = False) -> dict | None:
    """The ``facerf_bsdf`` parameters of the command lines' options (None: the defaults);
    ``visibility_emitter`` references the comparison scenes' envmap (:func:`_scene`'s ``"light"``)."""
    bsdf = {} if self_visibility else {"self_visibility": False}
    if visibility_rule:
        bsdf["visibility_rule"] = visibility_rule
    if visibility_grid is not None:
        bsdf["visibility_grid"] = int(visibility_grid)
    if near_occluders is not None:
        bsdf["near_occluders"] = float(near_occluders)
    if visibility_emitter:
        bsdf["visibility_emitter"] = {"type": "ref", "id": "light"}
    return bsdf or None


def main(argv=None) -> None:
    import argparse

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model")
    ap.add_argument("--env", default="sky")
    ap.add_argument("--size", type=int, default=48)
    ap.add_argument("--spp", type=int, default=256)
    ap.add_argument("--expression", default=None)
    ap.add_argument("--integrators", default="direct,path")
    ap.add_argument("--exact-basis", default="voronoi")
    ap.add_argument("--eye", default="0.12,0.1,1.0", help="X,Y,Z: the camera's position in metres, looking at "
                    "the origin (the comparison and --regions)")
    ap.add_argument("--no-self-visibility", action="store_true", help="the material keeps the captured "
                    "self-shadowing (shadowed again by the shadow rays)")
    ap.add_argument("--visibility-rule", default=None, help="the material's self-visibility rule: cell "
                    "(default) or ray (facerf_bsdf visibility_rule)")
    ap.add_argument("--visibility-grid", type=int, default=None, help="the material's self-visibility grid order "
                    "inside each triangle (facerf_bsdf visibility_grid; default 3, 0: per vertex)")
    ap.add_argument("--near-occluders", type=float, default=None, help="metres: the material's near-field shadow "
                    "rule (facerf_bsdf near_occluders), for --integrators facerf_direct")
    ap.add_argument("--visibility-emitter", action="store_true", help="the material's cell shares of "
                    "self-visibility weighted by the scene's environment (facerf_bsdf visibility_emitter, a "
                    "reference to the envmap); the comparison and --regions only")
    ap.add_argument("--directional", action="store_true", help="the closed-form check instead: a directional "
                    "emitter along each of the most frontal light-stage lights (directional_oracle)")
    ap.add_argument("--animation", action="store_true", help="time an animation loop instead (kernels, s/frame)")
    ap.add_argument("--emitters", action="store_true", help="every kind of emitter against its reference "
                    "instead (envmap, directional, point, spot, area: emitters())")
    ap.add_argument("--hat", metavar="SYNTH", help="the hat's shadow on the face against the path-traced truth "
                    "of the synthetic subject of this synth output instead (hat_shadow)")
    ap.add_argument("--parts", metavar="EXPRESSION", help="eyes, teeth and mouth under the material against the "
                    "facerf integrator instead, per part (parts)")
    ap.add_argument("--regions", action="store_true", help="where the error lies instead: per pixel class "
                    "(skin, parts, outline band, facet-blocked skin) at --size (regions); --integrators "
                    "unshadowed: the material without shadow rays; NAME:key=value,... passes options to the "
                    "integrator (facerf_direct:part_rays=false)")
    ap.add_argument("--pictures", default=None, help="with --hat: a PNG of truth, material and the shadow factors")
    a = ap.parse_args(argv)
    try:
        eye = parse_eye(a.eye)
    except ValueError as e:
        ap.error(f"--eye: {e}")
    if a.visibility_emitter:
        others = [o for o in ("parts", "hat", "emitters", "directional", "animation") if getattr(a, o)]
        if others:
            ap.error(f"--visibility-emitter: only with the comparison or --regions, not with --{others[0]}")
    bsdf = material_options(not a.no_self_visibility, a.visibility_rule, a.visibility_grid, a.near_occluders,
                            a.visibility_emitter)
    for integ in a.integrators.split(","):
        try:
            _integrator_options(integ)
        except ValueError as e:   # one line naming the option, as argparse's own errors
            ap.error(f"--integrators: {e}")
    if a.regions:
        out = regions(a.model, env=a.env, size=a.size, spp=a.spp, integrator=a.integrators.split(",")[0], bsdf=bsdf,
                      eye=eye)
        rows = out.pop("rows")
        print(out)
        for r in rows:
            print(r)
        return
    if a.parts:
        for r in parts(a.model, a.parts, env=a.env, size=a.size, spp=a.spp, integrator=a.integrators.split(",")[0]):
            print(r)
        return
    if a.hat:
        for r in hat_shadow(a.hat, a.model, size=a.size, spp=a.spp, integrators=a.integrators.split(","),
                            pictures=a.pictures):
            print(r)
        return
    if a.emitters:
        print(format_emitter_rows(emitters(a.model, size=a.size, spp=a.spp, integrators=a.integrators.split(","),
                                           env=a.env, bsdf=bsdf)))
        return
    if a.directional:
        for r in directional_oracle(a.model, size=a.size, spp=a.spp, bsdf=bsdf):
            print(r)
        return
    if a.animation:
        for integ in a.integrators.split(","):
            for r in animation(a.model, integ, size=a.size, spp=4):
                print(integ, r)
        return
    print(format_rows(compare(a.model, a.env, a.integrators.split(","), a.size, a.spp, a.expression,
                              exact_basis=a.exact_basis, bsdf=bsdf, eye=eye)))


if __name__ == "__main__":
    main()
