"""Head pose, teeth and eyes (paper §4.2).

* **Head pose** — "one point on each ear and one point on the bridge of the nose, which
  together determine a rigid transformation": the three points of an expression against
  the same three in the neutral, Horn's closed form (:func:`mifacerf.geometry.rigid.rigid_from_points`). Where
  the marks are missing, a robust rigid fit to the registered fiducials (the most rigid
  third, iteratively trimmed) stands in, and the report says so.
* **Upper teeth** — rigid with the skull: the head pose itself.
* **Lower teeth** — "a single marked 3D point, which determines their translation relative
  to the reference expression, and the relative rotation is approximated as the head pose
  rotation": ``t = p_marked − R p_marked,neutral``. Beyond the paper, ``R`` is the jaw's
  rotation where the chin's fiducials are registered (a rigid fit to them; the registration
  passes it in), the head's otherwise: an open jaw turns the lower teeth by up to 20° from
  the head, the chin fit is within 3° on the draft subject.
* **Eyes** — the irises, marked in several views, give the front of each eye: the centre of
  the iris ellipse fitted in each view is triangulated. Where the subject looks along a
  known direction (at a named camera, or ``"forward"`` along the head's +Z), the eyeball
  centre lies ``iris_depth`` behind the iris centre along it. Those centres, expressed in
  the head frame, are averaged; every expression's eye centres are that average carried
  by its head pose.

Transforms are 4 × 4 homogeneous matrices acting on world points (neutral → expression).
"""
from __future__ import annotations

import numpy as np

from ..camera import Camera
from ..geometry.rigid import apply, homogeneous, rigid_from_points
from ..geometry.triangulate import triangulate


def refine_rigid(T0: np.ndarray, P: np.ndarray, Q: np.ndarray, Pr: np.ndarray, Qr: np.ndarray, scale: float,
                 iterations: int = 4) -> tuple[np.ndarray, int]:
    """Refine a rigid transform fitted to marks (P → Q) with extra correspondences (Pr → Qr) from
    regions that move almost rigidly: those within ``2·max(median residual, scale)`` of the
    current fit are added (iteratively, starting from ``T0``). Returns (T, number of extras used)."""
    T = T0
    used = 0
    for _ in range(iterations):
        if len(Pr) < 3:
            break
        r = np.linalg.norm(apply(T, Pr) - Qr, axis=1)
        keep = r <= 2.0 * max(float(np.median(r)), scale)
        used = int(keep.sum())
        if used < 3:
            break
        T = rigid_from_points(np.concatenate([P, Pr[keep]]), np.concatenate([Q, Qr[keep]]))
    return T, used


def triangulate_marks(cams: list[Camera], marks: dict) -> np.ndarray | None:
    """One 3-D point from clicks {camera name: (u, v)} (≥ 2 views), or None."""
    names = [c.name for c in cams]
    uv = np.full((len(cams), 1, 2), np.nan)
    for cam, p in marks.items():
        if cam in names:
            uv[names.index(cam), 0] = p
    tr = triangulate(cams, uv, max_error=3.0)
    return tr.points[0] if tr.ok[0] else None


def lower_teeth_transform(T_turn: np.ndarray, mark_neutral: np.ndarray, mark_expr: np.ndarray) -> np.ndarray:
    """Lower teeth (4, 4): the rotation of ``T_turn`` (jaw or head), translated so the marked point lands on its mark."""
    R = T_turn[:3, :3]
    return homogeneous(R, np.asarray(mark_expr) - R @ np.asarray(mark_neutral))


def ellipse_centre(poly: np.ndarray) -> np.ndarray:
    """Centre (2,) of the ellipse fitted to a closed polyline (P ≥ 5 points, pixels)."""
    import cv2

    P = np.asarray(poly, np.float64).reshape(-1, 2)
    mean = P.mean(0)
    if len(P) >= 8:
        (cx, cy), _, _ = cv2.fitEllipse(P.astype(np.float32).reshape(-1, 1, 2))
        c = np.array([cx, cy], np.float64)
        extent = np.ptp(P, axis=0).max()
        if np.isfinite(c).all() and np.linalg.norm(c - mean) <= 0.25 * extent:
            return c
    return mean


def iris_centre(cams: list[Camera], views: dict) -> np.ndarray | None:
    """3-D iris centre from iris polylines {camera: (P, 2)} in ≥ 2 views."""
    return triangulate_marks(cams, {c: ellipse_centre(p) for c, p in views.items()})


def gaze_direction(look_at: str, T_head: np.ndarray, iris: np.ndarray, cams: list[Camera]) -> np.ndarray | None:
    """Unit gaze direction for ``look_at`` = "forward" (head +Z) or a camera name; None if unknown."""
    if look_at == "forward":
        d = T_head[:3, :3] @ np.array([0.0, 0.0, 1.0])
    else:
        cam = next((c for c in cams if c.name == look_at), None)
        if cam is None:
            return None
        d = cam.centre - iris
    return d / np.linalg.norm(d)


def eye_depth(eye: dict) -> float:
    """Distance from the eyeball centre to the iris centre (template ``eyes`` entry)."""
    if "iris_depth" in eye:
        return float(eye["iris_depth"])
    r, ri = float(eye.get("radius", 0.012)), float(eye.get("iris_radius", 0.0059))
    return float(np.sqrt(max(r * r - ri * ri, 0.0)))
