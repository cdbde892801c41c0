"""Frame times of a model, measured side by side: every configuration renders the same frame before the
next frame is drawn, so a loaded machine slows them alike (compare the ratios, not the seconds).

    python benchmarks/speed.py MODEL [--configs exact,exact/c1,sh4,pca8] [--sizes 256,1024] [--frames 5]
                               [--sequence 120] [--drive TRACK --drive-frames 30] [--cold] [--skips] [--warm]
                               [--json OUT.json]

Per configuration and size: median seconds per frame over ``--frames`` fresh frames (random blends of
two captured expressions, yaw ±25°, pitch ±6°, 4 spp, sky; ``mifacerf bench``'s frames) after a warm-up frame, the median of each
stage (``RenderStats.times``), the Dr.Jit kernels launched and compiled per frame (kernel history), and
the PSNR of the frame against the ``exact`` configuration's (face pixels, alpha = 1). ``--warm``: every
timed frame is rendered once before (its fields loaded: the stage ``load`` is then ~0, a warm model).
A frame's seconds include ``Face.target`` and ``Face.parts`` (the target mesh and part poses of its
blend), which no render stage counts.
``--sequence N``: an animation of N frames at the first size from one camera (the weights travel
smoothly through four expressions, the head turns a few degrees): frames per second over all N,
kernels compiled after the first frame. ``--drive TRACK``: ``mifacerf drive`` itself (:func:`mifacerf.tracking.drive.drive`)
on the first ``--drive-frames`` frames of a tracked performance at the first size, one environment
(``--env``), PNG + EXR + mp4 written to a temporary folder, the model opened fresh (its fields are loaded
during the run, once): frames per second over all frames and after the first, the mean render seconds
drive.json records, kernels compiled after the first frame. A track's frames carry the §5 weights of its
mesh (per vertex and region: a frame touches every expression, ~130 chunks on the draft model), so they
cost several times a two-expression blend's. ``--skips``: each skip of the exact path on its own (time with
and without, PSNR between the two). ``--cold``: a fresh process imports mifacerf, opens the model
and renders one frame at the first size (seconds since the process started).
The variant is ``$MIFACERF_VARIANT`` (``llvm_ad_rgb`` by default; ``cuda_ad_rgb`` on a GPU:
benchmarks/gpu.sh).
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

import numpy as np


def renderer_for(face, config: str):
    """A configuration name (``exact``, ``<method><rank>``: ``sh4``, ``pca8``; a suffix ``/c<n>`` traces the
    surface at Phong level n instead of the model's own, ``/c1`` flat: ``exact/c1``; a last suffix ``/dr``
    relights with Dr.Jit's kernel instead of the CPU one, ``exact/dr``) → a Renderer of the model."""
    import re

    from mifacerf.rendering.renderer import Renderer

    drjit = config.endswith("/dr")
    name, _, level = config.removesuffix("/dr").partition("/c")
    if level and not level.isdigit():
        raise SystemExit(f"unknown configuration {config!r}: the surface suffix is /c<level>, e.g. exact/c1")
    surface = {"curved": int(level)} if level else {}
    if name == "exact":
        r = Renderer(face.model, **surface)
    else:
        m = re.fullmatch(r"([a-z_]+?)(\d+)", name)
        if not m:
            raise SystemExit(f"unknown configuration {config!r} (exact, or <method><rank> such as sh4, pca8)")
        r = Renderer(face.model, method=m[1], rank=int(m[2]), **surface)
    r.cache_frames = False
    if drjit:
        r.cpu_relight = False
    return r


def draw_frames(face, n: int, seed: int) -> list[dict]:
    """The bench's frames (:func:`mifacerf.evaluation.bench.frames`): random 2-expression blends, ring cameras."""
    from mifacerf.evaluation.bench import frames

    return frames(face.model, n, seed, 0)


def compiled_kernels(history) -> tuple[int, int]:
    import drjit as dr

    jit = [e for e in history if e["type"] == dr.KernelType.JIT]
    return len(jit), sum(1 for e in jit if not e["cache_hit"])


def psnr(img, ref) -> float:
    m = (ref[..., 3] > 0.999) & (img[..., 3] > 0.999)
    err = float(((img[..., :3] - ref[..., :3])[m] ** 2).mean()) if m.any() else 0.0
    return float("inf") if err == 0 else float(10 * np.log10(ref[..., :3][m].max() ** 2 / err))


def render(face, renderer, fr, size, env, spp=4, seed=0, stats=None):
    cam = face.camera((fr["yaw"], fr["pitch"]), size=size)
    target, W = face.target(fr["expression"])
    return renderer.render(target, W, cam, face.environment(env), spp=spp, seed=seed, stats=stats,
                           parts=face.parts(fr["expression"]))


def frames_table(face, configs, sizes, n_frames, env, seed, warm=False):
    import drjit as dr

    from mifacerf.rendering.renderer import RenderStats

    renderers = {c: renderer_for(face, c) for c in configs}
    rows = []
    for size in sizes:
        frames = draw_frames(face, n_frames + 1, seed + size)
        if warm:   # a warm model: every frame's fields loaded and its lighting nodes evaluated before timing
            for fr in frames[1:]:
                for c in configs:
                    render(face, renderers[c], fr, size, env)
        per = {c: {"seconds": [], "stages": [], "kernels": [], "compiled": [], "psnr_exact": []} for c in configs}
        for k, fr in enumerate(frames):
            ref = None
            for c in configs:
                st = RenderStats()
                dr.kernel_history()
                t0 = time.perf_counter()
                img = render(face, renderers[c], fr, size, env, stats=st)
                dt = time.perf_counter() - t0
                launched, compiled = compiled_kernels(dr.kernel_history())
                if c == "exact":
                    ref = img
                if k == 0:
                    continue      # the warm-up frame (fields loaded, kernels compiled)
                p = per[c]
                p["seconds"].append(dt)
                p["stages"].append(st.times)
                p["kernels"].append(launched)
                p["compiled"].append(compiled)
                if ref is not None:
                    p["psnr_exact"].append(psnr(img, ref))
        for c in configs:
            p = per[c]
            stages = sorted({s for t in p["stages"] for s in t})
            rows.append({"config": c, "size": size, "frames": n_frames,
                         "median_s": float(np.median(p["seconds"])), "seconds": p["seconds"],
                         "stages_median_s": {s: float(np.median([t.get(s, 0.0) for t in p["stages"]])) for s in stages},
                         "kernels_per_frame": float(np.median(p["kernels"])),
                         "compiled_per_frame": p["compiled"],
                         "psnr_vs_exact_db": float(np.median(p["psnr_exact"])) if p["psnr_exact"] else None})
    return rows


def sequence(face, config, n, size, env):
    """An animation of ``n`` frames from one camera: fps over all, kernels compiled after frame 0."""
    import drjit as dr

    renderer = renderer_for(face, config)
    names = face.expressions[:4]
    t = np.linspace(0, len(names), n, endpoint=False)
    compiled = []
    times = []
    for k, x in enumerate(t):
        i = int(x) % len(names)
        w = float(x - int(x))
        spec = {names[i]: 1 - w, names[(i + 1) % len(names)]: w} if w > 0 else {names[i]: 1.0}
        fr = {"expression": spec, "yaw": 5 * np.sin(2 * np.pi * k / n), "pitch": 0.0}
        dr.kernel_history()
        t0 = time.perf_counter()
        render(face, renderer, fr, size, env, seed=k)
        times.append(time.perf_counter() - t0)
        compiled.append(compiled_kernels(dr.kernel_history())[1])
    return {"config": config, "size": size, "frames": n, "fps": float(n / sum(times)),
            "fps_after_first": float((n - 1) / sum(times[1:])) if n > 1 else None,
            "first_frame_s": times[0], "compiled_after_first": int(sum(compiled[1:]))}


def drive_sequence(model, track, n, size, env):
    """``mifacerf drive`` on the first ``n`` frames of ``track`` (a fresh model, one environment, a temporary
    folder): fps over all frames and after the first (the frames' completion times, seen by an observer),
    drive.json's render seconds per frame, kernels compiled after the first frame."""
    import tempfile
    from pathlib import Path

    import drjit as dr

    import mifacerf as mf
    from mifacerf.tracking.drive import FrameObserver, drive

    class Clock(FrameObserver):
        def __init__(self):
            self.done, self.compiled = [], []

        def frame(self, f, rgba, plate, picked):
            self.done.append(time.perf_counter())
            self.compiled.append(compiled_kernels(dr.kernel_history())[1])

    face = mf.load_model(model)
    clock = Clock()
    with tempfile.TemporaryDirectory() as tmp:
        dr.kernel_history()
        t0 = time.perf_counter()
        out = drive(track, face, out=Path(tmp) / "drive", envs=(env,), frames=(0, n), size=size, progress=False,
                    observer=clock)
        total = time.perf_counter() - t0
        meta = json.loads((out / "drive.json").read_text())
    e = next(iter(meta["environments"].values()))
    steps = np.diff([t0] + clock.done)
    return {"track": str(track), "frames": len(steps), "size": size, "env": env, "seconds": total,
            "fps": float(len(steps) / total), "first_frame_s": float(steps[0]),
            "fps_after_first": float((len(steps) - 1) / steps[1:].sum()) if len(steps) > 1 else None,
            "render_seconds_per_frame": e["render_seconds_per_frame"],
            "write_seconds_per_frame": e["write_seconds_per_frame"],
            "compiled_after_first": int(sum(clock.compiled[1:]))}


def skips(face, n_frames, size, env, seed):
    """Each skip of the exact path measured in isolation, side by side: median seconds with and without it
    and the PSNR between the two images (inf: identical)."""
    from mifacerf.rendering.renderer import Renderer

    frames = draw_frames(face, n_frames + 1, seed)
    variants = {"all lights (light_epsilon 0)": dict(light_epsilon=0.0), "default": {}}
    rs = {k: Renderer(face.model, **kw) for k, kw in variants.items()}
    for r in rs.values():
        r.cache_frames = False
    t = {k: [] for k in rs}
    p = []
    for i, fr in enumerate(frames):
        imgs = {}
        for k, r in rs.items():
            t0 = time.perf_counter()
            imgs[k] = render(face, r, fr, size, env)
            if i:
                t[k].append(time.perf_counter() - t0)
        if i:
            p.append(psnr(imgs["default"], imgs["all lights (light_epsilon 0)"]))
    out = [{"skip": "negligible lights (light_epsilon 1e-4)", "without_s": float(np.median(t["all lights (light_epsilon 0)"])),
            "with_s": float(np.median(t["default"])), "psnr_db": float(np.median(p))}]
    # an unchanged frame: the digest of the inputs returns the previous image
    r = Renderer(face.model)
    render(face, r, frames[1], size, env)
    t0 = time.perf_counter()
    render(face, r, frames[1], size, env)
    cached = time.perf_counter() - t0
    out.append({"skip": "unchanged frame (cache_frames)", "without_s": float(np.median(t["default"])),
                "with_s": cached, "psnr_db": float("inf")})
    # eyes and teeth only where a sample hits them: the skin-only frame is the pass's cost
    r.cache_frames = False
    ts, tp = [], []
    for fr in frames[1:]:
        cam = face.camera((fr["yaw"], fr["pitch"]), size=size)
        target, W = face.target(fr["expression"])
        t0 = time.perf_counter()
        r.render(target, W, cam, env, spp=4)
        ts.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        r.render(target, W, cam, env, spp=4, parts=face.parts(fr["expression"]))
        tp.append(time.perf_counter() - t0)
    out.append({"skip": "eyes/teeth pass (run only when a sample hits a part): with it vs a skin-only frame", "without_s": float(np.median(tp)),
                "with_s": float(np.median(ts)), "psnr_db": None})
    out.append(unchanged_geometry(face, frames[1]["expression"], size, env))
    return out


def unchanged_geometry(face, expression, size, env, yaws=(-20, -10, 0, 10, 20), rounds=3):
    """A turntable of one expression (the same target from ``yaws``): Mitsuba's scene update, which rebuilds
    the BVH, skipped while the vertices are unchanged (``MeshScene.set_vertices``) against forced, alternating."""
    from mifacerf.geometry import meshscene
    from mifacerf.rendering.renderer import Renderer

    r = Renderer(face.model)
    r.cache_frames = False
    frames = [{"expression": expression, "yaw": y, "pitch": 0.0} for y in yaws]
    for fr in frames:
        render(face, r, fr, size, env)
    scenes = [r._scene] + ([r._combined.scene] if r._combined is not None else [])
    t = {True: [], False: []}
    p = []
    for _ in range(rounds):
        for fr in frames:
            imgs = {}
            for skip in (True, False):
                if not skip:           # forget what the scenes hold: the next update rebuilds
                    for sc in scenes:
                        getattr(sc, "_curved", sc)._in_scene = None
                t0 = time.perf_counter()
                imgs[skip] = render(face, r, fr, size, env)
                t[skip].append(time.perf_counter() - t0)
            p.append(psnr(imgs[True], imgs[False]))
    return {"skip": "unchanged geometry (a turntable of one expression: no BVH rebuild)",
            "without_s": float(np.median(t[False])), "with_s": float(np.median(t[True])), "psnr_db": float(np.median(p))}


def cold(model, size, env):
    """Seconds from a fresh process's start to its first frame (import, open the model, render)."""
    code = ("import sys; sys.path.insert(0, %r); import speed, mifacerf as mf; face = mf.load_model(%r); "
            "fr = speed.draw_frames(face, 1, 1)[0]; speed.render(face, face.renderer, fr, %d, %r); "
            "from mifacerf.evaluation.bench import process_age; print(process_age())") % (os.path.dirname(os.path.abspath(__file__)), str(model), size, env)
    out = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, text=True).stdout
    return float(out.strip().splitlines()[-1])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("model")
    ap.add_argument("--configs", default="exact")
    ap.add_argument("--sizes", default="256")
    ap.add_argument("--frames", type=int, default=5)
    ap.add_argument("--sequence", type=int, default=0)
    ap.add_argument("--sequence-config", default="exact")
    ap.add_argument("--drive", default=None, metavar="TRACK", help="time mifacerf drive on this tracked performance")
    ap.add_argument("--drive-frames", type=int, default=30)
    ap.add_argument("--cold", action="store_true")
    ap.add_argument("--skips", action="store_true", help="measure each skip of the exact path in isolation")
    ap.add_argument("--warm", action="store_true",
                    help="render every timed frame once before timing it (fields loaded: the issue's warm model)")
    ap.add_argument("--env", default="sky")
    ap.add_argument("--seed", type=int, default=int(time.time()))
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    import mifacerf as mf
    from mifacerf.variant import variant_name

    sizes = [int(s) for s in a.sizes.split(",")]
    configs = a.configs.split(",")
    if "exact" in configs:           # the reference renders first in every frame
        configs = ["exact"] + [c for c in configs if c != "exact"]
    report = {"model": str(a.model), "variant": variant_name(), "cpus": os.cpu_count(),
              "load_before": os.getloadavg(), "seed": a.seed}
    if a.cold:
        report["cold_start_s"] = cold(a.model, sizes[0], a.env)
        print(f"cold start (import, open model, first {sizes[0]}² frame): {report['cold_start_s']:.2f} s", flush=True)
    import drjit as dr

    dr.set_flag(dr.JitFlag.KernelHistory, True)
    face = mf.load_model(a.model)
    env = face.environment(a.env)
    if a.frames > 0:
        report["frames"] = frames_table(face, configs, sizes, a.frames, env, a.seed, a.warm)
        print("| config | size | median s/frame | × exact | PSNR vs exact (dB) | kernels/frame | compiled/frame | "
              "stages (median s) |\n|---|---|---|---|---|---|---|---|")
        for r in report["frames"]:
            ex = next(x for x in report["frames"] if x["size"] == r["size"] and x["config"] == configs[0])
            pe = r["psnr_vs_exact_db"]
            print(f"| {r['config']} | {r['size']}² | {r['median_s']:.3f} | {ex['median_s'] / r['median_s']:.2f} | "
                  f"{'—' if pe is None or r['config'] == 'exact' else f'{pe:.1f}'} | {r['kernels_per_frame']:.0f} | "
                  f"{max(r['compiled_per_frame'])} | "
                  + ", ".join(f"{k} {v:.3f}" for k, v in r["stages_median_s"].items() if v >= 0.0005) + " |",
                  flush=True)
    if a.skips:
        report["skips"] = skips(face, a.frames, sizes[0], env, a.seed)
        print("| skip | without (s) | with (s) | PSNR with vs without (dB) |\n|---|---|---|---|")
        for r in report["skips"]:
            pe = "—" if r["psnr_db"] is None else f"{r['psnr_db']:.1f}"
            print(f"| {r['skip']} | {r['without_s']:.3f} | {r['with_s']:.4f} | {pe} |", flush=True)
    if a.sequence:
        report["sequence"] = sequence(face, a.sequence_config, a.sequence, sizes[0], env)
        s = report["sequence"]
        print(f"sequence: {s['frames']} frames {s['size']}² ({s['config']}): {s['fps']:.1f} fps "
              f"({s['fps_after_first']:.1f} after the first), kernels compiled after the first frame: "
              f"{s['compiled_after_first']}", flush=True)
    if a.drive:
        report["drive"] = drive_sequence(a.model, a.drive, a.drive_frames, sizes[0], a.env)
        d = report["drive"]
        print(f"drive: {d['frames']} frames {d['size']}² ({d['env']}): {d['fps']:.2f} fps ({d['fps_after_first']:.2f} "
              f"after the first, first {d['first_frame_s']:.1f} s); render {d['render_seconds_per_frame']:.3f} s, "
              f"write {d['write_seconds_per_frame']:.3f} s per frame; kernels compiled after the first frame: "
              f"{d['compiled_after_first']}", flush=True)
    report["load_after"] = os.getloadavg()
    print(f"load average before {report['load_before'][0]:.1f}, after {report['load_after'][0]:.1f}; "
          f"{report['cpus']} CPUs; variant {report['variant']}")
    if a.json:
        with open(a.json, "w") as f:
            json.dump(report, f, indent=1)
    return report


if __name__ == "__main__":
    main()
