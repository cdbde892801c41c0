"""A frame's host (Numba) kernels against what they replace, side by side::

    python benchmarks/relight_cpu.py MODEL TRACK [--reps 3] [--env sky] [--size 256] [--switch relight|raster|part-rays|part-cache]

``--switch relight`` (the default): the relight sum on the CPU (``relight_cpu``) against Dr.Jit's kernel
(``Renderer.cpu_relight`` True / False); ``--switch raster``: the primary hits rasterised
(``geometry.raster``) against Mitsuba's ray cast (``MIFACERF_NUMBA_RASTER`` 1 / 0); ``--switch part-rays``:
the parts' rays cast into the scene curved only round the parts (``CombinedScene.rays``, the default)
against the whole Phong scene (before 2026-12-04); ``--switch part-cache``: the parts' views uploaded to the
device once for the frames that read them (``PartFrame(cache=)``, the renderer's) against every frame
(before 2026-12-04).

Three kinds of warm 256² frames, 4 spp, each rendered by one renderer both ways, which way first
alternating frame by frame (the second render of a frame skips the BVH rebuild: until 2026-12-04 the new
way always went first and paid it alone): five frames of the tracked performance ``TRACK`` (the §5 weights of
each frame's mesh, as ``mifacerf drive`` renders them, ~113 chunks), five of the bench's blends of two
expressions from ring cameras (``mifacerf bench``'s frames, 12 chunks), and five single captured
expressions from nearby views (3 chunks). Prints the median seconds per frame of each kind and way, their
ratio, and per frame how far the two images are apart (max |difference|, PSNR over alpha-1 pixels, the
largest alpha difference).
"""
from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("model")
    ap.add_argument("track")
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--env", default="sky")
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--switch", choices=("relight", "raster", "part-rays", "part-cache"), default="relight")
    a = ap.parse_args(argv)
    import drjit as dr

    import mifacerf as mf
    import speed
    from mifacerf.rendering.parts import part_transforms
    from mifacerf.tracking.drive import frame_parts
    from mifacerf.tracking.track import Track

    face = mf.load_model(a.model)
    m = face.model
    tr = Track(a.track)
    s0 = m.expression_index(m.neutral)
    base = part_transforms(m.template, m.eye_centres[s0], m.teeth[s0], m.head_pose[s0]) if m.references else {}
    env = face.environment(a.env)
    r = face.renderer
    r.cache_frames = False
    cam = face.camera(None, a.size)
    picks = np.linspace(10, len(tr.vertices) - 1, 5).astype(int)
    drive = [(tr.vertices[f], face.target(mesh=tr.vertices[f])[1], frame_parts(face, tr, f, base) if base else None)
             for f in picks]
    names = m.expressions
    single = [{"expression": names[i % len(names)], "yaw": y, "pitch": 0.0}
              for i, y in ((0, 5.0), (3, -20.0), (7, 30.0), (11, 0.0), (15, 12.0))]
    kinds = {"drive": [lambda x=x: r.render(x[0], x[1], cam, env, spp=4, parts=x[2]) for x in drive],
             "blend": [lambda fr=fr: speed.render(face, r, fr, a.size, a.env) for fr in speed.draw_frames(face, 5, 7)],
             "single": [lambda fr=fr: speed.render(face, r, fr, a.size, a.env) for fr in single]}
    if a.switch == "relight":
        ways = {"new": True, "old": False}
        names = ("Dr.Jit kernel", "CPU kernel")

        def use(flag):
            r.cpu_relight = flag
    elif a.switch == "part-rays":
        ways = {"new": True, "old": False}
        names = ("whole scene", "curved round the parts")
        reduced = r._combined.rays

        def use(flag):
            r._combined.rays = reduced if flag else r._combined.scene
    elif a.switch == "part-cache":
        ways = {"new": True, "old": False}
        names = ("uploaded every frame", "uploaded once")
        kept = r._part_frames

        def use(flag):
            r._part_frames = kept if flag else None
    else:
        ways = {"new": "1", "old": "0"}
        names = ("ray cast", "raster")

        def use(flag):
            os.environ["MIFACERF_NUMBA_RASTER"] = flag
    for flag in ways.values():          # warm: fields loaded, kernels compiled, for both ways
        use(flag)
        for fs in kinds.values():
            for f in fs:
                f()
    times = {(k, w): [] for k in kinds for w in ways}
    images = {}
    for rep in range(a.reps):
        for k, fs in kinds.items():
            for i, f in enumerate(fs):
                # which way renders a frame first alternates: the second render of a frame finds its geometry
                # in Mitsuba's scene already and skips the BVH rebuild (MeshScene.set_vertices)
                order = list(ways.items()) if (rep + i) % 2 == 0 else list(ways.items())[::-1]
                for w, flag in order:
                    use(flag)
                    dr.sync_thread()
                    t = time.perf_counter()
                    images[(k, i, w)] = f()
                    dr.sync_thread()
                    times[(k, w)].append(time.perf_counter() - t)
    print(f"{a.size}² warm frames, {a.reps} rounds, {a.env}; load {os.getloadavg()[0]:.1f}")
    print(f"| frames | {names[0]} (s) | {names[1]} (s) | × | images: max abs diff, min PSNR (dB), max alpha diff |")
    print("|---|---|---|---|---|")
    for k, fs in kinds.items():
        d, n = np.median(times[(k, "old")]), np.median(times[(k, "new")])
        diffs, psnrs, alpha = [], [], 0.0
        for i in range(len(fs)):
            x, y = images[(k, i, "old")], images[(k, i, "new")]
            mask = (x[..., 3] > 0.999) & (y[..., 3] > 0.999)
            err = float(((x[..., :3] - y[..., :3])[mask] ** 2).mean())
            psnrs.append(np.inf if err == 0 else 10 * np.log10(x[..., :3][mask].max() ** 2 / err))
            diffs.append(float(np.abs(x - y).max()))
            alpha = max(alpha, float(np.abs(x[..., 3] - y[..., 3]).max()))
        print(f"| {k} | {d:.4f} | {n:.4f} | {d / n:.2f} | {max(diffs):.1e}, {min(psnrs):.1f}, {alpha:.3g} |")


if __name__ == "__main__":
    main()
