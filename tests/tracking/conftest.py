"""Shared fixtures for the tracking tests: one tiny synthetic world, built once per session.

``world``: a three-expression light-stage capture of the synthetic subject through three 96 px
cameras framing the face (so a fiducial is ~0.7 px in radius), a 0.4 s performance recorded
through the same cameras (24 frames at 60 fps), a model built from a *truth* registration (test
code: rendering is tested apart from registration, as tests/rendering does), and the track of the
clean performance. Fault injection (dropped, duplicated, dark frames, a dot painted out) works on
copies of the performance folder (tests/helpers/tracking.py).
"""
from __future__ import annotations

import pytest

from helpers.tracking import world_cameras, write_truth_registration

EXPRESSIONS = ["neutral", "smile", "viseme_aa"]
SECONDS = 0.4


@pytest.fixture(scope="session")
def world(tmp_path_factory):
    from mifacerf.rendering.build import build_model
    from mifacerf.rig import LightStage, Rig
    from mifacerf.synthetic.synth import synthesize
    from mifacerf.synthetic.recording import record_performance
    from mifacerf.tracking.track import Track, track_performance

    out = tmp_path_factory.mktemp("world")
    rig = Rig(LightStage.semicircular_arm(6, 4, irradiance_spread=0.05, seed=7), world_cameras())
    synthesize(out, preset="tiny", expressions=EXPRESSIONS, progress=False, rig=rig)
    perf = record_performance(out, SECONDS, size=None, progress=False)
    reg = write_truth_registration(out)
    model = build_model(out / "capture", out / "model", registration=reg).parent
    track = track_performance(perf, out / "track", model=model, progress=False)
    return {"out": out, "perf": perf, "model": model, "track": Track(track)}
