"""A smoke test of ``mifacerf bench`` itself on the tiny preset (issue 19 item 5): every row runs and lands in
results.json, table.md and the plot; the timed-only rows (resolution sweep, cold start, sequence) carry no PSNR;
the sequence compiles no kernel after its first frame. Times are not asserted (benchmarks, not timed tests)."""
import json

import numpy as np
import pytest

EXPRESSIONS = ["neutral", "viseme_aa"]


@pytest.fixture(scope="module")
def bench_root(tmp_path_factory):
    from helpers.tiny_model import build_tiny_model
    from mifacerf.rendering.compression import compress_model
    from mifacerf.rendering.model import Model

    root = build_tiny_model(tmp_path_factory.mktemp("bench"), EXPRESSIONS)
    compress_model(Model(root / "model"), 2, progress=False, method="sh")
    compress_model(Model(root / "model"), 4, progress=False, method="pca")
    return root


@pytest.mark.slow
def test_bench_runs_every_row_on_the_tiny_preset(bench_root):
    from click.testing import CliRunner

    from mifacerf.evaluation.bench import configs, run

    out = bench_root / "bench"
    report = run(bench_root / "model", bench_root / "synth", out, n_frames=1, size=32, spp_truth=4,
                 progress=False, sequence_frames=3, sweep=(48,))
    rows = {r["config"]: r for r in report["results"]}
    meta = json.loads((bench_root / "model" / "model.json").read_text())
    assert list(rows) == configs(meta, sweep=(48,))
    assert {"dense", "exact", "sh2", "pca4", "exact@128", "lights/2", "size/48", "cold", "sequence"} <= set(rows)
    for name, r in rows.items():
        assert r["seconds_per_frame"] > 0 and np.isfinite(r["seconds_per_frame"]), name
        assert r["median_seconds"] > 0, name
    for name in ("size/48", "cold", "sequence"):
        assert rows[name]["psnr_truth"] is None and rows[name]["psnr_exact"] is None
        assert not list((out / name.replace("/", "_")).glob("frame*.npy"))
    for name in ("exact", "sh2", "pca4", "dense"):
        assert np.isfinite(rows[name]["psnr_truth"]), name
    assert rows["sequence"]["compiled_after_first"] == 0
    assert len(json.loads((out / "sequence" / "timing.json").read_text())["seconds"]) == 3
    table = (out / "table.md").read_text()
    assert "cold start" in table and "sequence (" in table and "exact at 48² (time only)" in table and "| sh2 |" in table
    assert (out / "runtime_vs_error.png").stat().st_size > 0
    assert json.loads((out / "results.json").read_text())["results"][0]["config"] == "dense"
    # the command line runs the same benchmark (quick: dense, exact, the first compressed, cold, sequence)
    from mifacerf.cli import main

    r = CliRunner().invoke(main, ["bench", str(bench_root / "model"), "--synth", str(bench_root / "synth"),
                                  "-o", str(bench_root / "quick"), "--frames", "1", "--size", "32",
                                  "--spp-truth", "2", "--quick"])
    assert r.exit_code == 0, r.output
    assert "| exact |" in r.output and "cold start" in r.output
