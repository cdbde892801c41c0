"""``mifacerf bench``: run time per frame against error, for every way of rendering the model.

Configurations (all in one run; times are ratios to the dense reference):

* ``dense``   — the straightforward NumPy reference: every light of every field (:mod:`.dense_reference`);
* ``exact``   — the Dr.Jit exact path (render chunks, lit textures; :mod:`mifacerf.rendering.renderer`);
* ``pca<K>``  — the compressed path with K coefficients per texel (:mod:`mifacerf.rendering.compression`;
  ``<method><K>`` for every compressed method the model holds, by its name in ``COMPRESSION_METHODS``);
* ``exact@<size>`` — the exact path at another image size;
* ``lights/<n>``   — the exact path with a subset of the light stage (every n-th arm position and strobe);
* ``size/<n>``     — the exact path at n² pixels, timed only (no ground truth at that size): the resolution
  sweep (128² … 1024² with ``exact@128`` and the job's size);
* ``cold``         — a fresh process: import, open the model, render the first frame (seconds since the
  process started; no warm-up);
* ``sequence``     — an animation of ``sequence_frames`` frames from the first frame's camera, the weights
  travelling through the job's blends (frames per second = 1 / its s/frame; kernels compiled after its
  first frame recorded: zero when nothing recompiles).

Each configuration runs in a fresh worker process (so its peak memory, ``VmHWM``, is its own),
renders the same frames (blends of captured expressions from novel viewpoints, §5-free) after a
warm-up frame, and reports seconds per frame. Errors: PSNR on the face mask against path-traced
ground truth and against the exact path. Sizes on disk: the data each configuration reads.
Outputs: ``results.json``, ``table.md`` and ``runtime_vs_error.png`` in the output folder.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import click
import numpy as np

from ..execution import Executor


def frames(model, n: int, seed: int, size: int):
    """``n`` benchmark frames: random 2-expression blends from random ring cameras."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        a, b = rng.choice(model.expressions, size=2, replace=False)
        w = float(rng.uniform(0.2, 0.8))
        out.append({"expression": {str(a): w, str(b): 1 - w},
                    "yaw": float(rng.uniform(-25, 25)), "pitch": float(rng.uniform(-6, 6))})
    return out


#: the resolution sweep's sizes beside the job's own and exact@128 (``size/<n>`` rows)
SWEEP_SIZES = (512, 1024)


def configs(model_meta: dict, quick: bool = False, sweep=SWEEP_SIZES) -> list[str]:
    compressed = [f"{method}{k}" for method, ranks in model_meta.get("compressed", {}).items() for k in ranks]
    out = ["dense", "exact"] + compressed + ["exact@128", "lights/2"] + [f"size/{n}" for n in sweep] + \
        ["cold", "sequence"]
    return out if not quick else ["dense", "exact"] + compressed[:1] + ["cold", "sequence"]


def compressed_config(config: str) -> tuple[str, int] | None:
    """``"<method><rank>"`` (``pca8``) → (method, rank) for a compression method that writes files, else None."""
    import re

    from ..rendering.compression import compressing_methods

    m = re.fullmatch(r"([a-z_]+?)(\d+)", config)
    return (m[1], int(m[2])) if m and m[1] in compressing_methods() else None


def vm_hwm() -> int:
    """Peak resident memory of this process in bytes (Linux ``VmHWM``), or -1."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return -1


def process_age() -> float:
    """Seconds since this process started (Linux ``/proc``; elsewhere since this module was imported)."""
    try:
        start = int(Path("/proc/self/stat").read_text().rsplit(")", 1)[1].split()[19]) / os.sysconf("SC_CLK_TCK")
        return float(Path("/proc/uptime").read_text().split()[0]) - start
    except (OSError, ValueError, IndexError):
        return time.perf_counter() - _IMPORTED


_IMPORTED = time.perf_counter()


def sequence_frames(frames: list[dict], n: int) -> list[dict]:
    """``n`` frames from the first frame's camera whose weights travel linearly through the blends of ``frames``
    (one after another, back to the first)."""
    out = []
    for k in range(n):
        x = k * len(frames) / n
        a, b = frames[int(x)]["expression"], frames[(int(x) + 1) % len(frames)]["expression"]
        w = x - int(x)
        spec = {e: (1 - w) * a.get(e, 0.0) + w * b.get(e, 0.0) for e in {*a, *b}}
        out.append({"expression": {e: v for e, v in spec.items() if v > 0}, "yaw": frames[0]["yaw"],
                    "pitch": frames[0]["pitch"]})
    return out


def worker(job_path: str, config: str) -> None:
    """Render the job's frames with one configuration; write renders and timings next to the job."""
    from ..rendering.api import load_model
    from ..rendering.renderer import Renderer, RenderStats
    from .dense_reference import dense_render

    job = json.loads(Path(job_path).read_text())
    out = Path(job["out"]) / config.replace("/", "_")
    out.mkdir(parents=True, exist_ok=True)
    for old in out.glob("frame*.npy"):   # a row that saves no frames must not show an earlier run's
        old.unlink()
    face = load_model(job["model"])
    size = job["size"]
    if config.startswith("exact@"):
        size = int(config.split("@")[1])
    if config.startswith("size/"):
        size = int(config.split("/")[1])
    compressed = compressed_config(config)
    if compressed:
        face.renderer = Renderer(face.model, method=compressed[0], rank=compressed[1])
    elif config.startswith("lights/"):
        step = int(config.split("/")[1])
        n_str = job["n_strobes"]
        idx = np.arange(face.model.n_lights)
        keep = idx[((idx // n_str) % step == 0) & ((idx % n_str) % step == 0)]
        face.renderer = Renderer(face.model, lights=keep)
    face.renderer.cache_frames = False   # the warm-up frame repeats frame 1: time real renders
    env = face.environment(job["env"])
    frames = [job["frames"][0]] + job["frames"]        # frame 0 is the warm-up
    save = not (config.startswith("size/") or config in ("cold", "sequence"))
    history = None
    if config == "cold":
        frames = job["frames"][:1]
    elif config == "sequence":
        import drjit as dr

        frames = sequence_frames(job["frames"], int(job.get("sequence_frames", 120)))
        face.renderer.cache_frames = True              # as mifacerf drive renders
        history_was = dr.flag(dr.JitFlag.KernelHistory)
        dr.set_flag(dr.JitFlag.KernelHistory, True)
        history = []
    times, stages = [], []
    for i, fr in enumerate(frames):
        cam = face.camera((fr["yaw"], fr["pitch"]), size=size)
        target, W = face.target(fr["expression"])
        st = RenderStats()
        if history is not None:
            dr.kernel_history()
        t0 = time.perf_counter()
        if config == "dense":
            img = dense_render(face.renderer, target, W, cam, env, spp=job["spp"])
        else:
            img = face.renderer.render(target, W, cam, env, spp=job["spp"], stats=st)
        dt = time.perf_counter() - t0
        if history is not None:
            history.append(sum(1 for e in dr.kernel_history() if e["type"] == dr.KernelType.JIT and not e["cache_hit"]))
        if config == "cold":
            times.append(process_age())
            stages.append(st.times)
        elif i > 0 or config == "sequence":
            times.append(dt)
            stages.append(st.times)
            if save:
                np.save(out / f"frame{i - 1}.npy", img)
    timing = {"seconds": times, "stages": stages, "peak_bytes": vm_hwm(), "median_seconds": float(np.median(times))}
    if history is not None:
        timing["compiled_after_first"] = int(sum(history[1:]))
        dr.kernel_history()
        dr.set_flag(dr.JitFlag.KernelHistory, history_was)   # as it was (a worker run in the caller's process)
    (out / "timing.json").write_text(json.dumps(timing))


def disk_bytes(model_root: Path, config: str) -> int:
    fields = model_root / "fields"
    compressed = compressed_config(config)
    if compressed:
        pats = [f"*.{compressed[0]}{compressed[1]}.npz", "*.texels.npz"]
    else:
        pats = ["*.rf.npy", "*.texels.npz"]
    total = sum(p.stat().st_size for pat in pats for p in fields.rglob(pat) if ".parts" not in p.name)
    if config.startswith("lights/"):
        step = int(config.split("/")[1])
        total = int(total / step ** 2)  # the subset's share of the reflectance data (estimate)
    return total


def truth_unit(context, unit: tuple) -> tuple[np.ndarray, np.ndarray]:
    """Ground-truth frame ``(i, frame)`` → (path-traced truth (H, W, 4), its face mask (H, W)); ``context``: a
    :class:`.render_cases.CaseContext` with ``env``, ``size`` and ``spp_truth``."""
    from .masks import classify_pixels, face_mask

    i, f = unit
    tr, face = context.opened()
    cam = face.camera((f["yaw"], f["pitch"]), size=context.size)
    t = tr.render(tr.blend(f["expression"]), cam, context.env, spp=context.spp_truth, seed=100 + i)
    return t, face_mask(classify_pixels(tr.scene(face.environment(context.env)), cam)) & (t[..., 3] > 0.999)


def config_unit(job_path: str, cfg: str) -> dict:
    """One configuration of the sweep: :func:`worker` in a process of its own (its peak memory is its own);
    returns its ``timing.json``."""
    subprocess.run([sys.executable, "-m", "mifacerf.evaluation.bench", str(job_path), cfg], check=True,
                   env={**os.environ})
    return _timing(job_path, cfg)


def config_here(job_path: str, cfg: str) -> dict:
    """:func:`config_unit` in this process (``run(processes=False)``): no process start per configuration;
    the peak memory is this process's. ``cold`` still starts its fresh process (that is what it measures)."""
    if cfg == "cold":
        return config_unit(job_path, cfg)
    worker(job_path, cfg)
    return _timing(job_path, cfg)


def _timing(job_path: str, cfg: str) -> dict:
    return json.loads((Path(json.loads(Path(job_path).read_text())["out"]) / cfg.replace("/", "_") /
                       "timing.json").read_text())


#: ``--quick``'s sequence row: this many frames (the full row: ``sequence_frames``, the demo's 120)
QUICK_SEQUENCE_FRAMES = 12


def run(model, synth_out, out, n_frames: int = 3, size: int = 256, env: str = "sky", spp: int = 1,
        spp_truth: int = 1024, seed: int = 7, quick: bool = False, progress: bool = True, executor=None,
        sequence_frames: int = 120, sweep=SWEEP_SIZES, only=None, processes: bool = True) -> dict:
    """Run the benchmark (``progress``: bars over the truths and the configurations); returns the results
    (also written to ``out``).

    ``quick``: dense, exact, the first compressed rank, the cold start and a sequence of
    :data:`QUICK_SEQUENCE_FRAMES` frames. ``only``: the configurations to run (names of :func:`configs`, in
    its order; ``dense`` and ``exact`` always run, every row is measured against them). ``processes``: each
    configuration in a fresh worker process (the default: its peak memory is its own); False runs them in
    this process (:func:`config_here`; a quick check of the benchmark itself, e.g. its smoke test).

    ``executor`` (:mod:`mifacerf.execution`; default: this process) runs the ground-truth frames and the
    configurations as units. Configurations run at once on one machine share its cores: their times are
    each other's load (compare times from one run with one worker per machine)."""
    from ..rendering.api import load_model
    from ..synthetic.truth_scene import TruthRenderer
    from .masks import classify_pixels, face_mask
    from .metrics import psnr
    from .render_cases import CaseContext

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    face = load_model(model)
    cfgs = configs(face.model.meta, quick, sweep)
    if only is not None:
        unknown = sorted(set(only) - set(cfgs))
        if unknown:
            raise ValueError(f"unknown bench configuration(s) {', '.join(unknown)}; this model has {', '.join(cfgs)}")
        cfgs = [c for c in cfgs if c in {"dense", "exact", *only}]
    fr = frames(face.model, n_frames, seed, size)
    tr = TruthRenderer.from_synth(synth_out)
    ex = executor or Executor()
    context = CaseContext(synth_out, model, tr, face, env=env, size=size, spp_truth=spp_truth)
    done = ex.map(truth_unit, list(enumerate(fr)), context,
                  desc="ground truth", unit="frame", progress=progress)
    truths, masks = [t for t, _ in done], [m for _, m in done]
    n_str = int(json.loads((Path(synth_out) / "capture" / "manifest.json").read_text())["rig"]["lights"]
                ["layout"]["n_strobes"])
    if quick:
        sequence_frames = min(int(sequence_frames), QUICK_SEQUENCE_FRAMES)
    job = {"model": str(Path(model).resolve()), "frames": fr, "size": size, "env": env, "spp": spp,
           "out": str(out.resolve()), "n_strobes": n_str, "sequence_frames": int(sequence_frames)}
    job_path = out / "job.json"
    job_path.write_text(json.dumps(job))
    results = []
    timings = ex.imap(config_unit if processes else config_here, cfgs, str(job_path), desc="configurations",
                      unit="config", progress=progress)
    for cfg, timing in zip(cfgs, timings):
        results.append({"config": cfg, "seconds_per_frame": float(np.mean(timing["seconds"])),
                        "peak_bytes": timing["peak_bytes"], "disk_bytes": disk_bytes(Path(model), cfg),
                        "stages": {k: float(np.mean([s.get(k, 0) for s in timing["stages"]]))
                                   for k in sorted({k for s in timing["stages"] for k in s})}})
    exact = {i: np.load(out / "exact" / f"frame{i}.npy") for i in range(n_frames)}
    for r in results:
        d = out / r["config"].replace("/", "_")
        timing = json.loads((d / "timing.json").read_text())
        r["median_seconds"] = timing.get("median_seconds")
        if "compiled_after_first" in timing:
            r["compiled_after_first"] = timing["compiled_after_first"]
        if not (d / "frame0.npy").exists():     # timed only: the sweep's sizes, the cold start, the sequence
            r["psnr_truth"] = r["psnr_exact"] = None
            continue
        p_truth, p_exact = [], []
        for i in range(n_frames):
            img = np.load(d / f"frame{i}.npy")
            if img.shape != truths[i].shape:  # another image size: compare at that size
                cam = face.camera((fr[i]["yaw"], fr[i]["pitch"]), size=img.shape[0])
                t = tr.render(tr.blend(fr[i]["expression"]), cam, env, spp=spp_truth, seed=100 + i)
                m = face_mask(classify_pixels(tr.scene(face.environment(env)), cam)) & (t[..., 3] > 0.999)
                p_truth.append(psnr(img, t, m & (img[..., 3] > 0.999)))
                continue
            m = masks[i] & (img[..., 3] > 0.999)
            p_truth.append(psnr(img, truths[i], m))
            p_exact.append(psnr(img, exact[i], m & (exact[i][..., 3] > 0.999)))
        r["psnr_truth"] = float(np.mean(p_truth))
        r["psnr_exact"] = float(np.mean(p_exact)) if p_exact else None
    dense = next(r for r in results if r["config"] == "dense")
    exact_r = next(r for r in results if r["config"] == "exact")
    for r in results:
        r["speedup_vs_dense"] = dense["seconds_per_frame"] / r["seconds_per_frame"]
        r["speedup_vs_exact"] = exact_r["seconds_per_frame"] / r["seconds_per_frame"]
        r["size_vs_exact"] = exact_r["disk_bytes"] / max(r["disk_bytes"], 1)
    report = {"frames": fr, "size": size, "env": env, "spp": spp, "spp_truth": spp_truth, "results": results,
              "machine": {"cpus": os.cpu_count()}}
    (out / "results.json").write_text(json.dumps(report, indent=1))
    write_table(report, out / "table.md")
    plot(report, out / "runtime_vs_error.png")
    return report


def config_label(r: dict) -> str:
    """A row's name in the table: the timed-only rows say what their seconds are."""
    c = r["config"]
    if c == "cold":
        return "cold start (s: import, open, first frame)"
    if c == "sequence":
        return (f"sequence ({1 / r['seconds_per_frame']:.1f} fps; "
                f"{r.get('compiled_after_first', '?')} kernels compiled after frame 1)")
    if c.startswith("size/"):
        return f"exact at {c.split('/')[1]}² (time only)"
    return c


def write_table(report: dict, path: Path) -> None:
    rows = ["| configuration | s / frame | × dense | × exact | PSNR vs truth (dB) | PSNR vs exact (dB) | "
            "peak memory (MB) | data on disk (MB) | × smaller than exact |",
            "|---|---|---|---|---|---|---|---|---|"]
    for r in report["results"]:
        pe = "—" if r["psnr_exact"] is None else (f"{r['psnr_exact']:.1f}" if np.isfinite(r["psnr_exact"]) else "∞")
        pt = "—" if r["psnr_truth"] is None else f"{r['psnr_truth']:.2f}"
        rows.append(f"| {config_label(r)} | {r['seconds_per_frame']:.3f} | {r['speedup_vs_dense']:.1f} | "
                    f"{r['speedup_vs_exact']:.2f} | {pt} | {pe} | {r['peak_bytes'] / 1e6:.0f} | "
                    f"{r['disk_bytes'] / 1e6:.1f} | {r['size_vs_exact']:.1f} |")
    path.write_text("\n".join(rows) + "\n")


def plot(report: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.2), dpi=120)
    for r in report["results"]:
        if r["psnr_truth"] is None:
            continue
        ax.scatter(r["seconds_per_frame"], r["psnr_truth"], s=30)
        ax.annotate(r["config"], (r["seconds_per_frame"], r["psnr_truth"]), textcoords="offset points",
                    xytext=(4, 3), fontsize=8)
    ax.set_xscale("log")
    ax.set_xlabel(f"seconds per {report['size']}² frame (log)")
    ax.set_ylabel("PSNR against path-traced ground truth (dB)")
    ax.set_title("run time against error")
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def compression_knob(model, synth_out, out, configs=("exact", "sh2", "sh3", "sh4", "sh6", "sh8"), n_frames: int = 3,
                     size: int = 256, env: str = "sky", spp: int = 4, spp_truth: int = 64, seed: int = 7,
                     warm: bool = False) -> dict:
    """The compression knob (rank / order) against size, time and error, side by side in this process.

    Every configuration (``exact`` or ``<method><rank>`` of a compressed copy the model holds) renders each of
    ``n_frames`` bench frames (:func:`frames`) after a warm-up frame, one after another, so a loaded machine slows
    them alike. Per configuration: data on disk, median seconds per frame and of the relight stage, PSNR on
    the face mask against the path-traced truth and against the exact path. Writes ``knob.json`` and
    ``knob.png`` (three panels over the knob: size, time, error) to ``out``; returns the report. ``warm``:
    every frame is rendered once by every configuration before the timed pass (fields loaded, lighting
    cached: the times are then the render's, not the disk's).
    """
    from ..rendering.api import load_model
    from ..rendering.renderer import Renderer, RenderStats
    from ..synthetic.truth_scene import TruthRenderer
    from .masks import classify_pixels, face_mask
    from .metrics import psnr

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    face = load_model(model)
    envo = face.environment(env)
    tr = TruthRenderer.from_synth(synth_out)
    fr = frames(face.model, n_frames + 1, seed, size)
    renderers = {}
    for c in configs:
        comp = compressed_config(c)
        renderers[c] = Renderer(face.model) if comp is None else Renderer(face.model, method=comp[0], rank=comp[1])
        renderers[c].cache_frames = False
    rows = {c: {"seconds": [], "relight": [], "psnr_truth": [], "psnr_exact": []} for c in configs}
    if warm:
        for f in fr:
            cam = face.camera((f["yaw"], f["pitch"]), size=size)
            target, W = face.target(f["expression"])
            for c in configs:
                renderers[c].render(target, W, cam, envo, spp=spp, parts=face.parts(f["expression"]))
    for i, f in enumerate(fr):
        cam = face.camera((f["yaw"], f["pitch"]), size=size)
        target, W = face.target(f["expression"])
        parts = face.parts(f["expression"])
        if i:
            t = tr.render(tr.blend(f["expression"]), cam, env, spp=spp_truth, seed=100 + i)
            mask = face_mask(classify_pixels(tr.scene(envo), cam)) & (t[..., 3] > 0.999)
        ref = None
        for c in configs:
            st = RenderStats()
            t0 = time.perf_counter()
            img = renderers[c].render(target, W, cam, envo, spp=spp, stats=st, parts=parts)
            dt = time.perf_counter() - t0
            ref = img if ref is None else ref
            if not i:
                continue
            m = mask & (img[..., 3] > 0.999)
            rows[c]["seconds"].append(dt)
            rows[c]["relight"].append(st.times.get("relight", 0.0))
            rows[c]["psnr_truth"].append(psnr(img, t, m))
            rows[c]["psnr_exact"].append(psnr(img, ref, m & (ref[..., 3] > 0.999)))
    report = {"model": str(model), "size": size, "spp": spp, "spp_truth": spp_truth, "env": env, "frames": fr[1:],
              "warm": bool(warm),
              "load": os.getloadavg(), "reference": configs[0], "rows": []}
    for c in configs:
        r = rows[c]
        report["rows"].append({"config": c, "disk_bytes": disk_bytes(Path(model), c),
                               "median_seconds": float(np.median(r["seconds"])),
                               "median_relight_seconds": float(np.median(r["relight"])),
                               "psnr_truth": float(np.mean(r["psnr_truth"])),
                               "psnr_exact": float(np.mean(r["psnr_exact"])) if c != configs[0] else None})
    (out / "knob.json").write_text(json.dumps(report, indent=1))
    plot_knob(report, out / "knob.png")
    return report


def plot_knob(report: dict, path: Path) -> None:
    """Size, time and error of every configuration over its knob, one panel each (lines per method)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = report["rows"]
    ref = rows[0]
    fig, axes = plt.subplots(1, 3, figsize=(11, 3.4), dpi=120)
    by_method: dict = {}
    for r in rows[1:]:
        comp = compressed_config(r["config"])
        if comp:
            by_method.setdefault(comp[0], []).append((comp[1], r))
    for method, pts in by_method.items():
        pts.sort()
        k = [p[0] for p in pts]
        axes[0].plot(k, [ref["disk_bytes"] / p[1]["disk_bytes"] for p in pts], "o-", label=method)
        axes[1].plot(k, [ref["median_seconds"] / p[1]["median_seconds"] for p in pts], "o-", label=f"{method}: frame")
        axes[1].plot(k, [ref["median_relight_seconds"] / max(p[1]["median_relight_seconds"], 1e-9) for p in pts],
                     "s--", label=f"{method}: relight stage")
        axes[2].plot(k, [p[1]["psnr_truth"] - ref["psnr_truth"] for p in pts], "o-", label=method)
    axes[0].axhline(10, color="grey", lw=0.8, ls=":")
    axes[1].axhline(5, color="grey", lw=0.8, ls=":")
    axes[2].axhline(-1, color="grey", lw=0.8, ls=":")
    axes[0].set_ylabel(f"× smaller than {ref['config']}")
    axes[1].set_ylabel(f"× faster than {ref['config']}")
    axes[2].set_ylabel(f"PSNR vs truth − {ref['config']}'s (dB)")
    for ax in axes:
        ax.set_xlabel("order / rank")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7)
    axes[0].set_yscale("log")
    fig.suptitle(f"compression knob: {report['size']}² frames, {len(report['frames'])} "
                 f"{'warm ' if report.get('warm') else ''}frames, "
                 f"load {report['load'][0]:.1f} (dotted: the issue's targets)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


@click.command("bench-worker")
@click.argument("job", type=click.Path(exists=True, dir_okay=False))
@click.argument("config")
def worker_cmd(job, config):
    """Render the frames of a bench JOB (job.json) with one CONFIG: the worker process of ``mifacerf bench``
    (``python -m mifacerf.evaluation.bench JOB CONFIG``)."""
    worker(job, config)


if __name__ == "__main__":
    worker_cmd()
