"""The neutral's mouth and eyes found in its images, for the proposed template (:mod:`.template_proposal`).

Everything here reads the lighting-independent diffuse proxy of the neutral, nothing else:

* **lips**: pixels whose chromaticity is redder than the skin's median by ``lip_chroma`` (the lips'
  colour, whatever the skin's); the largest such blob on the face is the mouth; the **mouth line** (a
  closed mouth's lip margins) is the darkest row of the blob in each of its columns (the shadow between
  the lips), its ends the mouth corners.
* **eyes**: the eye opening is the white of the eye (saturation well below the skin's, brightness near the
  skin's: eyebrows and hair are as grey but darker) closed over the iris; its top and bottom edges in
  each column are the upper and lower **eyelid margins**, its ends the corners; the **iris** is the
  opening's dark pixels, its centre their centroid, its radius half their width.
* **lifting to 3-D** (:func:`lift_curve`): one view (the one facing the feature most directly) gives the
  rays; along each ray the depth that brings the point nearest to the feature's curve in the other views
  (truncated at ``trunc_px``) wins, regularised towards a prior depth (the dots' surface for the mouth,
  the eyeball for the lids). A curve along an epipolar line constrains nothing and the prior decides.
"""
from __future__ import annotations

import numpy as np

LIP_CHROMA = 0.03


def _chroma(img: np.ndarray) -> np.ndarray:
    return img / np.maximum(img.sum(-1, keepdims=True), 1e-9)


def _largest(mask: np.ndarray, min_px: int = 4, keep: int = 1) -> list:
    """The ``keep`` largest connected components (bool masks) of ``mask`` with at least ``min_px`` pixels."""
    from scipy.ndimage import label

    lab, n = label(mask)
    if n == 0:
        return []
    sizes = np.bincount(lab.ravel())[1:]
    order = np.argsort(sizes)[::-1]
    return [lab == (k + 1) for k in order[:keep] if sizes[k] >= min_px]


def lip_blob(img: np.ndarray, face: np.ndarray, lip_chroma: float = LIP_CHROMA) -> np.ndarray | None:
    ch = _chroma(img.astype(np.float64))
    skin = np.median(ch[face], axis=0)
    red = face & ((ch[..., 0] - skin[0]) > lip_chroma) & ((skin[1] - ch[..., 1]) > 0.4 * lip_chroma)
    comps = _largest(red, min_px=6)
    return comps[0] if comps else None


def lips_region(img: np.ndarray, face: np.ndarray, lip_chroma: float = LIP_CHROMA) -> np.ndarray | None:
    """Both lips (an open mouth parts them into two blobs): the largest red blob and every other at least
    a third its size."""
    ch = _chroma(img.astype(np.float64))
    skin = np.median(ch[face], axis=0)
    red = face & ((ch[..., 0] - skin[0]) > lip_chroma) & ((skin[1] - ch[..., 1]) > 0.4 * lip_chroma)
    comps = _largest(red, min_px=6, keep=3)
    if not comps:
        return None
    big = comps[0].sum()
    out = comps[0].copy()
    for c in comps[1:]:
        if c.sum() >= big / 3:
            out |= c
    return out


def mouth_corners(region: np.ndarray) -> np.ndarray:
    """(2, 2) the lips' two ends (u, v), left then right: the mean row of the end columns' lip pixels."""
    cols = np.flatnonzero(region.any(0))
    out = []
    for u, side in ((cols[0], -0.5), (cols[-1], 0.5)):
        rows = np.flatnonzero(region[:, u])
        out.append((u + side, rows.mean()))
    return np.array(out, np.float64)


def mouth_line(img: np.ndarray, blob: np.ndarray) -> np.ndarray | None:
    """(n, 2) pixels (u, v) of the mouth line, one per column of the lip blob, left to right."""
    from scipy.ndimage import gaussian_filter1d

    lum = gaussian_filter1d(img.astype(np.float64).sum(-1), 0.7, axis=0)
    cols = np.flatnonzero(blob.any(0))
    pts = []
    for u in cols:
        rows = np.flatnonzero(blob[:, u])
        if len(rows) < 2:
            pts.append((u, rows.mean()))
            continue
        inner = rows[(rows > rows.min()) & (rows < rows.max())] if len(rows) > 3 else rows
        r = inner[np.argmin(lum[inner, u])]
        # sub-pixel: the parabola through the darkest row and its neighbours
        if 0 < r < len(lum) - 1:
            a, b, c = lum[r - 1, u], lum[r, u], lum[r + 1, u]
            den = a - 2 * b + c
            r = r + (0.5 * (a - c) / den if den > 1e-12 else 0.0)
        pts.append((u, float(r)))
    if len(pts) < 3:
        return None
    P = np.array(pts, np.float64)
    # a closed mouth's line is smooth: a median over 3 columns removes single-column jumps
    from scipy.ndimage import median_filter

    P[:, 1] = median_filter(P[:, 1], size=3, mode="nearest")
    return P


def eye_openings(img: np.ndarray, face: np.ndarray, below_row: float | None, keep: int = 2) -> list:
    """Up to ``keep`` eye openings (bool masks): white blobs (closed across the iris) with the dark iris
    pixels between their ends, above ``below_row``."""
    from scipy.ndimage import binary_closing, binary_fill_holes

    x = img.astype(np.float64)
    mx, mn = x.max(-1), x.min(-1)
    sat = (mx - mn) / np.maximum(mx, 1e-9)
    lum = x.sum(-1)
    skin_sat, skin_lum = np.median(sat[face]), np.median(lum[face])
    white = face & (sat < 0.45 * skin_sat) & (lum > 0.55 * skin_lum)
    dark = face & (lum < 0.45 * skin_lum)
    if below_row is not None:
        white[int(max(0, np.floor(below_row))):] = False
    # the iris splits the white in two: close across it (an iris is at most ~0.2 of the face's width)
    cols = np.flatnonzero(face.any(0))
    span = int(max(3, round(0.06 * (cols.max() - cols.min() + 1)))) if cols.size else 3
    closed = binary_closing(white | (dark & binary_closing(white, np.ones((1, 2 * span + 1)))),
                            np.ones((1, 2 * span + 1)))
    out = []
    for comp in _largest(closed, min_px=3, keep=2 * keep + 2):
        rows, cols = np.nonzero(comp)
        if rows.max() - rows.min() > 0.8 * (cols.max() - cols.min()) + 2:   # an eye is wider than tall
            continue
        if not (comp & white).any():
            continue
        r0, r1, c0, c1 = rows.min(), rows.max(), cols.min(), cols.max()
        box = np.zeros_like(comp)
        box[max(0, r0 - 1):r1 + 2, c0:c1 + 1] = True
        opening = binary_fill_holes(comp | (dark & box & binary_closing(comp | dark, np.ones((3, 3)))))
        out.append(opening)
        if len(out) == keep:
            break
    return out


def opening_edges(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Upper and lower edges (n, 2) (u, v) of an opening, left corner to right corner."""
    cols = np.flatnonzero(mask.any(0))
    top, bot = [], []
    for u in cols:
        rows = np.flatnonzero(mask[:, u])
        top.append((u, rows.min() - 0.5))
        bot.append((u, rows.max() + 0.5))
    top, bot = np.array(top, np.float64), np.array(bot, np.float64)
    left = np.array([cols[0] - 0.5, 0.5 * (top[0, 1] + bot[0, 1])])
    right = np.array([cols[-1] + 0.5, 0.5 * (top[-1, 1] + bot[-1, 1])])
    return (np.vstack([left, top, right]), np.vstack([left, bot, right]))


def iris_of(img: np.ndarray, opening: np.ndarray) -> tuple[np.ndarray, float] | None:
    """Centre (u, v) and radius (px) of the iris in an eye opening: its darker half's centroid and width."""
    lum = img.astype(np.float64).sum(-1)
    vals = lum[opening]
    if vals.size < 3:
        return None
    dark = opening & (lum <= np.percentile(vals, 45))
    rows, cols = np.nonzero(dark)
    if len(rows) == 0:
        return None
    w = lum[dark].max() - lum[dark] + 1e-6
    c = np.array([np.sum(cols * w) / w.sum(), np.sum(rows * w) / w.sum()])
    r = 0.5 * (cols.max() - cols.min() + 1)
    return c, float(r)


def polyline_distance(P: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """Distance (n,) of points P (n, 2) from the polyline (m, 2)."""
    p, q = poly[:-1], poly[1:]
    d = q - p
    t = np.clip(np.einsum("nij,ij->ni", P[:, None] - p[None], d) / np.maximum((d * d).sum(1), 1e-12), 0, 1)
    proj = p[None] + t[..., None] * d[None]
    return np.sqrt(np.min(np.sum((P[:, None] - proj) ** 2, -1), 1))


def resample(poly: np.ndarray, n: int) -> np.ndarray:
    """``n`` points evenly spaced along a polyline (its ends kept)."""
    seg = np.linalg.norm(np.diff(poly, axis=0), axis=1)
    s = np.concatenate([[0], np.cumsum(seg)])
    t = np.linspace(0, s[-1], n)
    return np.stack([np.interp(t, s, poly[:, k]) for k in range(poly.shape[1])], 1)


def lift_curve(cams, master: str, uv: np.ndarray, prior_depth: np.ndarray, curves: dict,
               span: float = 0.02, trunc_px: float = 3.0, prior_weight: float = 0.2) -> np.ndarray:
    """3-D points (n, 3) on ``master``'s rays through ``uv`` (n, 2): the depth within ``prior_depth`` ±
    ``span`` (metres, camera depth) that brings them nearest (px, truncated) to ``curves`` {camera: (m, 2)}
    of the other views, plus ``prior_weight`` px² per mm² of departure from the prior."""
    cam = next(c for c in cams if c.name == master)
    o, d = cam.pixel_rays(np.asarray(uv, np.float64).reshape(-1, 2))
    d = np.asarray(d).reshape(-1, 3)
    o = np.broadcast_to(np.asarray(o, np.float64).reshape(-1, 3), d.shape)
    oz = (o @ cam.R.T + cam.t)[:, 2]
    dz = d @ cam.R[2]
    steps = np.linspace(-span, span, 81)
    cost = np.zeros((len(steps), len(uv)))
    for k, s in enumerate(steps):
        X = o + d * ((prior_depth + s - oz) / dz)[:, None]
        cost[k] = prior_weight * (s * 1000) ** 2
        for c in cams:
            if c.name == master or c.name not in curves:
                continue
            p, z = c.project(X)
            dist = polyline_distance(np.nan_to_num(p, nan=-1e6), curves[c.name])
            cost[k] += np.minimum(dist, trunc_px) ** 2
    best = steps[np.argmin(cost, axis=0)]
    return o + d * ((prior_depth + best - oz) / dz)[:, None]


def depth_from_points(cam, P: np.ndarray, uv: np.ndarray, k: int = 6, triangles: np.ndarray | None = None) -> np.ndarray:
    """Camera depth (n,) at pixels ``uv`` (n, 2) on the surface of the 3-D points P (N, 3) seen by ``cam``:
    interpolated in the nearest triangle of ``triangles`` (F, 3) that covers the pixel, else from the
    ``k`` nearest projections (inverse-distance weights; sparse points mix the far side of the face in)."""
    from scipy.spatial import cKDTree

    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    p, z = cam.project(P)
    ok = np.isfinite(p).all(1) & (z > 0)
    tree = cKDTree(p[ok])
    dist, idx = tree.query(uv, min(k, int(ok.sum())))
    w = 1.0 / np.maximum(dist, 0.5) ** 2
    out = np.sum(w * z[ok][idx], 1) / w.sum(1)
    if triangles is None or len(triangles) == 0:
        return out
    F = np.asarray(triangles, np.int64)
    F = F[ok[F].all(1)]
    a, b, c = p[F[:, 0]], p[F[:, 1]], p[F[:, 2]]
    den = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1])
    good = np.abs(den) > 1e-9
    F, a, b, c, den = F[good], a[good], b[good], c[good], den[good]
    for i, q in enumerate(uv):
        w1 = ((b[:, 0] - q[0]) * (c[:, 1] - q[1]) - (c[:, 0] - q[0]) * (b[:, 1] - q[1])) / den
        w2 = ((c[:, 0] - q[0]) * (a[:, 1] - q[1]) - (a[:, 0] - q[0]) * (c[:, 1] - q[1])) / den
        w3 = 1.0 - w1 - w2
        hit = (w1 >= 0) & (w2 >= 0) & (w3 >= 0)
        if hit.any():
            zz = w1[hit] * z[F[hit, 0]] + w2[hit] * z[F[hit, 1]] + w3[hit] * z[F[hit, 2]]
            out[i] = float(zz.min())          # the front-most surface along the ray
    return out


def ray_sphere_depth(cam, uv: np.ndarray, centre: np.ndarray, radius: float) -> np.ndarray:
    """Camera depth (n,) of the near intersection of the rays through ``uv`` with a sphere (the centre's
    depth minus the radius where a ray misses)."""
    o, d = cam.pixel_rays(np.asarray(uv, np.float64).reshape(-1, 2))
    d = np.asarray(d).reshape(-1, 3)
    o = np.broadcast_to(np.asarray(o, np.float64).reshape(-1, 3), d.shape)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    oc = o - centre
    b = np.einsum("ij,ij->i", oc, d)
    disc = b ** 2 - (np.einsum("ij,ij->i", oc, oc) - radius ** 2)
    t = -b - np.sqrt(np.maximum(disc, 0.0))
    X = o + d * t[:, None]
    z = (X @ cam.R.T + cam.t)[:, 2]
    zc = float((cam.R @ centre + cam.t)[2]) - radius
    return np.where(disc > 0, z, zc)


def _facing(cams, names: list, point: np.ndarray, forward: np.ndarray) -> list:
    """``names`` ordered by how directly their camera looks at ``point`` along ``forward``."""
    def cos(n):
        c = next(c for c in cams if c.name == n)
        d = c.centre - point
        return float(d @ forward / np.linalg.norm(d))
    return sorted(names, key=cos, reverse=True)


def find_face(cams, images: dict, P: np.ndarray, n_lip: int = 15, n_lid: int = 8, eye_radius: float = 0.012,
              triangles: np.ndarray | None = None) -> dict:
    """The mouth and eyes of the neutral: {"mouth": {"line" (n_lip, 3), "views", "curves"} | None,
    "eyes": {"L"/"R": {"iris" (3,), "iris_radius", "upper" (n_lid, 3), "lower" (n_lid, 3), "views"}},
    "notes": [...]} from the diffuse proxies ``images`` {camera: (H, W, 3)} and the dots P (N, 3)
    (the prior surface, meshed by ``triangles`` when given). Left and right are the subject's (+X is the
    subject's left)."""
    from ..geometry.triangulate import triangulate
    from ..registration.dots import face_mask

    names = [c.name for c in cams]
    cam_of = {c.name: c for c in cams}
    notes = []
    faces = {n: face_mask(images[n]) for n in names}
    out = {"mouth": None, "eyes": {}, "notes": notes}
    # ---------------------------------------------------------------- mouth
    blobs = {n: lip_blob(images[n], faces[n]) for n in names}
    lines = {}
    for n, b in blobs.items():
        if b is not None:
            ln = mouth_line(images[n], b)
            if ln is not None:
                lines[n] = ln
    top_row = {}
    if lines:
        master = max(lines, key=lambda n: np.ptp(lines[n][:, 0]))
        uv = resample(lines[master], n_lip)
        depth = depth_from_points(cam_of[master], P, uv, triangles=triangles)
        X = lift_curve(cams, master, uv, depth, {n: ln for n, ln in lines.items() if n != master})
        if X[0, 0] > X[-1, 0]:
            X = X[::-1]
        out["mouth"] = {"line": X, "master": master, "views": sorted(lines), "curves": lines}
        top_row = {n: float(np.flatnonzero(b.any(1)).min()) for n, b in blobs.items() if b is not None}
    else:
        notes.append("no lips found (no blob redder than the skin): no lip margins, no teeth")
    # ---------------------------------------------------------------- eyes
    openings = {n: eye_openings(images[n], faces[n], top_row.get(n)) for n in names}
    centre = P.mean(0)
    fwd = np.array([0.0, 0.0, 1.0])
    # the views that show two eyes, most frontal first: left / right by the image direction of +X
    both = [n for n in _facing(cams, names, centre, fwd) if len(openings[n]) == 2]
    per_eye = {"L": {}, "R": {}}
    for n in both:
        cam = cam_of[n]
        du = cam.project(np.array([centre + [0.03, 0, 0], centre - [0.03, 0, 0]]))[0]
        sgn = np.sign(du[0, 0] - du[1, 0]) or 1.0
        ms = sorted(openings[n], key=lambda m: sgn * np.nonzero(m)[1].mean())
        per_eye["R"][n], per_eye["L"][n] = ms[0], ms[1]
    for side in ("L", "R"):
        irises = {n: iris_of(images[n], m) for n, m in per_eye[side].items()}
        irises = {n: v for n, v in irises.items() if v is not None}
        X = None
        if len(irises) >= 2:
            uvs = np.full((len(cams), 1, 2), np.nan)
            for n, (c, _) in irises.items():
                uvs[names.index(n), 0] = c
            tr = triangulate(cams, uvs, max_error=3.0)
            if tr.ok[0]:
                X = tr.points[0]
        if X is None:
            notes.append(f"eye {side}: its iris was not found in two views facing the face; no eye, no lids")
            continue
        # the views that show only one eye: the opening nearest the iris' projection
        for n in names:
            if n in per_eye[side] or not openings[n]:
                continue
            p = cam_of[n].project(X[None])[0][0]
            if not np.isfinite(p).all():
                continue
            dist = [np.min(np.hypot(*(np.stack(np.nonzero(m)[::-1], 1) - p).T)) for m in openings[n]]
            k = int(np.argmin(dist))
            if dist[k] < 2.0:
                per_eye[side][n] = openings[n][k]
        fp = np.linalg.norm(X - cam_of[next(iter(irises))].centre) / cam_of[next(iter(irises))].K[0, 0]
        r_iris = float(np.clip(np.median([r for _, r in irises.values()]) * fp, 0.0045, 0.0075))
        depth_c = np.sqrt(max(eye_radius ** 2 - r_iris ** 2, 1e-6))
        eye_c = X - depth_c * fwd
        master = _facing(cams, list(per_eye[side]), X, fwd)[0]
        edges = {n: opening_edges(m) for n, m in per_eye[side].items()}
        up_uv, lo_uv = edges[master]
        cam = cam_of[master]
        lid = {}
        for key, poly, j in (("upper", up_uv, 0), ("lower", lo_uv, 1)):
            uv = resample(poly, n_lid)
            prior = ray_sphere_depth(cam, uv, eye_c, eye_radius + 5e-4)
            curves = {n: e[j] for n, e in edges.items() if n != master}
            lid[key] = lift_curve(cams, master, uv, prior, curves, span=0.006, prior_weight=0.5)
        corner_a = 0.5 * (lid["upper"][0] + lid["lower"][0])
        corner_b = 0.5 * (lid["upper"][-1] + lid["lower"][-1])
        for key in ("upper", "lower"):
            lid[key][0], lid[key][-1] = corner_a, corner_b
            if lid[key][0, 0] > lid[key][-1, 0]:
                lid[key] = lid[key][::-1]
        out["eyes"][side] = {"iris": X, "iris_radius": r_iris, "iris_depth": float(depth_c), "centre": eye_c,
                             "radius": eye_radius, "upper": lid["upper"], "lower": lid["lower"],
                             "views": sorted(per_eye[side]), "iris_views": sorted(irises)}
    return out
