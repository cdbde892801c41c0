"""Driving the model with the track: weights, relit renders, composites, video, coherence; and its PSNR
against the path-traced truth (mifacerf.evaluation.drive, an observer of the drive)."""
import json

import numpy as np
import pytest

FRAMES = (10, 22)   # the face starts moving at frame 12
N = FRAMES[1] - FRAMES[0]


@pytest.fixture(scope="module")
def driven(world, tmp_path_factory):
    from mifacerf.evaluation.drive import evaluate_drive

    out = tmp_path_factory.mktemp("drive")
    evaluate_drive(world["track"], world["model"], world["out"], out, truth_spp=32, envs=("sky", "interior"),
                   size=64, spp=2, frames=FRAMES, progress=False)
    return out


@pytest.mark.slow
def test_outputs(driven, world):
    import imageio.v2 as iio

    meta = json.loads((driven / "drive.json").read_text())
    assert meta["n_frames"] == N and set(meta["environments"]) == {"sky", "interior"}
    W = np.load(driven / "weights.npz")["weights"].astype(np.float64)
    T = world["track"].vertices.shape[1]
    assert W.shape[:2] == (N, T) and np.allclose(W.sum(-1), 1.0, atol=5e-3) and (W >= -1e-3).all()
    for env in ("sky", "interior"):
        frames = sorted((driven / env / "frames").glob("F*.png"))
        assert len(frames) == N and len(list((driven / env / "frames").glob("F*.exr"))) == N
        assert frames[0].name == "F00010.png"
        reader = iio.get_reader(str(driven / env / "performance.mp4"))
        video = [f for f in reader]
        reader.close()
        assert len(video) == N and video[0].shape[:2] == (64, 64)
        e = meta["environments"][env]
        assert e["render_seconds_per_frame"] > 0 and len(e["psnr_db"]) == N
        assert e["truth_noise_psnr_db"] > e["psnr_summary"]["mean"]   # the truth's noise is not what limits it
    assert (driven / "strip.png").exists() and meta["strip_frames"][0] == FRAMES[0]


@pytest.mark.slow
def test_psnr_and_coherence_against_truth(driven, world, tmp_path):
    meta = json.loads((driven / "drive.json").read_text())
    for env in ("sky", "interior"):
        e = meta["environments"][env]
        assert e["psnr_summary"]["min"] > 18.0, e["psnr_summary"]   # 3 expressions, 24 lights, 64 px
        # no scintillation: frame-to-frame change of the render within a small factor of the truth's
        r, t = e["pixel_coherence"], e["truth_pixel_coherence"]
        # (a second difference of 0.2 % is below what 8-bit video shows)
        assert r["flicker"]["mean"] < 3.0 * t["flicker"]["mean"] + 2e-3, (r, t)
    # the rendered weights change smoothly (motion), not back and forth (scintillation)
    w, wt = meta["weights"]["coherence"], meta["weights"]["truth_coherence"]
    assert w["flicker_to_change"] < 1.0, (w, wt)
    assert w["change"]["mean"] < 10.0 * wt["change"]["mean"] + 0.02, (w, wt)


@pytest.mark.slow
def test_a_wrong_track_scores_worse(driven, world, tmp_path):
    """The measurement can fail: the same frames driven by a mesh 8 mm off score lower."""
    import shutil

    from mifacerf.evaluation.drive import evaluate_drive
    from mifacerf.tracking.track import Track

    bad = tmp_path / "badtrack"
    shutil.copytree(world["track"].root, bad)
    z = dict(np.load(bad / "track.npz"))
    z["vertices"] = z["vertices"] + np.array([0.008, 0.0, 0.0])
    np.savez(bad / "track.npz", **z)
    out = evaluate_drive(Track(bad), world["model"], world["out"], tmp_path / "d", truth_spp=32, envs=("sky",),
                         size=64, spp=2, frames=(10, 12), progress=False, exr=False, video=False)
    good = json.loads((driven / "drive.json").read_text())["environments"]["sky"]["psnr_db"][:2]
    worse = json.loads((out / "drive.json").read_text())["environments"]["sky"]["psnr_db"]
    assert np.mean(worse) < np.mean(good) - 1.0, (worse, good)


def test_coherence_measures_detect_flicker():
    from mifacerf.tracking.coherence import PixelCoherence, weight_summary

    rng = np.random.default_rng(0)
    t = np.linspace(0, 1, 30)
    smooth = np.stack([np.stack([1 - x, x], -1) * np.ones((5, 1)) for x in t])            # (N, T, S)
    noisy = smooth.copy()
    noisy[::2] = noisy[::2][..., ::-1] * 0.2 + noisy[::2] * 0.8                            # popping weights
    assert weight_summary(smooth)["flicker_to_change"] < 0.1
    assert weight_summary(noisy)["flicker_to_change"] > 1.0
    pc, pn = PixelCoherence(), PixelCoherence()
    for k, x in enumerate(t):
        img = np.ones((8, 8, 4)) * np.array([0.5 + 0.2 * x, 0.5, 0.5, 1.0])
        pc.add(img)
        pn.add(img + np.concatenate([0.02 * rng.standard_normal((8, 8, 3)), np.zeros((8, 8, 1))], -1))
    assert pn.summary()["flicker"]["mean"] > 10 * pc.summary()["flicker"]["mean"]


@pytest.mark.slow
def test_drive_cli(world, tmp_path):
    """``mifacerf drive`` renders without reading the truth; ``mifacerf evaluate drive`` adds the comparison."""
    from click.testing import CliRunner
    from openwatch import watch_opens

    from mifacerf.cli import main

    with watch_opens(world["out"] / "truth") as opened:
        r = CliRunner().invoke(main, ["drive", str(world["track"].root), "--model", str(world["model"]), "-o",
                                      str(tmp_path / "d"), "--env", "gradient", "--frames", "3", "--size", "48",
                                      "--spp", "1", "--no-exr"])
    assert r.exit_code == 0, r.output
    assert opened == [], "drive opened ground-truth files"
    assert len(list((tmp_path / "d" / "gradient" / "frames").glob("*.png"))) == 3
    assert (tmp_path / "d" / "gradient" / "performance.mp4").exists()
    meta = json.loads((tmp_path / "d" / "drive.json").read_text())
    assert "psnr_db" not in meta["environments"]["gradient"] and not (tmp_path / "d" / "gradient" / "truth").exists()
    r = CliRunner().invoke(main, ["evaluate", "drive", str(world["out"]), str(world["track"].root), "--model",
                                  str(world["model"]), "-o", str(tmp_path / "e"), "--env", "gradient", "--frames",
                                  "1", "--size", "32", "--spp", "1", "--truth-spp", "4", "--no-exr"])
    assert r.exit_code == 0, r.output
    meta = json.loads((tmp_path / "e" / "drive.json").read_text())
    assert len(meta["environments"]["gradient"]["psnr_db"]) == 1 and "PSNR mean" in r.output
    r = CliRunner().invoke(main, ["drive", str(world["track"].root), "--model", str(world["model"]), "--env",
                                  "no-such-env", "--frames", "1"])
    assert r.exit_code != 0
    r = CliRunner().invoke(main, ["drive", str(world["track"].root), "--model", str(world["model"]), "-o",
                                  str(tmp_path / "c"), "--frames", "1", "--method", "sh", "--rank", "9",
                                  "--workers", "1"])
    assert r.exit_code == 1 and "mifacerf compress" in r.output and "Traceback" not in r.output
    assert len(r.output.strip().splitlines()) == 1, r.output


@pytest.mark.slow
def test_demo_performance_stage(world, tmp_path):
    """``mifacerf demo``'s performance stage: reuses the recorded performance, tracks, drives, compares the
    track with the truth, returns its metrics."""
    import shutil

    from mifacerf.demo import stage_performance

    out = tmp_path / "demo"
    for name in ("capture", "truth", "performance"):
        shutil.copytree(world["out"] / name, out / name, ignore=shutil.ignore_patterns("track", "images", "cache"))
    m = stage_performance(out, world["model"], env="gradient")
    assert m["frames"] == 24 and m["dot_error_px"]["median"] < 0.5
    assert m["tracking_seconds_per_frame"] > 0 and m["render_seconds_per_frame"] > 0
    assert (out / "performance_render" / "gradient" / "performance.mp4").exists()
    json.dumps(m)
