"""Fiducial dots: ~300 fluorescent-yellow gel-ink dots spread evenly over the face and neck.

Dots are chosen on the **neutral** skin by farthest-point sampling over area-uniform candidate
points of an allowed region (face and neck below the hairline; not on the red of the lips, the
eyelids, inside the nostrils or on the ears), seeded with the landmark dots the coarse registration
mesh uses (nose tip, chin, brows, cheeks ...). Each dot is stored as a skin surface point
(triangle, barycentric), so its centre is exact in every expression.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from . import head as H
from .textures import hair_mask, head_azimuth, vermilion_mask, vertex_normals

DOT_RADIUS = 0.0015          #: 3 mm diameter
N_DOTS = 300

#: landmark dots (approximate neutral targets, head frame); the nearest allowed point is used
LANDMARK_DOTS = {
    "forehead": (0.0, 0.055, 0.10),
    "brow_L": (0.034, 0.030, 0.10),
    "brow_R": (-0.034, 0.030, 0.10),
    "nose_tip": (0.0, -0.033, 0.13),
    "cheek_L": (0.045, -0.025, 0.09),
    "cheek_R": (-0.045, -0.025, 0.09),
    "philtrum": (0.0, H.Y_MOUTH + 0.013, 0.11),
    "under_lip": (0.0, H.Y_MOUTH - 0.020, 0.11),
    "chin": (0.0, -0.100, 0.10),
    "jaw_L": (0.056, -0.080, 0.03),
    "jaw_R": (-0.056, -0.080, 0.03),
    "throat": (0.0, -0.135, 0.06),
    "neck_low": (0.0, -0.180, 0.06),
}


def sample_surface(V, F, n, seed):
    """``n`` area-uniform random surface points: triangle ids and barycentrics."""
    rng = np.random.default_rng(seed)
    a = 0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1)
    tri = rng.choice(len(F), size=n, p=a / a.sum())
    r1 = np.sqrt(rng.random(n))
    r2 = rng.random(n)
    bary = np.stack([1 - r1, r1 * (1 - r2), r1 * r2], 1)
    return tri, bary


def allowed(P, N):
    """Where dots may go, on neutral positions ``P`` with normals ``N`` (bool)."""
    x, y, z = P[:, 0], P[:, 1], P[:, 2]
    ok = np.abs(head_azimuth(P)) < np.radians(98)
    ok &= y > -0.195
    ok &= hair_mask(P) < 0.02
    for sgn in (1.0, -1.0):
        ok &= np.linalg.norm(P - H.EYE_CENTRE * np.array([sgn, 1, 1]), axis=1) > 0.0190
        # ears
        ec = np.array([sgn * 0.0715, -0.011, -0.016])
        ok &= np.linalg.norm((P - ec) / np.array([0.024, 0.038, 0.028]), axis=1) > 1.0
        # nostrils and the underside of the nose
        nc = np.array([sgn * 0.0066, -0.0428, 0.0985])
        ok &= np.linalg.norm((P - nc) / np.array([0.0075, 0.0055, 0.0090]), axis=1) > 1.0
    ok &= ~((N[:, 1] < -0.45) & (np.abs(x) < 0.026) & (y > -0.050) & (y < -0.025) & (z > 0.075))
    return ok


def choose_dots(neutral, faces, n_dots=N_DOTS, seed=1234, n_candidates=60000, avoid=None, avoid_dist=0.006):
    """Dots on the neutral skin: ``(tri, bary, names)``; ``names[i]`` is a landmark name or ''.
    ``avoid``: (k, 3) points (other template vertices) that dots keep ``avoid_dist`` from."""
    tri, bary = sample_surface(neutral, faces, n_candidates, seed)
    P = np.einsum("nk,nkj->nj", bary, neutral[faces[tri]])
    Nv = vertex_normals(neutral, faces)
    N = np.einsum("nk,nkj->nj", bary, Nv[faces[tri]])
    ok = allowed(P, N)
    # keep 3 mm (plus the dot radius) off the red of the lips
    lips = P[vermilion_mask(P) > 0.5]
    if len(lips):
        d, _ = cKDTree(lips).query(P, k=1)
        ok &= d > 0.0030 + DOT_RADIUS
    if avoid is not None and len(avoid):
        d, _ = cKDTree(np.asarray(avoid)).query(P, k=1)
        ok &= d > avoid_dist
    tri, bary, P = tri[ok], bary[ok], P[ok]
    # farthest-point sampling seeded with the landmarks
    chosen, names = [], []
    for name, target in LANDMARK_DOTS.items():
        t = np.asarray(target)
        # nearest candidate, preferring the front-most along the view line for frontal targets
        d = np.linalg.norm(P - t, axis=1)
        chosen.append(int(np.argmin(d)))
        names.append(name)
    dist = np.full(len(P), np.inf)
    if avoid is not None and len(avoid):
        dist = np.minimum(dist, cKDTree(np.asarray(avoid)).query(P, k=1)[0])
    for c in chosen:
        dist = np.minimum(dist, np.linalg.norm(P - P[c], axis=1))
    while len(chosen) < n_dots:
        c = int(np.argmax(dist))
        chosen.append(c)
        names.append("")
        dist = np.minimum(dist, np.linalg.norm(P - P[c], axis=1))
    chosen = np.array(chosen)
    return tri[chosen].astype(np.int32), bary[chosen], names
