"""A picture of one tracked frame: the dots over the video (``mifacerf track --overlay F``).

Green circles: tracked dots, used in this camera; yellow: tracked, not used in this camera; red:
untracked (at its filled-in position). ``marks`` (optional, world metres) are drawn as blue
crosses — the evaluation passes the true dot centres (:func:`mifacerf.evaluation.tracking.overlay`).
Pixel centres at integer coordinates (OpenCV), the picture ``scale`` times the video's size.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .track import Track


def overlay(track, frame: int, camera: str, path, marks=None, scale: int = 3) -> Path:
    """Write the picture of ``frame`` seen by ``camera`` to ``path``; ``marks`` (D, 3) or None."""
    import cv2

    from ..formats.performance import PerformanceFolder
    from ..imageio import to_srgb8, write_png

    tr = track if isinstance(track, Track) else Track(track)
    perf = PerformanceFolder(tr.performance)
    c = perf.camera_names.index(camera)
    cam = perf.cameras[c]
    img = perf.read(camera, frame)
    img = np.zeros((cam.height, cam.width, 3), np.float32) if img is None else img
    big = cv2.resize(to_srgb8(img, 1.5), None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
    big = np.ascontiguousarray(big)
    uv_used = tr.uv[frame, c]
    proj = cam.project(tr.dots[frame])[0]
    if marks is not None:
        for u, v in cam.project(np.asarray(marks))[0]:
            if np.isfinite(u):
                cv2.drawMarker(big, (int(round((u + 0.5) * scale - 0.5)), int(round((v + 0.5) * scale - 0.5))),
                               (80, 120, 255), cv2.MARKER_CROSS, 2 * scale, 1)
    for d in range(len(proj)):
        used = np.isfinite(uv_used[d]).all()
        tracked = tr.dot_status[frame, d] == 1
        u, v = uv_used[d] if used else proj[d]
        if not np.isfinite(u):
            continue
        colour = (60, 230, 60) if (tracked and used) else ((230, 200, 60) if tracked else (255, 40, 40))
        cv2.circle(big, (int(round((u + 0.5) * scale - 0.5)), int(round((v + 0.5) * scale - 0.5))),
                   max(2, scale), colour, 1)
    write_png(path, big)
    return Path(path)
