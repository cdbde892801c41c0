"""Measurements of the capture side (docs/hardware.md): ``python -m mifacerf.capture.benchmark …``.

* ``session``: a simulated session of N expressions with injected faults and hard kills of
  the process (``--kills``), resumed until complete; reports takes, retakes, runs,
  resumes and that every image verifies by checksum.
* ``motion``: how far the subject must move during a take for the motion check to catch it.
* ``geometry`` / ``response``: calibration errors against the rendered truth.

Each prints one JSON object. These are measurements, not tests (minutes, not seconds).
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import click
import numpy as np

CLI = "import sys; from mifacerf.cli import main; sys.exit(main())"


@click.group()
def main():
    """Capture-side measurements."""


@main.command()
@click.option("--expressions", type=int, default=60, show_default=True)
@click.option("--preset", default="tiny", show_default=True)
@click.option("--resolution", type=int, default=64, show_default=True)
@click.option("--renderer", default="procedural", show_default=True)
@click.option("--fault-rate", type=float, default=0.02, show_default=True)
@click.option("--frame-drop", type=float, default=0.002, show_default=True)
@click.option("--motion-rate", type=float, default=0.1, show_default=True)
@click.option("--kills", type=int, default=3, show_default=True, help="Hard kills at random frames.")
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--out", type=click.Path(file_okay=False, path_type=Path))
def session(expressions, preset, resolution, renderer, fault_rate, frame_drop, motion_rate, kills, seed, out):
    """A simulated session with faults and kills, resumed to completion."""
    from mifacerf.capture.journal import read_journal
    from mifacerf.capture.session import summarize, verify_capture
    from mifacerf.rig import preset as get_preset

    out = out or Path(tempfile.mkdtemp(prefix="mifacerf-session-")) / "cap"
    p = get_preset(preset)
    total = expressions * p.n_cameras * p.n_positions * p.n_strobes
    rng = np.random.default_rng(seed)
    kill_at = sorted(rng.integers(total // 10, total, kills).tolist()) if kills else []
    base = ["capture", str(out), "--simulate", "--preset", preset, "--resolution", str(resolution),
            "--expressions", str(expressions), "--renderer", renderer, "--fault-rate", str(fault_rate),
            "--frame-drop", str(frame_drop), "--motion-rate", str(motion_rate), "--seed", str(seed),
            "--timeout", "0.1"]
    t0 = time.time()
    runs = []
    args = base
    done_frames = 0
    for k in kill_at + [None]:
        extra = [] if k is None else ["--crash-after-frames", str(max(1, k - done_frames))]
        r = subprocess.run([sys.executable, "-c", CLI, *args, *extra], capture_output=True, text=True)
        runs.append(r.returncode)
        if (out / "session.jsonl").exists():
            done_frames = sum(len(x["frames"]) for x in read_journal(out / "session.jsonl").records
                              if x["event"] in ("frames", "adopted"))
        args = ["capture", str(out), "--resume"]
        if r.returncode not in (0, 70):
            raise click.ClickException(f"capture failed ({r.returncode}): {r.stderr[-2000:]}")
    while runs[-1] != 0:  # not finished yet (should not happen): resume again
        r = subprocess.run([sys.executable, "-c", CLI, *args], capture_output=True, text=True)
        runs.append(r.returncode)
    wall = time.time() - t0
    rep = summarize(read_journal(out / "session.jsonl").records)
    ok, problems = verify_capture(out)
    click.echo(json.dumps({"command": " ".join(["mifacerf", *base]), "kills_at_frame": kill_at,
                           "process_exit_codes": runs, "wall_s": round(wall, 1), "images_expected": total,
                           "images_verified": ok, "problems": problems[:5], "report": rep.to_dict(),
                           "folder": str(out)}, indent=1))


@main.command()
@click.option("--renderer", default="procedural", show_default=True)
@click.option("--resolution", type=int, default=64, show_default=True)
@click.option("--trials", type=int, default=8, show_default=True)
@click.option("--drifts", default="0,1,2,3,4,6,8", show_default=True, help="Drift in mm over the take.")
def motion(renderer, resolution, trials, drifts):
    """Detection rate of the motion check against the drift of the subject during a take."""
    from mifacerf.capture.motion import MotionCheck, representative_lights
    from mifacerf.capture.simulation.cameras import SimulatedSubject, SyntheticCameras
    from mifacerf.capture.simulation.lab import expression_params, make_renderer
    from mifacerf.capture.simulation.device import Trigger
    from mifacerf.rig import preset

    rig = preset("tiny").rig()
    rig.cameras = [c.resized(resolution, resolution) for c in rig.cameras]
    r = make_renderer(renderer, rig)
    names = (["smile", "viseme_aa", "surprise", "head_turn_left"] if renderer == "synthetic"
             else ["a", "b", "c", "d"])
    params = {n: expression_params(r, n, i + 1) for i, n in enumerate(names)}
    L = len(rig.lights)
    mc = MotionCheck(sample=32)
    sample = representative_lights(rig.lights.n_positions, rig.lights.n_strobes, 32)
    rows = {}
    reference = None
    for d_mm in [float(x) for x in drifts.split(",")]:
        caught, ratios = 0, []
        for trial in range(trials):
            name = names[trial % len(names)]
            subj = SimulatedSubject(params, motion_rate=1.0 if d_mm else 0.0, motion_mm=d_mm, n_lights=L, seed=trial)
            cams = SyntheticCameras(rig, r, subj)
            subj.assume(name, 1)
            cams.start(L)
            for step in range(L):
                cams._on_trigger(Trigger(1, step + 1, step, step, 0xFF, step / 60))
            frames = cams.collect(timeout=0)
            by_cam = {c: np.stack([f.image for f in fl])[sample] for c, fl in frames.items()}
            scores = mc.scores(by_cam)
            if reference is None:
                ref_subj = SimulatedSubject(params, n_lights=L)
                ref_cams = SyntheticCameras(rig, r, ref_subj)
                ref_subj.assume(names[0], 1)
                ref_cams.start(L)
                for step in range(L):
                    ref_cams._on_trigger(Trigger(1, step + 1, step, step, 0xFF, step / 60))
                rf = ref_cams.collect(timeout=0)
                reference = mc.scores({c: np.stack([f.image for f in fl])[sample] for c, fl in rf.items()})
            v = mc.judge(scores, reference)
            caught += int(v.blurred)
            ratios.append(min(v.ratios.values()))
        rows[str(d_mm)] = {"detected": caught / trials, "min_ratio_median": float(np.median(ratios))}
    click.echo(json.dumps({"renderer": renderer, "resolution": resolution, "threshold": mc.threshold,
                           "pixel_mm": 1000 * rig.cameras[1].pixel_footprint(1.3), "by_drift_mm": rows}, indent=1))


@main.command()
@click.option("--preset", default="draft", show_default=True)
@click.option("--resolution", type=int, default=None)
@click.option("--views", type=int, default=20, show_default=True)
@click.option("--spp", type=int, default=4, show_default=True)
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--model", default="full", show_default=True)
def geometry(preset, resolution, views, spp, seed, model):
    """Render boards into the preset's cameras, calibrate, compare with the truth."""
    from mifacerf.capture.calibration.charuco import BoardSpec
    from mifacerf.capture.calibration.zhang2000 import calibrate_rig, detect_views, pose_errors, relative_pose_errors
    from mifacerf.capture.simulation.boards import read_board_dataset, write_board_dataset
    from mifacerf.rig import preset as get_preset

    rig = get_preset(preset).rig()
    if resolution:
        rig.cameras = [c.resized(resolution, resolution) for c in rig.cameras]
    board = BoardSpec(9, 7, 0.03, 0.022)
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.time()
        write_board_dataset(tmp, rig.cameras, board, n_views=views, spp=spp, seed=seed)
        t_render = time.time() - t0
        _, images, desc = read_board_dataset(tmp)
    t0 = time.time()
    det = detect_views(board, images)
    w = rig.cameras[0].width
    cal = calibrate_rig(board, det, {c.name: (c.width, c.height) for c in rig.cameras}, model=model,
                        principal_prior_px=0.01 * w, world_view=0,
                        world_pose=(np.asarray(desc["world_pose"]["R"]), np.asarray(desc["world_pose"]["t"])))
    t_cal = time.time() - t0
    errs = [pose_errors(cal.camera(c.name), c) for c in rig.cameras]
    rel = relative_pose_errors([cal.camera(c.name) for c in rig.cameras], rig.cameras)
    click.echo(json.dumps({
        "preset": preset, "resolution": w, "views": views, "board": board.to_dict(), "model": model,
        "render_s": round(t_render, 1), "calibrate_s": round(t_cal, 1), "rms_px": cal.rms,
        "views_detected": {c: len(d) for c, d in det.items()},
        "focal_error_pct": [round(100 * e["focal_rel"], 3) for e in errs],
        "principal_point_error_px": [round(e["principal_px"], 2) for e in errs],
        "rotation_error_deg": [round(e["rotation_deg"], 3) for e in errs],
        "centre_error_mm": [round(1000 * e["centre_m"], 1) for e in errs],
        "distortion_error_px": [round(e["distortion_px"], 2) for e in errs],
        "relative_rotation_error_deg": [round(r["rotation_deg"], 3) for r in rel],
        "relative_centre_error_mm": [round(1000 * r["centre_m"], 1) for r in rel]}, indent=1))


@main.command()
@click.option("--preset", default="tiny", show_default=True)
@click.option("--resolution", type=int, default=96, show_default=True)
@click.option("--seed", type=int, default=0, show_default=True)
def response(preset, resolution, seed):
    """Render charts through realistic sensors, calibrate both ways, compare with the truth."""
    from mifacerf.capture.calibration.debevec1997 import curve_error
    from mifacerf.capture.calibration.radiometric import RESPONSE_METHODS, calibrate_radiometry
    from mifacerf.capture.simulation.cameras import SensorModel
    from mifacerf.capture.simulation.charts import write_chart_dataset
    from mifacerf.rig import preset as get_preset

    rig = get_preset(preset).rig()
    rig.cameras = [c.resized(resolution, resolution) for c in rig.cameras]
    sensors = {c.name: SensorModel.realistic(seed=seed * 100 + i) for i, c in enumerate(rig.cameras)}
    out = {"preset": preset, "resolution": resolution, "sensor": "realistic (gamma 2.2 with toe, 10 bits, "
                                                                 "read noise 0.002, colour crosstalk)"}
    with tempfile.TemporaryDirectory() as tmp:
        write_chart_dataset(tmp, rig, sensors)
        for method in RESPONSE_METHODS:
            res = calibrate_radiometry(tmp, method=method)
            rows = {}
            for c, r in res.items():
                s = sensors[c]
                ce = curve_error(r.radiometry.response, s.inverse_response)
                rows[c] = {"response_rms_pct": round(100 * ce["rms"], 3), "response_max_pct": round(100 * ce["max"], 3),
                           "exposure": round(r.radiometry.exposure, 4), "true_exposure": s.exposure,
                           "delta_e2000_mean": round(float(r.delta_e.mean()), 3),
                           "delta_e2000_max": round(float(r.delta_e.max()), 3)}
            out[method] = rows
    click.echo(json.dumps(out, indent=1))


if __name__ == "__main__":
    os.environ.setdefault("PYTHONHASHSEED", "0")
    main()
