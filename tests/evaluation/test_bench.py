"""A smoke test of ``mifacerf bench`` itself on the tiny preset (issue 19 item 5): every row runs and lands in
results.json, table.md and the plot; the timed-only rows (resolution sweep, cold start, sequence) carry no PSNR;
the sequence compiles no kernel after its first frame. Times are not asserted (benchmarks, not timed tests:
the measurements are benchmarks/speed.py's and ``mifacerf bench``'s own runs).

Kept small for 2 cores: the tiny subject through three 48 px cameras and a 4 x 3 light arm, a model built from
the synthetic truth's registration (registration is tested apart), 24² frames, one frame per row, the rows in
this process (``run(processes=False)``; the cold start still starts its own), and the command line once with
``--quick`` (its rows in worker processes)."""
import json

import numpy as np
import pytest

EXPRESSIONS = ["neutral", "viseme_aa"]


@pytest.fixture(scope="module")
def bench_root(tmp_path_factory):
    from helpers.tracking import world_cameras, write_truth_registration
    from mifacerf.rendering.build import build_model
    from mifacerf.rendering.compression import compress_model
    from mifacerf.rendering.model import Model
    from mifacerf.rig import LightStage, Rig
    from mifacerf.synthetic.synth import synthesize

    root = tmp_path_factory.mktemp("bench")
    rig = Rig(LightStage.semicircular_arm(4, 3, irradiance_spread=0.05, seed=7), world_cameras(48))
    synthesize(root / "synth", preset="tiny", expressions=EXPRESSIONS, progress=False, rig=rig)
    reg = write_truth_registration(root / "synth")
    build_model(root / "synth" / "capture", root / "model", registration=reg)
    compress_model(Model(root / "model"), 2, progress=False, method="sh")
    return root


@pytest.mark.slow
def test_bench_runs_every_row_on_the_tiny_preset(bench_root):
    from mifacerf.evaluation.bench import configs, run

    out = bench_root / "bench"
    sweep = (32,)
    report = run(bench_root / "model", bench_root / "synth", out, n_frames=1, size=24, spp_truth=2,
                 progress=False, sequence_frames=3, sweep=sweep, processes=False)
    rows = {r["config"]: r for r in report["results"]}
    meta = json.loads((bench_root / "model" / "model.json").read_text())
    assert list(rows) == configs(meta, sweep=sweep)
    assert {"dense", "exact", "sh2", "exact@128", "lights/2", "size/32", "cold", "sequence"} <= set(rows)
    for name, r in rows.items():
        assert r["seconds_per_frame"] > 0 and np.isfinite(r["seconds_per_frame"]), name
        assert r["median_seconds"] > 0, name
    for name in ("size/32", "cold", "sequence"):
        assert rows[name]["psnr_truth"] is None and rows[name]["psnr_exact"] is None
        assert not list((out / name.replace("/", "_")).glob("frame*.npy"))
    for name in ("exact", "sh2", "dense", "lights/2", "exact@128"):
        assert np.isfinite(rows[name]["psnr_truth"]), name
    assert rows["sequence"]["compiled_after_first"] == 0
    assert len(json.loads((out / "sequence" / "timing.json").read_text())["seconds"]) == 3
    table = (out / "table.md").read_text()
    assert "cold start" in table and "sequence (" in table and "exact at 32² (time only)" in table and "| sh2 |" in table
    assert (out / "runtime_vs_error.png").stat().st_size > 0
    assert json.loads((out / "results.json").read_text())["results"][0]["config"] == "dense"
    with pytest.raises(ValueError, match="unknown bench configuration"):
        run(bench_root / "model", bench_root / "synth", bench_root / "none", n_frames=1, size=24, spp_truth=1,
            progress=False, only=["pca99"], processes=False)


@pytest.mark.slow
def test_the_command_line_runs_the_quick_benchmark(bench_root):
    """``mifacerf bench --quick``: dense, exact, the first compressed, cold, a 12-frame sequence, each in its
    own worker process."""
    from click.testing import CliRunner

    from mifacerf.cli import main

    out = bench_root / "quick"
    r = CliRunner().invoke(main, ["bench", str(bench_root / "model"), "--synth", str(bench_root / "synth"),
                                  "-o", str(out), "--frames", "1", "--size", "24", "--spp-truth", "1", "--quick"])
    assert r.exit_code == 0, r.output
    assert "| exact |" in r.output and "| sh2 |" in r.output and "cold start" in r.output
    rows = [x["config"] for x in json.loads((out / "results.json").read_text())["results"]]
    assert rows == ["dense", "exact", "sh2", "cold", "sequence"]
    assert len(json.loads((out / "sequence" / "timing.json").read_text())["seconds"]) == 12
