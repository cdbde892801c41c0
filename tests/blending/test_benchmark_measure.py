"""Smoke tests of the benchmark and measurement scripts at toy sizes (not timed)."""
import numpy as np

from mifacerf.blending import benchmark, measure
from mifacerf.blending.toy import random_sources, toy_subject


def test_benchmark_runs_and_agrees():
    out = benchmark.run(n_vertices=48, n_sources=10, n_frames=30, quiet=True)
    assert out["vertices"] == 48 and out["frames"] == 30
    assert out["max_dense_diff_float64"] < 1e-7
    assert out["ghost_simplices"] > 0            # the walk meets ghost slivers here (a case that once failed)
    assert out["ratio_float64"] > 0 and out["reference_s"] > 0


def test_measure_runs_and_blending_beats_the_neutral(tmp_path):
    sub = toy_subject(nx=9, ny=8, n_shapes=4, seed=1)
    S, params = random_sources(sub, 12, seed=2)
    rng = np.random.default_rng(0)
    problem = dict(name="tiny", sources=S, params=params, neutral_index=0, triangles=sub.triangles,
                   regions=sub.regions, vertices=sub.neutral,
                   pose=lambda P: sub.pose(P, rng.normal(size=(len(P), 3)) * 0.1),
                   out_of_set=rng.random((8, 4)))
    out = measure.run(problem, residual_threshold=1e-5, n_blends=8, out_dir=str(tmp_path))
    e = out["errors"]["random blends"]
    assert e["blend (no culling)"]["mean_mm"] < 0.5 * e["neutral only"]["mean_mm"]
    assert set(out["kept"]) == set(sub.regions) and all(1 <= k <= 12 for k in out["kept"].values())
    assert (tmp_path / "blending_dims_culling.png").stat().st_size > 10_000
    assert (tmp_path / "blending_error.png").stat().st_size > 10_000
