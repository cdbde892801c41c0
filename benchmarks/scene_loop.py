"""The Mitsuba scene path's animation loop against the Python renderer, side by side in one run: a blend of
the neutral and a second expression changing every frame, set through ``mi.traverse`` and rendered by
``mi.render`` (``scenes/face_envmap.xml``, the ``facerf`` integrator), and the same frames (camera, weights,
environment) by ``FaceModel.render``; the median of the frames after each path has seen both sources once,
their ratio, and the kernels the scene loop compiled after its first frame::

    python benchmarks/scene_loop.py MODEL [--second smile] [--frames 8] [--size 256] [--spp 4]
"""
from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

SCENES = Path(__file__).resolve().parents[1] / "scenes"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("model")
    ap.add_argument("--second", default=None, help="the expression blended with the neutral (default: the model's second)")
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--spp", type=int, default=4)
    a = ap.parse_args()
    import drjit as dr

    import mifacerf as mf
    from mifacerf.environment import Environment
    from mifacerf.rendering.sensors import camera_from_sensor
    from mifacerf.variant import ensure_variant

    mi = ensure_variant()
    mf.register_plugins()
    envmap = SCENES / "envmaps" / "sky.exr"
    scene = mi.load_file(str(SCENES / "face_envmap.xml"), model=str(Path(a.model).resolve()), width=a.size,
                         height=a.size, spp=a.spp, envmap=str(envmap))
    face = [s for s in scene.shapes() if s.id() == "face"][0]
    params = mi.traverse(scene)
    model = mf.load_model(a.model)
    neutral = model.model.neutral
    second = a.second or [e for e in model.expressions if e != neutral][0]
    camera = camera_from_sensor(scene.sensors()[0])
    env = Environment.load(envmap)

    def scene_frame(w):
        params["face.expression"] = face.weights({neutral: 1 - w, second: w})
        params.update()
        dr.eval(mi.render(scene))
        dr.sync_thread()

    def api_frame(w):
        model.render(f"{neutral}={1 - w},{second}={w}", camera=camera, env=env, spp=a.spp)

    for f in (scene_frame, api_frame):   # first frames: kernels, each source's fields, the bases
        f(0.0)
        f(0.5)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    times = {"scene": [], "api": []}
    compiled = 0
    for k in range(a.frames):
        w = (k + 1) / (a.frames + 1)
        for name, f in (("scene", scene_frame), ("api", api_frame)):   # alternating: the same load for both
            dr.kernel_history()
            t0 = time.perf_counter()
            f(w)
            times[name].append(time.perf_counter() - t0)
            if name == "scene":
                compiled += sum(1 for h in dr.kernel_history()
                                if h["type"] == dr.KernelType.JIT and not h.get("cache_hit", False))
    dr.set_flag(dr.JitFlag.KernelHistory, False)
    s, p = statistics.median(times["scene"]), statistics.median(times["api"])
    print(f"{a.size}² × {a.spp} spp, {a.frames} frames of {neutral}/{second}: scene loop (mi.traverse + mi.render) "
          f"{s:.3f} s per frame, Python renderer {p:.3f} s, ratio {s / p:.2f}; kernels compiled by the scene "
          f"loop after its first frames: {compiled}")


if __name__ == "__main__":
    main()
