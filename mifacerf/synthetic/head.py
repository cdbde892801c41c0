"""Procedural head geometry: an analytic signed-distance head, sliced into a meridian-profile grid.

The skin is built on a 2-D parameter grid (row = position along a meridian profile, column =
azimuth ``φ`` about the vertical axis ``x = 0, z = AXIS_Z``). For each column the head's
signed-distance function (SDF) is sliced by the half-plane at that azimuth; the outer zero contour
from the crown (on the axis) down to the neck base (``y = NECK_BASE_Y``) is that column's profile.
Rows sit at fixed fractions of arc length between *anchor* heights (the same fractions in every
column), so rows run round the head like lines of latitude; the crown is one shared pole vertex and
the neck base is closed by a flat cap.

Mouth and eye openings are **slits**: a row segment whose inner vertices are duplicated (the
originals belong to the upper lip / upper lid, the duplicates to the lower one; the two end vertices,
the corners, are shared). In the rest shape (this module's output) the slits are closed, the lips
touch and the lids are shut, draped over a sphere round the eyeball; :mod:`.expressions` opens them
with smooth, fold-free displacement fields (the neutral expression has open eyes).

World frame per ``docs/conventions.md``: metres, +Y up, the face looks along +Z, +X is the
subject's left. All numbers here are the head frame at the neutral head pose.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

# --------------------------------------------------------------------------------------------
# anatomy (metres, head frame)
# --------------------------------------------------------------------------------------------
AXIS_Z = -0.010          #: z of the vertical axis the meridian grid turns about
NECK_BASE_Y = -0.220     #: the neck is cut (and capped) at this height; it never moves
CROWN_Y = 0.1235

EYE_CENTRE = np.array([0.0315, 0.0055, 0.0655])  #: left eye (+X); the right one is mirrored
EYE_RADIUS = 0.0120      #: sclera sphere
CORNEA_HEIGHT = 0.0012   #: the cornea bulges this far above the sclera sphere
IRIS_RADIUS = 0.0059     #: iris radius (chord) on the eyeball
PUPIL_RADIUS = 0.0020
LID_RADIUS = 0.0135      #: shut lids lie on this sphere about the eye centre (covers the cornea)
Y_EYE = 0.0035           #: height of the eye slits (the line where shut lids meet)
EYE_SLIT_AZ = (-0.98, 1.28)  #: medial, lateral end of the eye slit: azimuth about the eye centre (rad)

Y_MOUTH = -0.0670        #: height of the mouth slit (lips closed)
MOUTH_HALF_WIDTH = 0.0245  #: |x| of the mouth corners

JAW_HINGE = np.array([0.0, -0.012, -0.008])   #: jaw rotation axis: the X axis through this point
NECK_PIVOT = np.array([0.0, -0.085, -0.025])  #: head-pose rotations turn about this point

#: hairline: height (m) of the hair's edge as a function of |azimuth| about the vertical axis (deg)
HAIRLINE_DEG = (0, 20, 35, 48, 60, 70, 77, 80, 83, 87, 93, 110, 130, 150, 180)
HAIRLINE_Y = (0.079, 0.077, 0.069, 0.060, 0.050, 0.042, 0.030, 0.008, 0.006, 0.022, 0.027, 0.024, 0.000,
              -0.045, -0.068)
HAIR_THICKNESS = 0.006   #: the hair stands this far off the scalp (short hair)


def hairline_y(p):
    phi = np.degrees(np.abs(np.arctan2(p[..., 0], p[..., 2] - AXIS_Z)))
    return np.interp(phi, HAIRLINE_DEG, HAIRLINE_Y)


# anchor heights for the rows (every meridian crosses them once, from the crown downwards)
ANCHORS_Y = (0.075, 0.028, Y_EYE, Y_MOUTH)


# --------------------------------------------------------------------------------------------
# SDF primitives (vectorised over points (..., 3))
# --------------------------------------------------------------------------------------------
def smin(a, b, k):
    """Polynomial smooth minimum (union) with blend radius ``k``."""
    h = np.clip(0.5 + 0.5 * (b - a) / k, 0.0, 1.0)
    return b + (a - b) * h - k * h * (1.0 - h)


def smoothstep_np(e0, e1, x):
    t = np.clip((x - e0) / (e1 - e0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def smax(a, b, k):
    """Smooth maximum (intersection / subtraction with ``-b``)."""
    return -smin(-a, -b, k)


def sd_ellipsoid(p, c, r, rot=None):
    """Approximate signed distance to an ellipsoid (exact zero set)."""
    q = p - np.asarray(c)
    if rot is not None:
        q = q @ np.asarray(rot)  # rows: q_local = R^T q
    r = np.asarray(r, float)
    u = q / r
    k0 = np.sqrt(np.einsum("...k,...k->...", u, u))
    u = u / r
    k1 = np.sqrt(np.einsum("...k,...k->...", u, u))
    return np.where(k1 > 1e-12, k0 * (k0 - 1.0) / np.maximum(k1, 1e-12), -r.min())


def sd_superellipsoid_xz(p, c, r, e=2.6):
    """Quasi-distance to an ellipsoid whose horizontal (x-z) sections are super-ellipses of exponent
    ``e`` (flatter front and sides than an ellipse); exact zero set, ~metric near it."""
    q = (p - np.asarray(c)) / np.asarray(r, float)
    rxz = (np.abs(q[..., 0]) ** e + np.abs(q[..., 2]) ** e) ** (1.0 / e)
    k = np.sqrt(rxz * rxz + q[..., 1] ** 2)
    return (k - 1.0) * float(np.mean(r))


def _norm(v):
    return np.sqrt(np.einsum("...k,...k->...", v, v))


def _local_union(d, p, centre, radius, k, fn, carve=False):
    """``smin(d, fn(p), k)`` (or ``smax(d, -fn(p), k)`` if ``carve``), evaluated only where the
    feature (inside a ball ``centre``, ``radius``) can change ``d``; conservative bound."""
    lb = 0.5 * (_norm(p - np.asarray(centre)) - radius)
    m = (lb < k - d) if carve else (lb < d + k)
    if not np.any(m):
        return d
    d = d.copy()
    e = fn(p[m])
    d[m] = smax(d[m], -e, k) if carve else smin(d[m], e, k)
    return d


def sd_capsule(p, a, b, r):
    a = np.asarray(a, float)
    b = np.asarray(b, float)
    pa = p - a
    ba = b - a
    h = np.clip((pa @ ba) / (ba @ ba), 0.0, 1.0)
    return np.linalg.norm(pa - h[..., None] * ba, axis=-1) - (r(h) if callable(r) else r)


def rot_x(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def rot_y(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def rot_z(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def head_sdf(p: np.ndarray) -> np.ndarray:
    """Signed distance (approximately, metres; negative inside) of the rest head at points ``p``."""
    p = np.asarray(p, float)
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    ax = np.abs(x)
    ps = np.stack([ax, y, z], axis=-1)  # left-right symmetric features use |x|

    # cranium and forehead
    d = sd_ellipsoid(p, (0.0, 0.028, -0.014), (0.0745, 0.0955, 0.0990))
    fore = sd_superellipsoid_xz(p, (0.0, 0.040, 0.002), (0.0630, 0.0520, 0.0880), 2.4)
    d = smin(d, fore, 0.020)
    # short hair: the scalp inflated by HAIR_THICKNESS above the hairline (edge 4 mm above it)
    cap = smax(d - HAIR_THICKNESS, hairline_y(p) + 0.004 - y, 0.003)
    d = smin(d, cap, 0.002)
    # the lower face: a jaw mass that narrows towards the chin
    taper = 1.0 + 0.38 * np.clip((y + 0.040) / 0.070, -1.0, 0.5)
    pj = np.stack([x / taper, y, z], axis=-1)
    jaw = sd_superellipsoid_xz(pj, (0.0, -0.040, 0.012), (0.0620, 0.0680, 0.0760), 2.5) * np.minimum(taper, 1.0)
    d = smin(d, jaw, 0.020)
    # maxilla / mouth mound
    pb = np.stack([x, y, z + 14.0 * x * x], axis=-1)  # bent along the dental arch
    mound = sd_ellipsoid(pb, (0.0, -0.060, 0.059), (0.034, 0.026, 0.029))
    d = smin(d, mound, 0.012)
    # chin
    chin = sd_ellipsoid(p, (0.0, -0.0945, 0.068), (0.0195, 0.0140, 0.0195))
    d = smin(d, chin, 0.012)
    # jaw angles
    gon = sd_ellipsoid(ps, (0.051, -0.068, -0.010), (0.011, 0.018, 0.022))
    d = smin(d, gon, 0.022)
    # neck: an elliptic cylinder leaning slightly forwards at the bottom
    zc = -0.020 + 0.10 * np.clip(-(y + 0.10), 0.0, None)
    flare = 1.0 + 0.22 * smoothstep_np(-0.165, -0.225, y)
    rn = np.sqrt((x / (0.056 * flare)) ** 2 + ((z - zc) / (0.059 * flare)) ** 2)
    neck = (rn - 1.0) * 0.057
    neck = smax(neck, y + 0.03, 0.02)  # ends inside the head
    d = smin(d, neck, 0.022)
    # trapezius slope at the neck base (a hint of shoulders)
    trap = sd_ellipsoid(p, (0.0, -0.268, -0.032), (0.095, 0.070, 0.068))
    d = smin(d, trap, 0.025)

    # cheekbones and cheeks
    d = _local_union(d, ps, (0.050, -0.011, 0.047), 0.022, 0.016,
                     lambda q: sd_ellipsoid(q, (0.050, -0.011, 0.047), (0.020, 0.011, 0.022), rot_y(0.5)))
    d = _local_union(d, ps, (0.036, -0.032, 0.058), 0.025, 0.020,
                     lambda q: sd_ellipsoid(q, (0.036, -0.032, 0.058), (0.025, 0.025, 0.022)))
    # temples (slight hollow)
    d = _local_union(d, ps, (0.084, 0.022, 0.030), 0.020, 0.012,
                     lambda q: sd_ellipsoid(q, (0.084, 0.022, 0.030), (0.016, 0.020, 0.020)), carve=True)
    # brow ridge
    d = _local_union(d, ps, (0.0225, 0.024, 0.071), 0.036, 0.010,
                     lambda q: sd_capsule(q, (0.000, 0.0235, 0.0795), (0.045, 0.0250, 0.0625), 0.0105))

    # eye sockets, carved, then the shut-lid sphere
    ce = EYE_CENTRE
    sc = (ce[0] + 0.001, ce[1] - 0.0005, ce[2] + 0.0080)
    d = _local_union(d, ps, sc, 0.0195, 0.008,
                     lambda q: sd_ellipsoid(q, sc, (0.0195, 0.0140, 0.0140), rot_y(0.22)), carve=True)
    d = _local_union(d, ps, ce, LID_RADIUS, 0.0045, lambda q: _norm(q - ce) - LID_RADIUS)

    # nose: bridge, tip, alae; nostrils carved underneath
    d = _local_union(d, p, (0.0, -0.0075, 0.091), 0.032, 0.006,
                     lambda q: sd_capsule(q, (0.0, 0.012, 0.0775), (0.0, -0.027, 0.1050),
                                          lambda h: 0.0056 + 0.0020 * h))
    d = _local_union(d, p, (0.0, -0.0330, 0.1025), 0.0095, 0.004,
                     lambda q: sd_ellipsoid(q, (0.0, -0.0330, 0.1025), (0.0090, 0.0088, 0.0095)))
    d = _local_union(d, ps, (0.0122, -0.0400, 0.0870), 0.0085, 0.0065,
                     lambda q: sd_ellipsoid(q, (0.0122, -0.0400, 0.0870), (0.0062, 0.0056, 0.0080),
                                            rot_y(0.35)))
    d = _local_union(d, ps, (0.0066, -0.0428, 0.0985), 0.0052, 0.0018,
                     lambda q: sd_ellipsoid(q, (0.0066, -0.0428, 0.0985), (0.0033, 0.0019, 0.0050),
                                            rot_y(0.3)), carve=True)

    # lips (upper and lower) meeting along the mouth line, bent along the dental arch
    def bent(q):
        return np.stack([q[..., 0], q[..., 1], q[..., 2] + 18.0 * q[..., 0] ** 2], axis=-1)
    d = _local_union(d, p, (0.0, Y_MOUTH + 0.0048, 0.082), 0.030, 0.0030,
                     lambda q: sd_ellipsoid(bent(q), (0.0, Y_MOUTH + 0.0048, 0.0885), (0.0255, 0.0055, 0.0072)))
    d = _local_union(d, p, (0.0, Y_MOUTH - 0.0060, 0.081), 0.030, 0.0030,
                     lambda q: sd_ellipsoid(bent(q), (0.0, Y_MOUTH - 0.0060, 0.0868), (0.0230, 0.0066, 0.0078)))
    # mentolabial sulcus
    sulc = (0.0, Y_MOUTH - 0.0185, 0.0935)
    d = _local_union(d, p, sulc, 0.016, 0.004,
                     lambda q: sd_ellipsoid(q, sulc, (0.016, 0.0040, 0.0060)), carve=True)

    # ears: a flattened disc tilted backwards, with a hollow (concha) and a lobe
    er = rot_x(-0.25) @ rot_y(-0.28)
    d = _local_union(d, ps, (0.0715, -0.0110, -0.0160), 0.030, 0.006,
                     lambda q: sd_ellipsoid(q, (0.0715, -0.0110, -0.0160), (0.0115, 0.0300, 0.0185), er))
    d = _local_union(d, ps, (0.0835, -0.0170, -0.0105), 0.0115, 0.003,
                     lambda q: sd_ellipsoid(q, (0.0835, -0.0170, -0.0105), (0.0050, 0.0115, 0.0080), er),
                     carve=True)
    d = _local_union(d, ps, (0.0760, -0.0385, -0.0080), 0.0075, 0.004,
                     lambda q: sd_ellipsoid(q, (0.0760, -0.0385, -0.0080), (0.0060, 0.0075, 0.0065)))
    return d


def sdf_gradient(p: np.ndarray, h: float = 1e-5, f0: np.ndarray | None = None) -> np.ndarray:
    """Gradient of :func:`head_sdf`: central differences, or forward ones when ``f0`` (the SDF at
    ``p``) is given."""
    g = np.empty_like(p)
    for k in range(3):
        e = np.zeros(3)
        e[k] = h
        if f0 is None:
            g[..., k] = (head_sdf(p + e) - head_sdf(p - e)) / (2 * h)
        else:
            g[..., k] = (head_sdf(p + e) - f0) / h
    return g


# --------------------------------------------------------------------------------------------
# grid
# --------------------------------------------------------------------------------------------
def half_plane_points(rho, y, phi):
    rho = np.asarray(rho, float)
    y = np.asarray(y, float)
    return np.stack([rho * np.sin(phi), y, AXIS_Z + rho * np.cos(phi)], axis=-1)


def _density_cdf(t, knots, spacing):
    """Integrate 1/spacing (piecewise linear in ``t``) and normalise."""
    sp = np.interp(t, knots, spacing)
    w = 1.0 / sp
    c = np.concatenate([[0.0], np.cumsum(0.5 * (w[1:] + w[:-1]) * np.diff(t))])
    return c / c[-1]


def graded(n: int, knots, spacing, fine: int = 4000) -> np.ndarray:
    """``n + 1`` positions in [0, 1] whose local spacing follows ``spacing`` (relative) at ``knots``."""
    t = np.linspace(0.0, 1.0, fine)
    c = _density_cdf(t, knots, spacing)
    return np.interp(np.linspace(0.0, 1.0, n + 1), c, t)


def column_angles() -> np.ndarray:
    """Azimuths of the grid columns (radians, increasing, from −π), symmetric about 0."""
    # target spacing (radians) as a function of |φ|
    knots = np.radians([0, 12, 34, 42, 80, 100, 180])
    spacing = np.radians([1.1, 1.05, 1.1, 1.8, 2.8, 5.5, 6.5])
    n_half = 72  # columns from 0 to π
    s = graded(n_half, knots / np.pi, spacing) * np.pi
    half = s[1:-1]
    phis = np.concatenate([-s[-1:], -half[::-1], [0.0], half])
    return phis


# rows per anchor segment and their grading (relative spacing at normalised arc length knots)
ROW_SEGMENTS = (
    # (n_rows, knots, spacing)         crown -> 0.075 (scalp)
    (14, (0.0, 0.6, 1.0), (1.6, 1.3, 0.7)),
    # 0.075 -> 0.028 (forehead)
    (16, (0.0, 1.0), (1.0, 0.8)),
    # 0.028 -> eye slit (brow, upper lid)
    (16, (0.0, 0.5, 1.0), (1.0, 0.75, 0.55)),
    # eye slit -> mouth slit (lower lid, cheek, nose, upper lip)
    (48, (0.0, 0.12, 0.3, 0.8, 1.0), (0.55, 0.8, 1.0, 0.85, 0.55)),
    # mouth slit -> neck base (lower lip, chin, under-chin, neck)
    (56, (0.0, 0.08, 0.25, 0.45, 1.0), (0.5, 0.8, 1.1, 1.6, 2.8)),
)


def profile_curve(phi: float, res: float = 0.0019):
    """The outer zero contour of the head in the half-plane at azimuth ``phi``: (N, 2) of (ρ, y),
    ordered from the crown down to ``NECK_BASE_Y``."""
    import contourpy

    rho = np.arange(0.0, 0.150, res)
    ys = np.arange(NECK_BASE_Y - 0.006, CROWN_Y + 0.012, res)
    R, Y = np.meshgrid(rho, ys)
    F = head_sdf(half_plane_points(R, Y, phi))
    lines = contourpy.contour_generator(rho, ys, F).lines(0.0)
    best = None
    for ln in lines:
        ln = np.asarray(ln)
        # the profile starts on the axis at the crown
        ends = [ln[0], ln[-1]]
        top = [e for e in ends if e[0] < 2 * res and e[1] > 0.05]
        if top:
            if np.allclose(ln[-1], top[0]):
                ln = ln[::-1]
            if best is None or len(ln) > len(best):
                best = ln
    if best is None:
        raise RuntimeError(f"no head profile found at phi={phi}")
    # cut at the neck base
    below = np.nonzero(best[:, 1] < NECK_BASE_Y)[0]
    if len(below):
        k = below[0]
        a, b = best[k - 1], best[k]
        t = (NECK_BASE_Y - a[1]) / (b[1] - a[1])
        best = np.vstack([best[:k], a + t * (b - a)])
    best[0, 0] = 0.0
    return best


def _refine(rho, y, phi, fixed_y=None, iters=4):
    """Newton-project half-plane points onto the zero set (keeping y where ``fixed_y``)."""
    c, s = np.cos(phi), np.sin(phi)
    for _ in range(iters):
        p = half_plane_points(rho, y, phi)
        f = head_sdf(p)
        g = sdf_gradient(p)
        gr = g[..., 0] * s + g[..., 2] * c
        gy = g[..., 1]
        if fixed_y is not None:
            gy = np.where(fixed_y, 0.0, gy)
        n2 = gr * gr + gy * gy + 1e-20
        rho = rho - f * gr / n2
        y = y - f * gy / n2
    return rho, y


def _arc(curve):
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(curve, axis=0), axis=1))])


def _first_crossing(curve, s, level):
    k = np.nonzero(curve[:, 1] <= level)[0][0]
    a, b = curve[k - 1], curve[k]
    t = (a[1] - level) / (a[1] - b[1])
    return s[k - 1] + t * (s[k] - s[k - 1])


def row_fractions():
    """Per segment: positions in [0, 1] of its rows (first and last are the anchors)."""
    return [graded(n, k, sp) for (n, k, sp) in ROW_SEGMENTS]


def column_profile(phi: float):
    """Profile polyline (M, 2) of (ρ, y), its arc length (M,), and the arc length of its rows (by
    the row fractions between the anchors; crown excluded, neck base included), plus the indices
    of the anchor rows."""
    curve = profile_curve(phi)
    s = _arc(curve)
    anchors = [0.0] + [_first_crossing(curve, s, a) for a in ANCHORS_Y] + [s[-1]]
    pts = []
    anchor_rows = []
    for seg, fr in enumerate(row_fractions()):
        s0, s1 = anchors[seg], anchors[seg + 1]
        pts.append((s0 + fr * (s1 - s0))[1:])  # a segment's first row is the previous one's last
        anchor_rows.append(sum(len(q) for q in pts) - 1)
    return curve, s, np.concatenate(pts), anchor_rows


def project_to_surface(P, keep_y=None, iters=2):
    """Newton-project points onto the head's zero set; rows flagged in ``keep_y`` move in x-z only."""
    P = P.copy()
    for _ in range(iters):
        f = head_sdf(P)
        g = sdf_gradient(P)
        if keep_y is not None:
            g[keep_y, 1] = 0.0
        P -= (f / np.maximum(np.einsum("...k,...k->...", g, g), 1e-20))[..., None] * g
    return P


def _relax_free(P, crown, fixed_rows, region, iters=30, damping=0.55):
    """Tangential, weighted-Laplacian relaxation of the (R, C) grid ``P`` on the SDF surface.

    Edge weights are 1/h² of the initial median row / column spacings, so the designed grading
    survives; nodes of ``fixed_rows`` keep their height (the slits stay horizontal); the last row
    (neck base) and nodes outside ``region`` (R, C) do not move. Left-right symmetry is enforced."""
    R, C = P.shape[:2]
    Pc = np.concatenate([crown[None, None].repeat(C, 1), P], 0)
    hr = np.median(np.linalg.norm(np.diff(Pc, axis=0), axis=2), axis=1)
    hc = np.median(np.linalg.norm(P - np.roll(P, -1, axis=1), axis=2), axis=0)
    wr = 1.0 / hr ** 2
    wc = 1.0 / hc ** 2
    w_up = wr[:, None, None]
    w_dn = np.concatenate([wr[1:], [0.0]])[:, None, None]
    w_l = np.roll(wc, 1)[None, :, None]
    w_r = wc[None, :, None]
    wsum = w_up + w_dn + w_l + w_r
    keep_y = np.zeros((R, C), bool)
    keep_y[list(fixed_rows)] = True
    move = region.copy()
    move[R - 1] = False
    mirror = (C - np.arange(C)) % C   # column j <-> column C - j (0 and C/2 are the midline)
    idx = np.nonzero(move)
    ky = keep_y[idx]
    for _ in range(iters):
        up = np.concatenate([crown[None, None].repeat(C, 1), P[:-1]], 0)
        down = np.concatenate([P[1:], P[-1:]], 0)
        T = (w_up * up + w_dn * down + w_l * np.roll(P, 1, axis=1) + w_r * np.roll(P, -1, axis=1)) / wsum
        Q = P[idx]
        D = damping * (T[idx] - Q)
        g = sdf_gradient(Q, f0=head_sdf(Q))
        n = g / np.linalg.norm(g, axis=1, keepdims=True)
        D -= np.einsum("ij,ij->i", D, n)[:, None] * n
        D[ky, 1] = 0.0
        Q = Q + D
        f = head_sdf(Q)
        g2 = g.copy()
        g2[ky, 1] = 0.0
        Q -= (f / np.maximum(np.einsum("ij,ij->i", g2, g), 1e-20))[:, None] * g2
        P[idx] = Q
        # symmetry
        half = P[:, 1:C // 2]
        P[:, mirror[1:C // 2]] = half * np.array([-1.0, 1.0, 1.0])
        P[:, 0, 0] = 0.0
        P[:, C // 2, 0] = 0.0
    return P


@dataclass
class Slit:
    """A cut along grid row ``row`` between columns ``c0`` and ``c1`` (column indices, c0 < c1,
    not wrapping). ``upper`` / ``lower``: vertex ids of the inner vertices (upper side = the
    original grid vertices, lower side = duplicates), ``corners`` = (vertex at c0, vertex at c1)."""
    name: str
    row: int
    c0: int
    c1: int
    upper: np.ndarray
    lower: np.ndarray
    corners: tuple


@dataclass
class SkinGrid:
    """The rest (lips closed, lids shut) skin mesh and its grid structure."""
    vertices: np.ndarray          # (V, 3)
    faces: np.ndarray             # (F, 3) int32, outward (counter-clockwise seen from outside)
    phis: np.ndarray              # (C,) column azimuths
    n_rows: int
    grid_index: np.ndarray        # (R, C) vertex id of each grid node (upper side at slits)
    vertex_rc: np.ndarray         # (V, 2) float (row, col) of each vertex; pole -> (-1, 0), cap centre -> (R, 0)
    lower_side: np.ndarray        # (V,) bool: duplicate vertex on the lower side of a slit
    slits: dict = field(default_factory=dict)
    anchor_rows: list = field(default_factory=list)
    pole: int = 0
    cap_centre: int = -1
    row_arc: np.ndarray = None    # (R,) arc length of each row along the front meridian (φ = 0)


def build_skin_grid() -> SkinGrid:
    """Build the rest skin (deterministic; a few seconds)."""
    phis = column_angles()
    C = len(phis)
    cols = []
    anchor_rows = None
    # the head is left-right symmetric: slice |φ| once (mirrored by the sign of sin φ)
    by_phi = {}
    for phi in np.unique(np.round(np.abs(phis), 12)):
        by_phi[float(phi)] = column_profile(float(phi))
    profiles, S = [], []
    for phi in phis:
        curve, s_arc, rows, anchor_rows = by_phi[float(np.round(abs(phi), 12))]
        profiles.append((curve, s_arc))
        S.append(rows)
    S = np.stack(S, 1)
    R = S.shape[0]
    crown = np.array([0.0, _crown_y(), AXIS_Z])
    P = np.zeros((R, C, 3))
    for j, phi in enumerate(phis):
        curve, s_arc = profiles[j]
        P[:, j] = half_plane_points(np.interp(S[:, j], s_arc, curve[:, 0]),
                                    np.interp(S[:, j], s_arc, curve[:, 1]), abs(phi))
        if phi < 0:
            P[:, j, 0] *= -1.0
    keep_y = np.zeros((R, C), bool)
    keep_y[list(anchor_rows)] = True
    P = project_to_surface(P.reshape(-1, 3), keep_y.ravel(), iters=3).reshape(R, C, 3)
    # relax the face (front, above the neck) so grid lines flow round the nose, lips and eyes
    region = (np.abs(phis)[None, :] < np.radians(75)) & (P[..., 1] > -0.125) & (P[..., 1] < 0.09)
    P = _relax_free(P, crown, anchor_rows, region)

    verts = [crown[None]]
    grid_index = np.arange(R * C).reshape(R, C) + 1
    verts.append(P.reshape(-1, 3))
    nv = 1 + R * C
    vertex_rc = [np.array([[-1.0, 0.0]])]
    rr, cc = np.meshgrid(np.arange(R), np.arange(C), indexing="ij")
    vertex_rc.append(np.stack([rr.ravel(), cc.ravel()], 1).astype(float))

    # slits: duplicate inner vertices; remember which (row, col) are on the lower side
    slits = {}
    dup_of = {}
    eye_row = anchor_rows[2]
    mouth_row = anchor_rows[3]

    def add_slit(name, row, c0, c1):
        nonlocal nv
        inner = np.arange(c0 + 1, c1)
        upper = grid_index[row, inner]
        lower = np.arange(nv, nv + len(inner))
        nv += len(inner)
        verts.append(P[row, inner])
        vertex_rc.append(np.stack([np.full(len(inner), row, float), inner.astype(float)], 1))
        for c, v in zip(inner, lower):
            dup_of[(row, int(c))] = int(v)
        slits[name] = Slit(name, row, c0, c1, upper, lower,
                           (int(grid_index[row, c0]), int(grid_index[row, c1])))

    mj = _nearest_col(phis, P[mouth_row], +MOUTH_HALF_WIDTH)
    mi_ = _nearest_col(phis, P[mouth_row], -MOUTH_HALF_WIDTH)
    add_slit("mouth", mouth_row, mi_, mj)
    for side, sgn in (("eye_left", 1.0), ("eye_right", -1.0)):
        ce = EYE_CENTRE * np.array([sgn, 1, 1])
        ends = []
        for az in EYE_SLIT_AZ:
            # medial azimuth is towards the nose: negative for the left eye means towards -X
            x = ce[0] + sgn * LID_RADIUS * np.sin(az)
            ends.append(_nearest_col(phis, P[eye_row], x, near=ce))
        add_slit(side, eye_row, min(ends), max(ends))

    # faces
    faces = []
    # crown fan
    for j in range(C):
        a, b = grid_index[0, j], grid_index[0, (j + 1) % C]
        faces.append((0, a, b))

    def vid(r, c, below):
        """Vertex at (r, c) as seen from a quad lying below (below=True) row r."""
        if below and (r, c) in dup_of:
            return dup_of[(r, c)]
        return grid_index[r, c]

    for r in range(R - 1):
        for j in range(C):
            j2 = (j + 1) % C
            a = vid(r, j, True)
            b = vid(r, j2, True)
            c = grid_index[r + 1, j2]
            d = grid_index[r + 1, j]
            # split along the shorter diagonal
            pa, pb, pc, pd = (P[r, j], P[r, j2], P[r + 1, j2], P[r + 1, j])
            if np.linalg.norm(pa - pc) <= np.linalg.norm(pb - pd):
                faces.append((a, d, c))
                faces.append((a, c, b))
            else:
                faces.append((a, d, b))
                faces.append((b, d, c))
    # neck cap: a centre vertex and a fan (the cap is flat, at NECK_BASE_Y)
    cap = nv
    ring = P[R - 1]
    verts.append(np.array([[0.0, NECK_BASE_Y, float(ring[:, 2].mean())]]))
    vertex_rc.append(np.array([[float(R), 0.0]]))
    nv += 1
    for j in range(C):
        a, b = grid_index[R - 1, j], grid_index[R - 1, (j + 1) % C]
        faces.append((cap, b, a))

    V = np.concatenate(verts, 0)
    F = np.asarray(faces, np.int64)
    F = _orient_outwards(V, F)
    lower_side = np.zeros(len(V), bool)
    for s in slits.values():
        lower_side[s.lower] = True
    front = P[:, np.argmin(np.abs(phis))]
    row_arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(front, axis=0), axis=1))])
    row_arc += np.linalg.norm(front[0] - crown)
    return SkinGrid(V, F.astype(np.int32), phis, R, grid_index, np.concatenate(vertex_rc, 0),
                    lower_side, slits, list(anchor_rows), 0, cap, row_arc)


def _crown_y():
    # where the axis leaves the head
    ys = np.linspace(0.05, CROWN_Y + 0.03, 2000)
    f = head_sdf(np.stack([np.zeros_like(ys), ys, np.full_like(ys, AXIS_Z)], 1))
    k = np.nonzero(f > 0)[0][0]
    t = -f[k - 1] / (f[k] - f[k - 1])
    return ys[k - 1] + t * (ys[k] - ys[k - 1])


def _nearest_col(phis, row_pts, x, near=None):
    """Column whose vertex on this row has x closest to ``x`` (front half, optionally near a point)."""
    cand = np.nonzero(np.abs(phis) < np.pi / 2)[0]
    cost = np.abs(row_pts[cand, 0] - x)
    if near is not None:
        cost = cost + 10.0 * np.maximum(0, -(row_pts[cand, 2] - (near[2] - 0.02)))
    return int(cand[np.argmin(cost)])


def _orient_outwards(V, F):
    """Make the winding give outward normals (signed volume positive)."""
    a, b, c = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    vol = np.einsum("ij,ij->i", a, np.cross(b, c)).sum()
    return F if vol > 0 else F[:, [0, 2, 1]]


# --------------------------------------------------------------------------------------------
# caching
# --------------------------------------------------------------------------------------------
def grid_to_arrays(g: SkinGrid) -> dict:
    out = dict(vertices=g.vertices, faces=g.faces, phis=g.phis, n_rows=np.array(g.n_rows),
               grid_index=g.grid_index, vertex_rc=g.vertex_rc, lower_side=g.lower_side,
               anchor_rows=np.array(g.anchor_rows), pole=np.array(g.pole),
               cap_centre=np.array(g.cap_centre), row_arc=g.row_arc,
               slit_names=np.array(list(g.slits)))
    for k, s in g.slits.items():
        out[f"slit_{k}_meta"] = np.array([s.row, s.c0, s.c1, s.corners[0], s.corners[1]])
        out[f"slit_{k}_upper"] = s.upper
        out[f"slit_{k}_lower"] = s.lower
    return out


def grid_from_arrays(d: dict) -> SkinGrid:
    slits = {}
    for k in [str(n) for n in d["slit_names"]]:
        m = d[f"slit_{k}_meta"]
        slits[k] = Slit(k, int(m[0]), int(m[1]), int(m[2]), d[f"slit_{k}_upper"], d[f"slit_{k}_lower"],
                        (int(m[3]), int(m[4])))
    return SkinGrid(d["vertices"], d["faces"], d["phis"], int(d["n_rows"]), d["grid_index"],
                    d["vertex_rc"], d["lower_side"], slits, [int(a) for a in d["anchor_rows"]],
                    int(d["pole"]), int(d["cap_centre"]), d["row_arc"])


def load_skin_grid() -> SkinGrid:
    """:func:`build_skin_grid`, cached on disk (see :mod:`.cache`)."""
    from . import cache

    return grid_from_arrays(cache.cached(cache.key("skin-grid"), lambda: grid_to_arrays(build_skin_grid())))
