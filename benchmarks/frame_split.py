"""Where a warm frame's time goes, with the device synchronised after each step::

    python benchmarks/frame_split.py MODEL [--frames 5] [--size 256] [--seed 7] [--config exact]

Dr.Jit's LLVM kernels run asynchronously: a stage of ``RenderStats.times`` that launches kernels ends
before they do, and the next stage that reads a result back waits for them. So the renderer's own stage
times charge the relight kernels to whatever reads first (the trace's vertex update, in practice). Here
each step (the renderer's methods and the ray-casting scene's calls) is wrapped so that it waits for its
kernels (``dr.sync_thread``) before its time is taken: the sum is the frame (a little slower, the
overlap gone), and each step's time is its own. The bench's frames (random two-expression blends, sky,
4 spp), each rendered once before timing (warm model), median over ``--frames`` frames; also the same
frames without the synchronisation, for the frame time a user sees.
"""
from __future__ import annotations

import argparse
import collections
import functools
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

#: (module path, class or None, attribute, label) of the steps timed
STEPS = (
    ("mifacerf.rendering.renderer", "Renderer", "light_frame", "lighting + relight (light_frame)"),
    ("mifacerf.rendering.renderer", None, "plan_frame", "plan"),
    ("mifacerf.rendering.renderer", None, "facing_weights", "facing weights"),
    ("mifacerf.rendering.renderer", None, "resolve_pixels", "resolve"),
    ("mifacerf.rendering.renderer", "Renderer", "_camera_rays", "camera rays"),
    ("mifacerf.rendering.renderer", "Renderer", "_parts_inside_skin", "parts inside the skin"),
    ("mifacerf.rendering.renderer", "Renderer", "part_frame", "eyes/teeth set-up (part_frame)"),
    ("mifacerf.rendering.frame", "ChordOffset", "__call__", "chord offset"),
    ("mifacerf.rendering.frame", "LitFrame", "shade", "skin shading"),
    ("mifacerf.rendering.parts", "CombinedScene", "set_pose", "scene update (parts posed)"),
    ("mifacerf.rendering.parts", "PartFrame", "shade", "eyes/teeth shading"),
    ("mifacerf.geometry.meshscene", "MeshScene", "camera_hits", "primary hits (raster or ray cast)"),
    ("mifacerf.geometry.meshscene", "MeshScene", "commit", "Mitsuba scene update (BVH rebuild; parts hit)"),
    ("mifacerf.geometry.meshscene", "CurvedMeshScene", "commit", "Mitsuba scene update (BVH rebuild; parts hit)"),
    ("mifacerf.geometry.meshscene", "MeshScene", "trace", "ray casts"),
    ("mifacerf.geometry.meshscene", "MeshScene", "set_vertices", "scene update (vertices)"),
)


def main(argv=None) -> None:
    import importlib

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("model")
    ap.add_argument("--frames", type=int, default=5)
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--config", default="exact", help="a speed.py configuration: exact, sh3, pca8, exact/dr, ...")
    a = ap.parse_args(argv)
    import drjit as dr

    import mifacerf as mf
    import speed

    times = collections.defaultdict(float)
    depth = [0]
    sync = [True]

    def wrap(owner, name, label):
        f = getattr(owner, name)

        @functools.wraps(f)
        def timed(*args, **kw):
            depth[0] += 1
            t = time.perf_counter()
            try:
                return f(*args, **kw)
            finally:
                if sync[0]:
                    dr.sync_thread()
                depth[0] -= 1
                if depth[0] == 0:        # nested steps (a trace inside set-up) count once, in the outer
                    times[label] += time.perf_counter() - t

        setattr(owner, name, timed)

    for mod, cls, attr, label in STEPS:
        m = importlib.import_module(mod)
        wrap(getattr(m, cls) if cls else m, attr, label)
    face = mf.load_model(a.model)
    env = face.environment("sky")
    r = speed.renderer_for(face, a.config)
    wrap(type(face), "target", "target mesh and weights (Face.target)")
    wrap(type(face), "parts", "part poses (Face.parts)")
    frames = speed.draw_frames(face, a.frames, a.seed)
    for fr in frames:
        speed.render(face, r, fr, a.size, env)
    out = {}
    for synced in (False, True):
        sync[0] = synced
        times.clear()
        ts = []
        for fr in frames:
            dr.sync_thread()
            t = time.perf_counter()
            speed.render(face, r, fr, a.size, env)
            dr.sync_thread()
            ts.append(time.perf_counter() - t)
        out[synced] = (float(np.median(ts)), {k: v / len(frames) for k, v in times.items()}, float(np.mean(ts)))
    print(f"{a.config}, {a.size}² warm frame, median of {a.frames}: {out[False][0]:.3f} s as rendered, "
          f"{out[True][0]:.3f} s synchronised step by step; load {os.getloadavg()[0]:.1f}")
    total = out[True][2]     # the table's shares: of the mean synchronised frame (the steps are means)
    steps = sorted(out[True][1].items(), key=lambda kv: -kv[1])
    print("| step (synchronised) | s per frame (mean) | share |\n|---|---|---|")
    for k, v in steps:
        print(f"| {k} | {v:.4f} | {100 * v / total:.0f} % |")
    rest = total - sum(v for _, v in steps)
    print(f"| the rest (Python glue between steps) | {rest:.4f} | {100 * rest / total:.0f} % |")


if __name__ == "__main__":
    main()
