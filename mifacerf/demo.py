"""``mifacerf demo``: the main job, end to end, on the embedded synthetic subject.

Stages (each timed; a stage is skipped when the content digests of its inputs and outputs match
what ``OUT/steps.json`` recorded when it ran — :mod:`mifacerf.steps` — so a second run with nothing
changed runs nothing, rewrites nothing and takes seconds):

1. **capture** — the simulated light stage photographs the synthetic subject (``OUT/capture``,
   ground truth in ``OUT/truth``), with its contact sheet;
2. **register** — registration from the capture alone (``OUT/capture/registration``);
3. **model** — the relightable morphable model (``OUT/model``) and its PCA-compressed fields;
4. **renders** — blends of captured expressions under three environments, from a capture
   camera and from novel viewpoints, composited into the environment plates
   (``OUT/renders``: EXR + PNG and ``index.json``, written as one transaction; ``renders.png``, a
   contact grid);
5. **performance** — a tracked multi-view performance driving the model, composited into a
   plate (``OUT/performance_render``: frames, video);
6. **metrics** — PSNR against path-traced ground truth per case and time per stage
   (``OUT/metrics.json``), and the run-time-against-error benchmark (``OUT/bench``).
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import click
import numpy as np

from .formats.files import FolderLock, OutputFolder, atomic_write_bytes
from .steps import Steps

ENVIRONMENTS = ("sky", "interior", "gradient")


class Stages:
    """Times stages and prints a summary table at the end."""

    def __init__(self):
        self.rows = []

    def run(self, name: str, fn, *args, **kwargs):
        click.secho(f"==> {name}", bold=True)
        t0 = time.perf_counter()
        result = fn(*args, **kwargs)
        self.rows.append((name, time.perf_counter() - t0))
        return result

    def table(self) -> str:
        width = max(len(n) for n, _ in self.rows)
        lines = [f"{'stage'.ljust(width)}  seconds", "-" * (width + 10)]
        lines += [f"{n.ljust(width)}  {s:8.1f}" for n, s in self.rows]
        lines.append(f"{'total'.ljust(width)}  {sum(s for _, s in self.rows):8.1f}")
        return "\n".join(lines)


def write_json_text(path: Path, text: str) -> None:
    atomic_write_bytes(path, text.encode())


def stage_capture(out: Path, preset: str) -> Path:
    from .contact_sheet import contact_sheet
    from .synthetic.synth import synthesize

    cap = out / "capture"
    if (cap / "manifest.json").exists():
        click.echo(f"   cached: {cap}")
    else:
        synthesize(out, preset)
    if not (out / "contact_sheet.png").exists():
        contact_sheet(cap, out / "contact_sheet.png")
    return cap


def stage_register(cap: Path) -> Path:
    from .registration.register import register_capture

    return register_capture(cap)


def stage_model(cap: Path, reg: Path, out: Path, ranks=(8,), method: str | None = None) -> Path:
    from .rendering.build import build_model
    from .rendering.compression import DEFAULT_COMPRESS_METHOD, compress_model
    from .rendering.model import Model

    model = out / "model"
    build_model(cap, model, reg, overwrite=True)    # (the job's step record decides whether this runs)
    m = Model(model)
    method = method or DEFAULT_COMPRESS_METHOD   # a COMPRESSION_METHODS name that compresses
    for k in ranks:
        if k not in m.meta.get("compressed", {}).get(method, []):
            compress_model(m, k, method=method)
    return model


def stage_renders(model: Path, out: Path) -> dict:
    """The grid: 3 blends × 3 environments × (a capture camera, two novel views)."""
    from tqdm.auto import tqdm

    import mifacerf as mf

    from .imageio import write_exr, write_png
    from .pictures import grid, label, tile8
    from .rendering.renderer import RenderStats

    face = mf.load_model(model)
    names = face.expressions
    pick = lambda *cands: next((c for c in cands if c in names), names[min(1, len(names) - 1)])  # noqa: E731
    blends = [{pick("smile"): 0.6, pick("neutral"): 0.4},
              {pick("surprise", "eyes_wide_open"): 0.5, pick("viseme_aa", "mouth_open_wide"): 0.5},
              {pick("anger", "frown", "disgust"): 0.7, pick("viseme_oo", "viseme_pbm"): 0.3}]
    views = [None, (20.0, 3.0), (-25.0, -4.0)]
    tiles, times, index = [], [], []
    jobs = [(b, e, v) for b in range(len(blends)) for e in ENVIRONMENTS for v in views]
    # OUT/renders is one transaction: written beside, swapped in with its index.json once every render is in
    with OutputFolder(out / "renders", "index.json", what="renders",      # (earlier demos wrote no index)
                      legacy=lambda name: name.startswith("blend") and name.endswith((".exr", ".png"))) as output:
        rdir = output.root
        for b, env, view in tqdm(jobs, desc="renders"):
            cam = face.camera(view, size=256)
            st = RenderStats()
            t0 = time.perf_counter()
            rgba = face.render(blends[b], camera=cam, env=env, spp=4, stats=st)
            times.append({"seconds": time.perf_counter() - t0, "stages": st.times})
            comp = mf.composite(rgba, mf.environment_plate(env, cam))
            tag = f"blend{b}_{env}_{'capture' if view is None else f'yaw{view[0]:+.0f}'}"
            write_exr(rdir / f"{tag}.exr", rgba)
            write_png(rdir / f"{tag}.png", comp)
            index.append({"render": tag, "blend": blends[b], "environment": env, "view": view,
                          "warnings": st.warnings})
            desc = "+".join(f"{w:.1f} {n}" for n, w in blends[b].items())
            tiles.append(label(tile8(comp, size=192), f"{desc[:30]} | {env}"))
        write_json_text(rdir / "index.json", json.dumps({"format": "mifacerf.demo_renders", "version": 1,
                                                        "renders": index}, indent=1))
        output.finish()
    write_png(out / "renders.png", grid(tiles, len(views) * len(ENVIRONMENTS)))
    warm = times[1:] or times
    return {"frames": len(times), "seconds_per_frame": float(np.mean([t["seconds"] for t in warm])),
            "blends": blends}


def stage_performance(out: Path, model: Path, **options) -> dict:
    """Record (once), track, drive (:func:`mifacerf.tracking.demo.run_performance`; ``options`` are its
    keywords), and compare the track with the truth (dot error, dots tracked throughout)."""
    from .evaluation.tracking import evaluate_track
    from .tracking.demo import run_performance

    m = run_performance(out, model, **options)
    ev = evaluate_track(m.pop("track"), out)
    head = {k: m.pop(k) for k in ("frames", "fps")}
    return {**head, "dot_error_px": ev["dot_error"], "dots_tracked_whole_sequence": ev["dots_tracked_whole_sequence"],
            "dot_frames_tracked_of_seen": ev["dot_frames_tracked_of_seen"], **m}


def stage_metrics(out: Path, model: Path, fast: bool) -> dict:
    """A quick check within the demo's time budget (one case per kind, 256 truth samples per pixel; the
    README's numbers come from ``mifacerf evaluate render`` and ``mifacerf bench`` with more cases and samples)."""
    from .evaluation.bench import run as bench
    from .evaluation.render_cases import evaluate

    report = evaluate(out, model, envs=ENVIRONMENTS, n=1, seed=int(time.time()), spp_truth=64 if fast else 256,
                      pictures=out / "metrics_cases.png")
    b = bench(model, out, out / "bench", n_frames=1, size=128, spp_truth=64 if fast else 256, quick=True)
    return {"cases": report, "bench": b}


@click.command("demo")
@click.option("-o", "--out", default="mifacerf-demo", show_default=True, type=click.Path(file_okay=False),
              help="Output folder; its capture, registration and model are reused by later runs.")
@click.option("--preset", default="draft", show_default=True, type=click.Choice(["tiny", "draft", "paper"]))
@click.option("--fast", is_flag=True, help="Even fewer ground-truth samples in the metrics (noisier, quicker).")
def demo_cmd(out, preset, fast):
    """Run the main job on the embedded synthetic subject: capture, registration, model, renders,
    performance, metrics."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    # one demo at a time per OUT (its lock, .OUT.lock beside it, deleted when the run ends): a second one
    # is refused at once (exit 3) instead of both rewriting OUT/steps.json (a lost step record)
    with FolderLock(out, ValueError, wait=False, what="demo on this folder (mifacerf demo -o)", ephemeral=True):
        _demo(out, preset, fast)


def _demo(out: Path, preset: str, fast: bool) -> None:
    st = Stages()
    steps = Steps(out, log=click.echo)
    metrics = {"preset": preset}
    cap, reg, model = out / "capture", out / "capture" / "registration", out / "model"
    # each step is skipped when the digests of its inputs and outputs match OUT/steps.json (mifacerf.steps)
    st.run("capture (simulated light stage)", steps.run, "capture", [{"preset": preset}],
           [cap, out / "contact_sheet.png"], lambda: stage_capture(out, preset) and None)
    st.run("registration", steps.run, "register", [cap, cap / "hand"], [reg], lambda: stage_register(cap) and None)
    st.run("model build + compression", steps.run, "model", [cap, reg, {"ranks": [8]}], [model],
           lambda: stage_model(cap, reg, out) and None)
    metrics["renders"] = st.run("renders (blends x environments x views)", steps.run, "renders", [model],
                                [out / "renders", out / "renders.png"], stage_renders, model, out)
    metrics["performance"] = st.run("performance (track + drive)", steps.run, "performance", [model],
                                    [out / "performance_render"], stage_performance, out, model)
    m = st.run("metrics (ground truth, benchmark)", steps.run, "metrics", [model, {"fast": fast}],
               [out / "metrics_cases.png", out / "bench"], stage_metrics, out, model, fast)
    metrics["cases"] = m["cases"]["summary"]
    metrics["truth_noise_psnr"] = m["cases"]["truth_noise_psnr"]
    metrics["bench"] = m["bench"]["results"]
    # the time each stage's outputs took to make (a skipped stage: the run that made them)
    names = dict(zip(["capture", "register", "model", "renders", "performance", "metrics"], [n for n, _ in st.rows]))
    metrics["stages_seconds"] = {names[k]: steps.seconds(k) for k in names}
    text = json.dumps(metrics, indent=1, default=float)
    mpath = out / "metrics.json"
    if not (mpath.exists() and mpath.read_text() == text):     # nothing changed: not rewritten
        write_json_text(mpath, text)
    if steps.skipped:
        click.echo(f"skipped (inputs and outputs unchanged): {', '.join(steps.skipped)}")
    click.echo("")
    click.echo(st.table())
    click.echo("")
    for k, v in metrics["cases"].items():
        click.echo(f"case {k}: PSNR {v['psnr'].get('mean', float('nan')):.2f} dB against ground truth, "
                   f"{v['seconds'].get('mean', float('nan')):.2f} s per frame")
    click.echo(f"outputs in {out}/: contact_sheet.png renders.png renders/ metrics.json metrics_cases.png "
               "bench/runtime_vs_error.png performance_render/")
