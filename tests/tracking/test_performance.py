"""The scripted performance and its recording."""
import json

import numpy as np
import pytest

from mifacerf.synthetic.expressions import CONTROLS, default_params
from mifacerf.synthetic.performance import LEAD_IN, blend_residual, script


def _col(sc, name):
    return sc.params[:, sc.control_names.index(name)]


def test_script_layers_ranges_and_rest_start():
    sc = script(3.0, 60.0, seed=4)
    assert sc.params.shape == (180, len(CONTROLS))
    lo = np.array([c.lo for c in CONTROLS])
    hi = np.array([c.hi for c in CONTROLS])
    assert np.all(sc.params >= lo - 1e-12) and np.all(sc.params <= hi + 1e-12)
    lead = int(LEAD_IN * 60)
    assert np.allclose(sc.params[:lead], default_params())                   # starts at rest
    # speech, emotions, head motion, blinks and saccades all happen
    assert len(sc.events["visemes"]) >= 8 and sc.events["emotions"] and sc.events["blinks"]
    assert _col(sc, "jaw_open").max() > 0.05 and np.ptp(_col(sc, "head_yaw")) > 0.05
    assert _col(sc, "blink_L").max() > 0.5 and np.ptp(_col(sc, "gaze_yaw")) > 0.1
    # smooth, speech-like timing: the mouth never jumps more than a fraction of its range per frame
    for name in ("jaw_open", "pucker", "lips_press", "smile_L", "head_yaw"):
        c = next(c for c in CONTROLS if c.name == name)
        assert np.abs(np.diff(_col(sc, name))).max() < 0.25 * (c.hi - c.lo), name
    # deterministic per seed, different across seeds
    assert np.array_equal(sc.params, script(3.0, 60.0, seed=4).params)
    assert not np.allclose(sc.params, script(3.0, 60.0, seed=5).params)


def test_script_is_not_a_blend_of_the_captured_expressions():
    from mifacerf.synthetic.presets import presets

    X = np.stack([e.params for e in presets("draft")])
    scale = np.array([c.hi - c.lo for c in CONTROLS])
    sc = script(3.0, 60.0, seed=0)
    moving = sc.times >= LEAD_IN + 0.2
    r = blend_residual(sc.params[moving], X, scale)
    assert np.mean(r > 0.1) > 0.5, np.percentile(r, [10, 50, 90])
    # the measure itself: convex blends of the presets are inside (residual ~ 0)
    rng = np.random.default_rng(0)
    w = rng.dirichlet(np.ones(len(X)) * 0.3, size=20)
    assert blend_residual(w @ X, X, scale).max() < 1e-3


def test_bad_lengths_are_refused():
    with pytest.raises(ValueError):
        script(0.0)


@pytest.mark.slow
def test_recorded_performance_folder_and_truth(world):
    from mifacerf.formats.performance import PerformanceFolder
    from mifacerf.synthetic.recording import read_truth

    perf = PerformanceFolder(world["perf"])
    assert perf.n_frames == 24 and perf.fps == 60.0 and len(perf.cameras) == 3
    assert perf.meta["lighting"]["type"] == "studio" and perf.meta["starts_at_rest"]
    for cam in perf.camera_names:
        files = sorted((perf.root / "frames" / cam).glob("F*.exr"))
        assert len(files) == perf.n_frames
    img = perf.read(perf.camera_names[1], 10)
    assert img.shape == (96, 96, 3) and np.isfinite(img).all() and img.max() > 0.1
    # sensor noise: two frames at rest differ, but only by noise
    a, b = perf.read("cam1", 2), perf.read("cam1", 3)
    assert not np.array_equal(a, b) and np.abs(a - b).mean() < 0.01
    truth = read_truth(world["out"])
    T = len(perf.template()["vertices"])
    assert truth["params"].shape == (24, len(CONTROLS))
    assert truth["template_vertices"].shape == (24, T, 3) and truth["eyes"].shape == (24, 2, 4, 4)
    # the synthetic user marked only the keyframes
    keys = perf.keyframes()
    marked = sorted(int(p.stem[1:]) for p in (perf.root / "hand" / "rotoscope").glob("F*.json"))
    assert marked == sorted(set(keys["lips"]) | set(keys["eyelids"]) | set(keys["irises"]))
    assert 2 <= len(marked) < perf.n_frames // 2
    d = json.loads((perf.root / "hand" / "rotoscope" / f"F{keys['lips'][0]:05d}.json").read_text())
    assert {"lip_upper", "lip_lower"} <= set(d["curves"]) and len(d["curves"]["lip_upper"]) >= 2


@pytest.mark.slow
def test_synth_cli_records_a_performance_next_to_an_existing_capture(world, tmp_path):
    import shutil

    from click.testing import CliRunner

    from mifacerf.cli import main

    out = tmp_path / "synth"
    shutil.copytree(world["out"] / "capture", out / "capture")
    shutil.copytree(world["out"] / "truth", out / "truth", ignore=shutil.ignore_patterns("performance"))
    r = CliRunner().invoke(main, ["synth", str(out), "--performance", "0.05", "--performance-size", "48"])
    assert r.exit_code == 0, r.output
    m = json.loads((out / "performance" / "manifest.json").read_text())
    assert m["n_frames"] == 3 and m["cameras"][0]["width"] == 48
    assert (out / "truth" / "performance" / "frames.npz").exists()
    assert "capture reused" in r.output
