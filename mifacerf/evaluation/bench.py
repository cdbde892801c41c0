"""``mifacerf bench``: run time per frame against error, for every way of rendering the model.

Configurations (all in one run; times are ratios to the dense reference):

* ``dense``   — the straightforward NumPy reference: every light of every field (:mod:`.dense_reference`);
* ``exact``   — the Dr.Jit exact path (render chunks, lit textures; :mod:`mifacerf.rendering.renderer`);
* ``pca<K>``  — the compressed path with K coefficients per texel (:mod:`mifacerf.rendering.compression`;
  ``<method><K>`` for every compressed method the model holds, by its name in ``COMPRESSION_METHODS``);
* ``exact@<size>`` — the exact path at another image size;
* ``lights/<n>``   — the exact path with a subset of the light stage (every n-th arm position and strobe).

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


def configs(model_meta: dict, quick: bool = False) -> list[str]:
    compressed = [f"{method}{k}" for method, ranks in model_meta.get("compressed", {}).items() for k in ranks]
    out = ["dense", "exact"] + compressed + ["exact@128", "lights/2"]
    return out if not quick else ["dense", "exact"] + compressed[:1]


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


def worker(job_path: str, config: str) -> None:
    """Render the job's frames with one configuration; write renders and timings next to the job."""
    from ..rendering.api import load_model
    from ..rendering.renderer import Renderer, RenderStats
    from .dense_reference import dense_render

    job = json.loads(Path(job_path).read_text())
    out = Path(job["out"]) / config.replace("/", "_")
    out.mkdir(parents=True, exist_ok=True)
    face = load_model(job["model"])
    size = job["size"]
    if config.startswith("exact@"):
        size = int(config.split("@")[1])
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
    times, stages = [], []
    for i, fr in enumerate([job["frames"][0]] + job["frames"]):
        cam = face.camera((fr["yaw"], fr["pitch"]), size=size)
        target, W = face.target(fr["expression"])
        st = RenderStats()
        t0 = time.perf_counter()
        if config == "dense":
            img = dense_render(face.renderer, target, W, cam, env, spp=job["spp"])
        else:
            img = face.renderer.render(target, W, cam, env, spp=job["spp"], stats=st)
        dt = time.perf_counter() - t0
        if i > 0:  # frame 0 is the warm-up
            times.append(dt)
            stages.append(st.times)
            np.save(out / f"frame{i - 1}.npy", img)
    (out / "timing.json").write_text(json.dumps({"seconds": times, "stages": stages, "peak_bytes": vm_hwm()}))


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


def run(model, synth_out, out, n_frames: int = 3, size: int = 256, env: str = "sky", spp: int = 1,
        spp_truth: int = 1024, seed: int = 7, quick: bool = False, progress: bool = True) -> dict:
    """Run the benchmark (``progress``: bars over the truths and the configurations); returns the results
    (also written to ``out``)."""
    from ..progress import bar
    from ..rendering.api import load_model
    from ..synthetic.truth_scene import TruthRenderer
    from .masks import classify_pixels, face_mask
    from .metrics import psnr

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    face = load_model(model)
    fr = frames(face.model, n_frames, seed, size)
    tr = TruthRenderer.from_synth(synth_out)
    truths, masks = [], []
    for i, f in enumerate(bar(fr, progress, desc="ground truth")):
        cam = face.camera((f["yaw"], f["pitch"]), size=size)
        t = tr.render(tr.blend(f["expression"]), cam, env, spp=spp_truth, seed=100 + i)
        truths.append(t)
        masks.append(face_mask(classify_pixels(tr.scene(face.environment(env)), cam)) & (t[..., 3] > 0.999))
    n_str = int(json.loads((Path(synth_out) / "capture" / "manifest.json").read_text())["rig"]["lights"]
                ["layout"]["n_strobes"])
    job = {"model": str(Path(model).resolve()), "frames": fr, "size": size, "env": env, "spp": spp,
           "out": str(out.resolve()), "n_strobes": n_str}
    job_path = out / "job.json"
    job_path.write_text(json.dumps(job))
    cfgs = configs(face.model.meta, quick)
    results = []
    for cfg in bar(cfgs, progress, desc="configurations"):
        subprocess.run([sys.executable, "-m", "mifacerf.evaluation.bench", str(job_path), cfg], check=True,
                       env={**os.environ})
        d = out / cfg.replace("/", "_")
        timing = json.loads((d / "timing.json").read_text())
        results.append({"config": cfg, "seconds_per_frame": float(np.mean(timing["seconds"])),
                        "peak_bytes": timing["peak_bytes"], "disk_bytes": disk_bytes(Path(model), cfg),
                        "stages": {k: float(np.mean([s.get(k, 0) for s in timing["stages"]]))
                                   for k in sorted({k for s in timing["stages"] for k in s})}})
    exact = {i: np.load(out / "exact" / f"frame{i}.npy") for i in range(n_frames)}
    for r in results:
        d = out / r["config"].replace("/", "_")
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


def write_table(report: dict, path: Path) -> None:
    rows = ["| configuration | s / frame | × dense | × exact | PSNR vs truth (dB) | PSNR vs exact (dB) | "
            "peak memory (MB) | data on disk (MB) | × smaller than exact |",
            "|---|---|---|---|---|---|---|---|---|"]
    for r in report["results"]:
        pe = "—" if r["psnr_exact"] is None else (f"{r['psnr_exact']:.1f}" if np.isfinite(r["psnr_exact"]) else "∞")
        rows.append(f"| {r['config']} | {r['seconds_per_frame']:.3f} | {r['speedup_vs_dense']:.1f} | "
                    f"{r['speedup_vs_exact']:.2f} | {r['psnr_truth']:.2f} | {pe} | {r['peak_bytes'] / 1e6:.0f} | "
                    f"{r['disk_bytes'] / 1e6:.1f} | {r['size_vs_exact']:.1f} |")
    path.write_text("\n".join(rows) + "\n")


def plot(report: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.2), dpi=120)
    for r in report["results"]:
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


@click.command("bench-worker")
@click.argument("job", type=click.Path(exists=True, dir_okay=False))
@click.argument("config")
def worker_cmd(job, config):
    """Render the frames of a bench JOB (job.json) with one CONFIG: the worker process of ``mifacerf bench``
    (``python -m mifacerf.evaluation.bench JOB CONFIG``)."""
    worker(job, config)


if __name__ == "__main__":
    worker_cmd()
