"""Dots followed through the video and triangulated per frame; head pose; the template's other vertices.

:class:`DotTracker` runs frame by frame (paper §6.4: "Tracking the dots from the different cameras
allows us to triangulate 3D motion data"):

1. **prediction** of every dot's 3-D position from the previous frames: constant velocity from
   its last two tracked positions (time gaps from dropped frames included); a dot unseen for more
   than ``max_gap`` frames is *lost* and predicted from the motion of its tracked neighbours
   instead (a moving-least-squares affine map of the reference positions onto this frame's
   predictions, :func:`mifacerf.geometry.schaefer2006.mls_affine`);
2. **visibility** of the predicted positions in every camera, ray-traced against the predicted
   template mesh (occlusion by the nose, the head's turn) with a facing test;
3. **search** in every usable camera (:mod:`.health`) about the projected prediction — a small
   window for tracked dots, a wider one and a higher strength threshold for the re-detection of
   lost dots; one image dot per dot (:func:`.track2d.resolve_conflicts`, tracked dots first);
4. **triangulation** (:func:`mifacerf.geometry.triangulate.triangulate`, worst view dropped
   while views disagree by more than ``max_reproj_px``), gated against the prediction. A dot
   triangulated from ≥ 2 consistent views is *tracked* (status 1) in that frame; any other is
   *untracked* (status 0) and placed from its neighbours.

After the last frame (:func:`finish_dots`): tracked runs are smoothed in time (a Gaussian of
``smooth_sigma`` frames, zero phase; triangulation noise would otherwise flicker through the §5
weights), and every untracked stretch is filled by the neighbours' prediction plus an offset
interpolated between the dot's own tracked positions before and after, so a dot that comes back
does not jump. Head pose per frame: a robust rigid fit of the most rigid dots (forehead, nose,
round the ears) to the reference (:func:`head_poses`).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from ..camera import Camera
from ..registration.snap import dot_graph
from ..geometry.footprint import centre_footprint
from ..geometry.maxima import maxima_points
from ..geometry.rigid import apply as apply_T, robust_rigid
from ..geometry.schaefer2006 import mls_affine
from ..geometry.triangulate import triangulate
from ..geometry.visibility import Visibility
from .track2d import Detector, resolve_conflicts, search


@dataclass
class Options:
    """Tunable parameters of the dot tracker (lengths in pixels, or pixel footprints at the rig centre)."""

    search_px: float = 2.5         #: search radius about a tracked dot's prediction
    redetect_px: float = 4.0       #: ... about a lost dot's prediction from its neighbours
    accept: float = 0.3            #: strength a tracked dot's image dot must reach (1 = a typical dot)
    redetect_accept: float = 0.5   #: ... for re-detecting a lost dot
    max_reproj_px: float = 1.0     #: views must agree to this many pixels
    coherence_px: float = 1.5      #: a dot's step may differ this much from its neighbours' (footprints)
    gate_px: float = 4.0           #: a triangulated dot may lie this far from its prediction (footprints)
    redetect_gate_px: float = 6.0  #: ... for a lost dot
    min_cos: float = 0.15          #: views more oblique than this (cosine) are not searched
    max_gap: int = 3               #: frames a dot may go unseen before it is predicted from its neighbours
    neighbours: int = 12           #: anchors of the neighbour prediction
    smooth_sigma: float = 1.0      #: temporal smoothing of tracked runs (frames; 0 = off)
    dark_ratio: float = 0.25       #: a frame darker than this fraction of the camera's usual level is dark
    init_px: float = 4.0           #: search radius at initialisation (the first frame, at rest)

    def to_dict(self) -> dict:
        return asdict(self)


class DotTracker:
    """Frame-by-frame dot tracking (see the module docstring).

    ``cams``: the performance cameras; ``ref_vertices`` (T, 3): the template at rest (the user's
    template, or a model's registered neutral); ``triangles``: the template's; ``dot_ids`` (D,)
    template ids of the fiducials; ``dot_radius`` metres; ``n_frames``.
    """

    def __init__(self, cams: list[Camera], ref_vertices: np.ndarray, triangles: np.ndarray, dot_ids: np.ndarray,
                 dot_radius: float, n_frames: int, options: Options | None = None):
        self.cams = cams
        self.names = [c.name for c in cams]
        self.opt = options or Options()
        self.V_ref = np.asarray(ref_vertices, np.float64)
        self.F = np.asarray(triangles, np.int64)
        self.dots = np.asarray(dot_ids, np.int64)
        self.X_ref = self.V_ref[self.dots]
        self.dot_radius = float(dot_radius)
        self.fp = centre_footprint(cams)
        self.vis = Visibility(self.F, len(self.V_ref), tol=max(0.5 * self.fp, 5e-4))
        is_dot = np.zeros(len(self.V_ref), bool)
        is_dot[self.dots] = True
        index = np.full(len(self.V_ref), -1)
        index[self.dots] = np.arange(len(self.dots))
        graph = dot_graph(len(self.V_ref), self.F, is_dot)
        self.nbrs = [index[graph[v]] for v in self.dots]   # neighbouring dots (indices into the dots)
        C, D, N = len(cams), len(self.dots), n_frames
        self.X = np.full((N, D, 3), np.nan)
        self.status = np.zeros((N, D), np.int8)
        self.uv = np.full((N, C, D, 2), np.nan, np.float32)
        self.reproj = np.full((N, D), np.nan, np.float32)
        self.redetected = np.zeros((N, D), bool)
        self.detector: Detector | None = None
        self.init_frame: int | None = None
        self.last = np.full(D, -1)   # frame of the last tracked position
        self.prev = np.full(D, -1)   # ... and the one before

    # ----------------------------------------------------------------- helpers
    def mesh(self, Xd: np.ndarray) -> np.ndarray:
        """The template mesh carried onto dot positions ``Xd`` (D, 3) (dots exactly, the rest by MLS)."""
        V = mls_affine(self.X_ref, Xd, self.V_ref, k=self.opt.neighbours)
        V[self.dots] = Xd
        return V

    def from_neighbours(self, anchors: np.ndarray, Xd: np.ndarray, which: np.ndarray) -> np.ndarray:
        """Positions of dots ``which`` carried from the reference by the anchors' motion (anchors: bool (D,))."""
        if anchors.sum() < 4 or not which.any():
            return Xd[which]
        return mls_affine(self.X_ref[anchors], Xd[anchors], self.X_ref[which], k=self.opt.neighbours)

    def _search_camera(self, c: int, strength: np.ndarray, Xhat: np.ndarray, visible: np.ndarray,
                       tracked: np.ndarray, radius_t: float, radius_l: float) -> np.ndarray:
        o = self.opt
        cam = self.cams[c]
        p, _ = cam.project(Xhat)
        found = np.full((len(Xhat), 2), np.nan)
        sel_t = visible & tracked
        sel_l = visible & ~tracked
        cs = self.detector.centroid_sigma
        maxima = maxima_points(np.asarray(strength, np.float32), min(o.accept, o.redetect_accept))
        if sel_t.any():
            found[sel_t] = search(strength, p[sel_t], radius_t, o.accept, cs, maxima)[0]
        if sel_l.any():
            found[sel_l] = search(strength, p[sel_l], radius_l, o.redetect_accept, cs, maxima)[0]
        # one image dot per dot: the closer prediction wins, tracked dots before lost ones
        rank = np.linalg.norm(found - p, axis=1) + np.where(tracked, 0.0, 1e3)
        drop = resolve_conflicts(found, p, 1.0)
        if drop.any():
            # recompute with the ranking that prefers tracked dots
            from scipy.spatial import cKDTree

            idx = np.flatnonzero(np.isfinite(found).all(1))
            drop[:] = False
            for a, b in cKDTree(found[idx]).query_pairs(1.0, output_type="ndarray"):
                i, j = idx[a], idx[b]
                drop[i if rank[i] > rank[j] else j] = True
            found[drop] = np.nan
        return found

    # ----------------------------------------------------------------- frames
    def initialise(self, f: int, images: dict) -> bool:
        """Tune the detector and find every dot near its rest position (frame ``f`` shows the subject at rest)."""
        o = self.opt
        good = [c for c, n in enumerate(self.names) if images.get(n) is not None]
        if len(good) < 2:
            return False
        vis = self.vis(self.V_ref, self.cams, min_cos=0.3)[:, self.dots]
        uvs = {self.names[c]: self.cams[c].project(self.X_ref[vis[c]])[0] for c in good}
        self.detector = Detector.tune({self.names[c]: images[self.names[c]] for c in good}, uvs,
                                      self.dot_radius / self.fp)
        strengths = {c: self.detector.strength(images[self.names[c]], self.names[c]) for c in good}
        # a wide search about the rest positions, a robust rigid fit of what was found (the head may not
        # be exactly where the template was built), then a narrow search about the rigidly moved template
        X = self.X_ref.copy()
        tracked = np.ones(len(X), bool)
        for radius in (o.init_px, 0.6 * o.search_px, 0.6 * o.search_px):
            V = self.mesh(X)
            vis = self.vis(V, self.cams, min_cos=o.min_cos)[:, self.dots]
            uv = np.full((len(self.cams), len(X), 2), np.nan)
            for c in good:
                uv[c] = self._search_camera(c, strengths[c], X, vis[c], tracked, radius, radius)
            tr = triangulate(self.cams, uv, max_error=o.max_reproj_px)
            ok = tr.ok & (tr.max_error <= o.max_reproj_px)
            if ok.sum() < 4:
                return False
            X = apply_T(robust_rigid(self.X_ref[ok], tr.points[ok]), self.X_ref)
        ok &= np.linalg.norm(tr.points - X, axis=1) / self.fp <= o.search_px
        Xf = X.copy()
        Xf[ok] = tr.points[ok]
        self._store(f, Xf, ok, uv, tr)
        self.init_frame = f
        return True

    def _store(self, f, X, ok, uv, tr):
        Xf = X.copy()
        Xf[~ok] = self.from_neighbours(ok, X, ~ok)
        self.X[f] = Xf
        self.status[f] = ok.astype(np.int8)
        used = tr.used & ok[None]
        self.uv[f] = np.where(used[..., None], uv, np.nan).astype(np.float32)
        self.reproj[f] = np.where(ok, tr.error, np.nan)
        self.prev = np.where(ok, self.last, self.prev)
        self.last = np.where(ok, f, self.last)

    def predict(self, f: int) -> tuple[np.ndarray, np.ndarray]:
        """(predicted positions (D, 3), tracked (D,) bool: predicted from the dot's own history)."""
        o = self.opt
        D = len(self.dots)
        last, prev = self.last, self.prev
        age = f - last
        tracked = (last >= 0) & (age <= o.max_gap)
        Xl = self.X[np.maximum(last, 0), np.arange(D)]
        Xp = self.X[np.maximum(prev, 0), np.arange(D)]
        span = last - prev
        has_vel = tracked & (prev >= 0) & (span <= o.max_gap)
        vel = np.where(has_vel[:, None], (Xl - Xp) / np.maximum(span, 1)[:, None], 0.0)
        Xhat = Xl + vel * age[:, None]
        lost = ~tracked
        if lost.any():
            base = self.X[f - 1] if f > 0 and np.isfinite(self.X[f - 1]).all() else self.X_ref
            Xhat[lost] = base[lost]
            Xhat[lost] = self.from_neighbours(tracked, Xhat, lost)
        return Xhat, tracked

    def coherent(self, f: int, P: np.ndarray, ok: np.ndarray) -> np.ndarray:
        """(D,) bool: candidate positions ``P`` that moved since the previous frame like their neighbours.

        Skin is locally smooth: between two frames a dot moves with the dots around it (neighbours on
        the template, across no opening). A dot whose step differs from the median step of its
        candidate neighbours by more than ``coherence_px`` (plus a quarter of that step, for fast
        motion) has taken a neighbouring image dot or a crease: it is rejected for this frame.
        """
        o = self.opt
        out = np.ones(len(P), bool)
        if f == 0:
            return out
        prev_ok = self.status[f - 1] == 1
        step = P - self.X[f - 1]
        usable = ok & prev_ok
        for d in np.flatnonzero(ok & prev_ok):
            nb = self.nbrs[d]
            nb = nb[usable[nb]]
            if len(nb) < 2:
                continue
            med = np.median(step[nb], axis=0)
            dev = np.linalg.norm(step[d] - med) / self.fp
            out[d] = dev <= o.coherence_px + 0.25 * np.linalg.norm(med) / self.fp
        return out

    def step(self, f: int, images: dict) -> None:
        """Track frame ``f``; ``images`` {camera: (H, W, 3) or None when not usable}."""
        o = self.opt
        if self.detector is None:
            if not self.initialise(f, images):
                self.X[f] = self.X_ref
                self.status[f] = 0
            return
        Xhat, tracked = self.predict(f)
        good = [c for c, n in enumerate(self.names) if images.get(n) is not None]
        uv = np.full((len(self.cams), len(Xhat), 2), np.nan)
        if len(good) >= 2:
            V = self.mesh(Xhat)
            vis = self.vis(V, self.cams, min_cos=o.min_cos)[:, self.dots]
            for c in good:
                S = self.detector.strength(images[self.names[c]], self.names[c])
                uv[c] = self._search_camera(c, S, Xhat, vis[c], tracked, o.search_px, o.redetect_px)
        tr = triangulate(self.cams, uv, max_error=o.max_reproj_px)
        dist = np.linalg.norm(np.nan_to_num(tr.points, nan=1e3) - Xhat, axis=1) / self.fp
        gate = np.where(tracked, o.gate_px, o.redetect_gate_px)
        ok = tr.ok & (np.nan_to_num(tr.max_error, nan=1e9) <= o.max_reproj_px) & (dist <= gate)
        ok &= self.coherent(f, np.nan_to_num(tr.points), ok)
        X = np.where(ok[:, None], np.nan_to_num(tr.points), Xhat)
        self.redetected[f] = ok & ~tracked
        self._store(f, X, ok, uv, tr)


# --------------------------------------------------------------------------------- after the last frame
def _gaussian_runs(X: np.ndarray, ok: np.ndarray, sigma: float) -> np.ndarray:
    """Zero-phase Gaussian smoothing of X (N, 3) over each run of consecutive ``ok`` frames."""
    out = X.copy()
    if sigma <= 0:
        return out
    r = int(np.ceil(3 * sigma))
    k = np.exp(-0.5 * (np.arange(-r, r + 1) / sigma) ** 2)
    n = len(X)
    f = 0
    while f < n:
        if not ok[f]:
            f += 1
            continue
        g = f
        while g < n and ok[g]:
            g += 1
        seg = X[f:g]
        if len(seg) >= 3:
            # odd (point) reflection at both ends: keeps a linear motion unbiased up to the run's ends
            m = len(seg)
            li = np.clip(np.arange(r, 0, -1), 0, m - 1)
            ri = np.clip(m - 1 - np.arange(1, r + 1), 0, m - 1)
            ext = np.concatenate([2 * seg[0] - seg[li], seg, 2 * seg[-1] - seg[ri]])
            sm = np.stack([np.convolve(ext[:, j], k / k.sum(), mode="valid") for j in range(3)], 1)
            out[f:g] = sm
        f = g
    return out


def finish_dots(tracker: DotTracker) -> np.ndarray:
    """Smoothed, gap-filled dot positions (N, D, 3) (see the module docstring); status is unchanged."""
    o = tracker.opt
    X = tracker.X.copy()
    st = tracker.status.astype(bool)
    N, D = st.shape
    for d in range(D):
        if st[:, d].any():
            X[:, d] = _gaussian_runs(X[:, d], st[:, d], o.smooth_sigma)
    # untracked stretches: neighbours' prediction + the dot's own offset, interpolated across the gap
    for d in range(D):
        col = st[:, d]
        if col.all() or not col.any():
            continue
        f = 0
        while f < N:
            if col[f]:
                f += 1
                continue
            g = f
            while g < N and not col[g]:
                g += 1
            before, after = f - 1, g          # tracked frames bounding [f, g)
            offs = {}
            for b in (before, after):
                if 0 <= b < N and col[b]:
                    anchors = st[b].copy()
                    anchors[d] = False
                    pred = _predict_one(tracker, X[b], anchors, d)
                    offs[b] = X[b, d] - pred
            for h in range(f, g):
                anchors = st[h].copy()
                pred = _predict_one(tracker, X[h], anchors, d)
                if len(offs) == 2:
                    w = (h - before) / (after - before)
                    off = (1 - w) * offs[before] + w * offs[after]
                elif offs:
                    off = next(iter(offs.values()))
                else:
                    off = 0.0
                X[h, d] = pred + off
            f = g
    return X


def _predict_one(tracker: DotTracker, Xf: np.ndarray, anchors: np.ndarray, d: int) -> np.ndarray:
    if anchors.sum() < 4:
        return Xf[d]
    return mls_affine(tracker.X_ref[anchors], Xf[anchors], tracker.X_ref[d:d + 1], k=tracker.opt.neighbours)[0]


def rigid_dot_set(template, ref_vertices: np.ndarray) -> np.ndarray:
    """Indices (into the template's dots) of the dots that move most rigidly with the skull:
    the forehead and nose regions and the dots within 3 cm of the ear points."""
    dots = template.dot_ids
    regions = template.regions
    keep = set()
    for name in ("forehead", "nose"):
        keep.update(int(v) for v in regions.get(name, []))
    for name in ("ear_L", "ear_R", "nose_bridge"):
        vid = template.head_points.get(name)
        if vid is not None:
            d = np.linalg.norm(ref_vertices[dots] - ref_vertices[vid], axis=1)
            keep.update(int(v) for v in dots[d < 0.03])
    sel = np.flatnonzero(np.isin(dots, sorted(keep)))
    return sel if len(sel) >= 6 else np.arange(len(dots))


def head_poses(X: np.ndarray, status: np.ndarray, X_ref: np.ndarray, rigid: np.ndarray) -> np.ndarray:
    """Head pose per frame (N, 4, 4), neutral → frame: a robust rigid fit of the rigid dots that are tracked."""
    N = len(X)
    out = np.tile(np.eye(4), (N, 1, 1))
    for f in range(N):
        sel = rigid[status[f, rigid] == 1]
        if len(sel) < 4:
            sel = np.flatnonzero(status[f] == 1)
        if len(sel) >= 4:
            out[f] = robust_rigid(X_ref[sel], X[f, sel], keep=0.5)
        elif f > 0:
            out[f] = out[f - 1]
    return out
