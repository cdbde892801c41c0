"""The image-based material (``facerf_bsdf`` under Mitsuba's integrators) against the exact path (``facerf``).

The same scene — a ``facerf_face`` shape of the model, a camera, one emitter — rendered twice:
by the ``facerf`` integrator (the exact environment-lit sum over the light stage, noise-free
apart from anti-aliasing) and by a standard Mitsuba integrator (``direct``, ``path``) through the
material, in two independent passes of ``spp`` samples. Reported per integrator: PSNR of the
passes' mean against the exact image and the noise floor (PSNR of pass 1 against pass 2, i.e. what
two independent material renders agree to), over the face's pixels away from its outline (eroded
coverage); the mean brightness ratio material / exact; seconds per pass.

Run: ``python -m mifacerf.evaluation.material MODEL [--size 48] [--spp 256] [--env sky]``;
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


def psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> float:
    """PSNR (dB) of ``a`` against ``b`` over ``mask``, the peak being ``b``'s maximum there."""
    err = ((a - b)[mask] ** 2).mean()
    return float(10 * np.log10(b[mask].max() ** 2 / max(err, 1e-30)))


def compare(model, env: str = "sky", integrators=("direct", "path"), size: int = 48, spp: int = 256,
            expression: str | None = None, camera=None, exact_basis: str = "voronoi", bsdf=None) -> list[dict]:
    """Rows {integrator, psnr, noise_floor, brightness, seconds} of the material against the exact path
    under the environment ``env`` (a generated name or a lat-long file)."""
    from scipy.ndimage import binary_erosion

    from ..camera import Camera
    from ..environment import GENERATORS, cache_dir, generated
    from ..variant import ensure_plugins

    mi = ensure_plugins()
    if env in GENERATORS:
        generated(env)
        env = str(cache_dir() / "environments" / f"{env}-128.exr")
    emitter = {"type": "envmap", "filename": str(env)}
    if camera is None:
        camera = Camera.look_at("eval", [0.12, 0.1, 1.0], [0, 0, 0], width=size, height=size, focal=size * 4.0)
    exact_scene = _scene(mi, model, {"type": "facerf", "light_basis": exact_basis}, emitter, camera, 16, expression)
    t0 = time.perf_counter()
    exact = np.asarray(mi.render(exact_scene))
    t_exact = time.perf_counter() - t0
    mask = binary_erosion(exact[..., 3] > 0.999, iterations=1)
    ref = exact[..., :3]
    rows = [{"integrator": "facerf (exact)", "psnr": None, "noise_floor": None, "brightness": 1.0,
             "seconds": round(t_exact, 2), "spp": 16}]
    for name in integrators:
        integ = {"type": name} if name != "path" else {"type": "path", "max_depth": 3}
        scene = _scene(mi, model, integ, emitter, camera, spp, expression, bsdf)
        passes, seconds = [], []
        for seed in (0, 1):
            t0 = time.perf_counter()
            passes.append(np.asarray(mi.render(scene, seed=seed))[..., :3])
            seconds.append(time.perf_counter() - t0)
        mean = 0.5 * (passes[0] + passes[1])
        rows.append({"integrator": name, "psnr": round(psnr(mean, ref, mask), 2),
                     "noise_floor": round(psnr(passes[0], passes[1], mask), 2),
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


def format_rows(rows: list[dict]) -> str:
    out = ["| integrator | spp | PSNR vs exact (dB) | noise floor (dB) | mean material / exact | s / pass |",
           "|---|---|---|---|---|---|"]
    for r in rows:
        out.append(f"| {r['integrator']} | {r['spp']} | {r['psnr'] if r['psnr'] is not None else '—'} | "
                   f"{r['noise_floor'] if r['noise_floor'] is not None else '—'} | {r['brightness']:.4f} | "
                   f"{r['seconds']} |")
    return "\n".join(out)


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
    ap.add_argument("--no-self-visibility", action="store_true", help="the material keeps the captured "
                    "self-shadowing (shadowed again by the shadow rays)")
    ap.add_argument("--directional", action="store_true", help="the closed-form check instead: a directional "
                    "emitter along each of the most frontal light-stage lights (directional_oracle)")
    ap.add_argument("--animation", action="store_true", help="time an animation loop instead (kernels, s/frame)")
    a = ap.parse_args(argv)
    if a.directional:
        for r in directional_oracle(a.model, size=a.size, spp=a.spp,
                                    bsdf={"self_visibility": False} if a.no_self_visibility else None):
            print(r)
        return
    if a.animation:
        for integ in a.integrators.split(","):
            for r in animation(a.model, integ, size=a.size, spp=4):
                print(integ, r)
        return
    print(format_rows(compare(a.model, a.env, a.integrators.split(","), a.size, a.spp, a.expression,
                              exact_basis=a.exact_basis,
                              bsdf={"self_visibility": False} if a.no_self_visibility else None)))


if __name__ == "__main__":
    main()
