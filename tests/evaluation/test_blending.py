"""Smoke test of the blending measurement against true deformations at a toy size (not timed)."""
import numpy as np

from mifacerf.blending.toy import random_sources, toy_subject
from mifacerf.evaluation import blending as measure


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


def test_cli_on_the_toy_sheet(tmp_path):
    import json

    from click.testing import CliRunner

    from mifacerf.cli import main

    r = CliRunner().invoke(main, ["evaluate", "blending", "--subject", "toy", "--json", str(tmp_path / "b.json")])
    assert r.exit_code == 0, r.output
    out = json.loads((tmp_path / "b.json").read_text())
    assert out["subject"] == "toy sheet" and out["errors"]["out-of-set"]["targets"] == 60
