"""The tracking tests' synthetic world (its cameras, a registration written from the truth) and fault
injection on copies of a performance folder (tests/tracking/conftest.py builds the world)."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np


def world_cameras(size: int = 96):
    """The world's three ``size`` px cameras framing the face."""
    from mifacerf.rig import camera_ring

    return camera_ring([(-28.0, 6.0), (0.0, 0.0), (28.0, 6.0)], width=size, height=size, face_height=0.2)


def write_truth_registration(out: Path) -> Path:
    """A registration folder written from the synthetic truth (test code only)."""
    from mifacerf.formats.capture import Capture
    from mifacerf.formats.registration import RegisteredExpression, RegistrationWriter
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


def copy_performance(perf: Path, dest: Path) -> Path:
    """A copy of a performance folder (frames, hand inputs, manifest) at ``dest``."""
    shutil.copytree(perf, dest, ignore=shutil.ignore_patterns("track"))
    return dest


def as_recorded(perf: Path) -> Path:
    """The manifest's frame checksums and sizes made again from the frames on disk: the faults a test put
    into the frames (dropped, garbled, dark, painted-out dots) become the cameras' own, as recorded, and
    not later damage (which reading a frame reports as a checksum error)."""
    import json

    from mifacerf.formats.files import sha256_file, write_json_atomic

    meta = json.loads((perf / "manifest.json").read_text())
    frames = sorted(p for p in (perf / "frames").rglob("F*.exr"))
    meta["checksums"] = {p.relative_to(perf).as_posix(): sha256_file(p) for p in frames}
    meta["sizes"] = {p.relative_to(perf).as_posix(): p.stat().st_size for p in frames}
    write_json_atomic(perf / "manifest.json", meta)
    return perf


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
