"""Tracking against the synthetic truth (evaluation only: tracking itself never reads truth).

``mifacerf evaluate tracking OUT [TRACK] [--overlay F]``.

:func:`evaluate_track` compares a track folder with ``OUT/truth/performance`` and reports, in
**pixel footprints** (the size of one video pixel at the rig centre) unless stated otherwise:

* ``dot_error``: tracked dots (status 1) against the true dot centres — median, 95th percentile;
  ``dot_error_all``: every dot in every frame, untracked ones at their filled-in positions;
* ``dots_tracked_whole_sequence``: fraction of dots tracked in every frame that had at least two
  usable cameras; ``dot_frames_tracked``: fraction of (dot, frame) pairs tracked;
  ``dot_frames_seen_by_two_cameras``: fraction of (dot, frame) pairs two cameras could see at all
  (ray-traced against the true skin, the same facing test as tracking), ``dot_frames_tracked_of_seen`` how many of those
  were tracked, ``dots_seen_throughout`` the dots two cameras see in every frame;
* ``head_pose``: rotation error (degrees) and the error at the nose bridge;
* ``gaze_deg``: angle between tracked and true gaze, at iris keyframes and in between;
* ``margins``: lip and eyelid margins against the truth, at their keyframes and in between;
* ``vertices``: every template vertex.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..formats.files import write_json_atomic
from ..geometry.footprint import centre_footprint
from ..stats import median_p95
from ..synthetic.recording import read_truth
from ..tracking.track import Track


def _stats(x) -> dict:
    """Median, p95, max (rounded to 4 decimals) and count of the finite values."""
    return median_p95(x, with_max=True)


def truth_visibility(truth, params: np.ndarray, points: np.ndarray, cameras, min_cos: float, tol: float) -> np.ndarray:
    """(N, C, D) whether each camera sees each dot (``points`` (N, D, 3)) on the true skin of every frame."""
    from scipy.spatial import cKDTree

    from ..geometry.meshscene import MeshScene
    from ..synthetic.synth import load_subject, subject_from_truth

    subject = None
    for cand in (Path(truth) / "truth" / "truth.json", Path(truth).parent / "truth.json"):
        if cand.exists():
            subject = subject_from_truth(cand.parent.parent)
            break
    subject = subject if subject is not None else load_subject(None)
    scene = None
    out = np.zeros((len(params), len(cameras), points.shape[1]), bool)
    for f, p in enumerate(params):
        pose = subject.pose(p, textures=False)
        if scene is None:
            scene = MeshScene(pose.skin_vertices, subject.skin_faces)
        else:
            scene.set_vertices(pose.skin_vertices)
        _, near = cKDTree(pose.skin_vertices).query(points[f])
        normals = pose.skin_normals[near]
        for c, cam in enumerate(cameras):
            d = cam.centre - points[f]
            d /= np.linalg.norm(d, axis=1, keepdims=True)
            out[f, c] = scene.visible_from(points[f], cam, tol=tol) & (np.einsum("ij,ij->i", d, normals) > min_cos)
    return out


def evaluate_track(track, truth, write: bool = True, coverage: bool = True) -> dict:
    """Compare a track (folder or :class:`Track`) with the performance truth (``OUT`` or its truth folder)."""
    from ..formats.performance import PerformanceFolder
    from ..registration.hand import Template

    tr = track if isinstance(track, Track) else Track(track)
    tru = read_truth(truth)
    perf = PerformanceFolder(tr.performance)
    tpl = Template.from_dict(perf.template())
    fp = centre_footprint(perf.cameras)
    n = tr.n_frames
    dots = tr.dot_ids
    Xt = tru["template_vertices"][:n, dots]
    err = np.linalg.norm(tr.dots - Xt, axis=-1) / fp
    st = tr.dot_status == 1
    usable = (tr.camera_status == 0).sum(1) >= 2
    # which dots two cameras could see at all: the true skin (the nose, the chin occlude), facing test
    if coverage:
        seen2 = truth_visibility(truth, tru["params"][:n], tru["template_vertices"][:n, dots], perf.cameras,
                                 tr.meta["options"]["min_cos"], fp).sum(1) >= 2
    else:
        seen2 = np.ones(st.shape, bool)
    seen2 &= usable[:, None]
    out = {
        "footprint_m": fp,
        "dot_frames_seen_by_two_cameras": round(float(seen2.mean()), 4),
        "dot_frames_tracked_of_seen": round(float((st & seen2).sum() / max(seen2.sum(), 1)), 4),
        "dots_seen_throughout": round(float(seen2[usable].all(0).mean()), 4) if usable.any() else 0.0,
        "dot_error": _stats(err[st]),
        "dot_error_all": _stats(err),
        "dot_error_untracked": _stats(err[~st]),
        "dots_tracked_whole_sequence": round(float(st[usable].all(0).mean()), 4) if usable.any() else 0.0,
        "dot_frames_tracked": round(float(st.mean()), 4),
    }
    # head pose: the tracked rigid map against the truth's head transform (both rest → frame)
    Ht, Hg = tr.head_pose, tru["head"][:n]
    dR = np.einsum("nij,nkj->nik", Ht[:, :3, :3], Hg[:, :3, :3])
    ang = np.degrees(np.arccos(np.clip((np.trace(dR, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    nb = tpl.head_points.get("nose_bridge")
    p = tpl.vertices[nb] if nb is not None else np.zeros(3)
    pt = np.einsum("nij,j->ni", Ht[:, :3, :3], p) + Ht[:, :3, 3]
    pg = np.einsum("nij,j->ni", Hg[:, :3, :3], p) + Hg[:, :3, 3]
    out["head_pose"] = {"rotation_deg": _stats(ang), "nose_bridge_px": _stats(np.linalg.norm(pt - pg, axis=1) / fp)}
    # gaze
    keys = tr.meta.get("keyframes", {})
    g_true = tru["eyes"][:n, :, :3, 2]
    gang = np.degrees(np.arccos(np.clip(np.einsum("nkj,nkj->nk", tr.gaze, g_true), -1, 1)))
    ik = np.zeros(n, bool)
    ik[[k for k in keys.get("irises", []) if k < n]] = True
    out["gaze_deg"] = {"keyframes": _stats(gang[ik]), "in_between": _stats(gang[~ik])}
    # lips and eyelids
    V = tr.vertices
    Vt = tru["template_vertices"][:n]
    margins = {}
    for name, ids in tpl.margins.items():
        kind = "lips" if name.startswith("lip") else "eyelids"
        km = np.zeros(n, bool)
        km[[k for k in keys.get(kind, []) if k < n]] = True
        e = np.linalg.norm(V[:, ids] - Vt[:, ids], axis=-1) / fp
        margins[name] = {"keyframes": _stats(e[km]), "in_between": _stats(e[~km])}
    out["margins"] = margins
    out["vertices"] = _stats(np.linalg.norm(V - Vt, axis=-1) / fp)
    out["tracking_seconds_per_frame"] = tr.meta.get("time_s", {}).get("per_frame_mean")
    if write:
        write_json_atomic(tr.root / "evaluation.json", out)
    return out


def overlay(track, frame: int, camera: str, path, truth=None, scale: int = 3) -> Path:
    """:func:`mifacerf.tracking.overlay.overlay` with the true dot centres of ``frame`` (blue crosses) when
    ``truth`` (a ``mifacerf synth`` output or its performance truth folder) is given."""
    from ..tracking.overlay import overlay as draw

    tr = track if isinstance(track, Track) else Track(track)
    marks = None if truth is None else read_truth(truth)["template_vertices"][frame, tr.dot_ids]
    return draw(tr, frame, camera, path, marks=marks, scale=scale)
