"""Shared fixtures for the tracking tests: one tiny synthetic world, built once per session.

``world``: a three-expression light-stage capture of the synthetic subject through three 96 px
cameras framing the face (so a fiducial is ~0.7 px in radius), a 0.4 s performance recorded
through the same cameras (24 frames at 60 fps), a model built from a *truth* registration (test
code: rendering is tested apart from registration, as tests/rendering does), and the track of the
clean performance. Fault injection (dropped, duplicated, dark frames, a dot painted out) works on
copies of the performance folder.
"""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

EXPRESSIONS = ["neutral", "smile", "viseme_aa"]
SECONDS = 0.4
def test_cameras(size: int = 96):
    from mifacerf.rig import camera_ring

    return camera_ring([(-28.0, 6.0), (0.0, 0.0), (28.0, 6.0)], width=size, height=size, face_height=0.2)


test_cameras.__test__ = False  # not a test


def write_truth_registration(out: Path) -> Path:
    """A registration folder written from the synthetic truth (test code only)."""
    from mifacerf.capture_folder import Capture
    from mifacerf.registered import RegisteredExpression, RegistrationWriter
    from mifacerf.geometry.meshscene import MeshScene

    from mifacerf.synthetic import default_subject

    subject = default_subject()
    cap = Capture(out / "capture")
    template = json.loads((out / "capture" / "hand" / "template.json").read_text())
    tri = np.asarray(template["triangles"])
    rw = RegistrationWriter(out / "truth_registration", cap, template)
    scene = None
    for name in cap.expression_names:
        z = np.load(out / "truth" / "expressions" / f"{name}.npz")
        v = z["template_vertices"]
        scene = scene or MeshScene(v, tri)
        scene.set_vertices(v)
        uv = np.stack([c.project(v)[0] for c in cap.rig.cameras]).astype(np.float32)
        vis = np.stack([scene.visible_from(v, c) for c in cap.rig.cameras])
        eyes = np.stack([z[f"part_{e}"][:3, :3] @ subject.eye_centres[e] + z[f"part_{e}"][:3, 3]
                         for e in ("eye_left", "eye_right")])
        rw.write_expression(RegisteredExpression(name, v, np.ones(len(v)), uv, vis, eye_centres=eyes),
                            {"source": "truth"})
    return out / "truth_registration"


@pytest.fixture(scope="session")
def world(tmp_path_factory):
    from mifacerf.rendering.build import build_model
    from mifacerf.rig import LightStage, Rig
    from mifacerf.synthetic.synth import synthesize
    from mifacerf.synthetic.recording import record_performance
    from mifacerf.tracking.track import Track, track_performance

    out = tmp_path_factory.mktemp("world")
    rig = Rig(LightStage.semicircular_arm(6, 4, irradiance_spread=0.05, seed=7), test_cameras())
    synthesize(out, preset="tiny", expressions=EXPRESSIONS, progress=False, rig=rig)
    perf = record_performance(out, SECONDS, size=None, progress=False)
    reg = write_truth_registration(out)
    model = build_model(out / "capture", out / "model", registration=reg).parent
    track = track_performance(perf, out / "track", model=model, progress=False)
    return {"out": out, "perf": perf, "model": model, "track": Track(track)}


def copy_performance(perf: Path, dest: Path) -> Path:
    """A copy of a performance folder (frames, hand inputs, manifest) at ``dest``."""
    shutil.copytree(perf, dest, ignore=shutil.ignore_patterns("track"))
    return dest


def paint_out_dot(perf: Path, camera, frame: int, uv: np.ndarray, radius: float = 2.2) -> None:
    """Cover a dot in one image with the skin around it (a dot that fell off / is smeared)."""
    from mifacerf.imageio import read_exr, write_exr

    path = perf / "frames" / camera.name / f"F{frame:05d}.exr"
    if not path.exists():
        return
    img = read_exr(path)
    yy, xx = np.mgrid[0:img.shape[0], 0:img.shape[1]]
    d = np.hypot(xx - uv[0], yy - uv[1])
    ring = (d > radius + 1.0) & (d < radius + 3.0)
    img[d <= radius] = np.median(img[ring], axis=0)
    write_exr(path, img)
