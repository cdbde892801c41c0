"""Smoke test of the blending benchmark at a toy size (not timed)."""
from mifacerf.blending import benchmark


def test_benchmark_runs_and_agrees():
    out = benchmark.run(n_vertices=48, n_sources=10, n_frames=30, quiet=True)
    assert out["vertices"] == 48 and out["frames"] == 30
    assert out["max_dense_diff_float64"] < 1e-7
    assert out["ghost_simplices"] > 0            # the walk meets ghost slivers here (a case that once failed)
    assert out["ratio_float64"] > 0 and out["reference_s"] > 0


def test_cli(tmp_path):
    import json

    from click.testing import CliRunner

    from mifacerf.cli import main

    r = CliRunner().invoke(main, ["evaluate", "blending-speed", "--vertices", "48", "--sources", "10",
                                  "--frames", "30", "--json", str(tmp_path / "b.json")])
    assert r.exit_code == 0, r.output
    assert json.loads((tmp_path / "b.json").read_text())["frames"] == 30
