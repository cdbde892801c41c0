"""Registration of a light-stage capture into a morphable model in correspondence (paper §3–4).

``register_capture(CAPTURE)`` — what ``mifacerf register`` runs. It reads only the capture
folder (manifest, images, ``hand/``) and writes a registration folder
(:mod:`mifacerf.formats.registration`, default ``CAPTURE/registration/``):

1. **proxies** per (expression, camera) (:mod:`.proxies`, cached);
2. **dot filter** tuned on the neutral, **dot-strength maps** per view (:mod:`.dots`);
3. **base model** — the neutral: every template fiducial snapped from the user's position
   and triangulated from the views (:mod:`.snap`, :mod:`mifacerf.geometry.triangulate`); the template's
   other vertices placed relative to them (moving-least-squares, :mod:`.morph`);
4. **every other expression**, one at a time, the one most similar to those already done
   first: initial estimate by a 3-D morph of the coarse mesh from the most similar
   registered expression (per point, distance-weighted deformation metric), then the
   progressive snap-to with visibility ray-traced on the current estimate, the consensus pass
   (:mod:`.consensus`) and, for fiducials one view alone shows, the single-view snap (:mod:`.single_view`);
   then, for the fiducials still left, one more round from starts the registered ones' displacement
   gives, carried over the template mesh (:meth:`Registrar.refit_pass`);
5. **head pose, teeth, eyes** (:mod:`.eyes_teeth`), **lips and eyelids** relaxed onto the
   rotoscoped curves (:mod:`.contours`); the template's **extensions** (scalp, ears, neck: no
   fiducials) placed rigidly with the head or driven by the nearest registered fiducials
   (:mod:`.extensions`, reported per expression under ``extensions``);
6. **dot removal** from every OLAT image (:mod:`.dot_removal`);
7. **texture coordinates** and per-vertex visibility (:mod:`.texcoords`);
8. a per-expression report (registered fraction, threshold schedule, everything that could
   not be registered and why). Already registered expressions are skipped unless ``force``.

Status per vertex: 1 registered (snapped to its dot — in one view only for the report's
``single_view_dots``, depth from the estimate; or placed from data: a coarse point
clicked by the user, a margin fitted to rotoscoped curves, teeth from marks, extra vertices
placed from registered fiducials); 0 predicted only (flagged; never presented as data).
"""
from __future__ import annotations

import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from ..formats.capture import Capture
from ..formats.registration import RegisteredExpression, RegistrationWriter
from . import eyes_teeth as ET
from .contours import curve_residuals, propagate, relax_margin, rings
from .dot_removal import DEFAULT_DOT_FILL_METHOD, DOT_FILL_METHODS, Inpainter, dot_mask, fill_dots
from .dots import DotFilter, face_mask, peak_near
from .extensions import check_extensions, extensions_from_template, place_in_expression
from .hand import HandInputs, Template, read_hand_inputs
from .overrides import fixed_positions
from .morph import CoarseMorph, choose_references, coarse_neighbourhoods, deformation_distances
from .proxies import cone_weights, proxies_for
from .consensus import consensus_snap, free_peaks, view_peaks
from .single_view import single_view_snap
from .snap import Views, dot_graph, predict_from_neighbours, progressive_snap, snap, two_rings, view_weights
from .texcoords import texture_coordinates
from ..geometry.boubekeur2008 import check_curved, surface_entry
from ..geometry.footprint import centre_footprint
from ..geometry.maxima import local_maxima
from ..geometry.schaefer2006 import mls_affine
from ..geometry.rigid import apply as apply_T, rigid_from_points, robust_rigid, rotation_angle_deg
from ..geometry.triangulate import triangulate
from ..geometry.visibility import Visibility
from ..stats import median_p95
from ..errors import MifacerfError
from ..validation import check_field


HEAD = ("ear_L", "ear_R", "nose_bridge")
RIGID_REGIONS = ("forehead", "nose")    #: template regions that move (almost) with the skull
JAW_REGIONS = ("chin",)                  #: template regions that move (almost) with the jaw


class RegistrationInputError(MifacerfError, ValueError):
    """Registration cannot start: the message says which input is missing or unusable."""


@dataclass
class Options:
    """Tunable parameters (lengths in pixel footprints at the stage centre)."""

    radius_px: float = 3.0          #: 3-D search radius of the progressive snap
    neutral_radius_px: float = 3.0  #: search radius about the user's template positions (neutral; a point
    #:                                 clicked in two nearby views is uncertain in depth)
    max_radius_spacing: float = 0.35  #: ... and at most this fraction of the dots' spacing (low resolutions)
    step_px: float = 0.5            #: grid spacing of the coarse 3-D search
    decay: float = 0.8              #: threshold multiplier per level
    floor: float = 0.1              #: lowest threshold, as a fraction of the initial one
    min_strength: float = 0.8       #: ... and never below this (≈ one clear view, in dot-strength units)
    max_reproj: float = 1.0         #: views must agree to this many pixels
    min_cos: float = 0.2            #: views more oblique than this (cosine) are not used for a dot
    cone_deg: float = 60.0          #: cone omitted from the diffuse proxy
    removal_margin_px: float = 1.0  #: dot removal radius beyond the dot's image radius
    remove_dots: bool = True
    dot_fill: str = DEFAULT_DOT_FILL_METHOD  #: a .dot_removal.DOT_FILL_METHODS name: "texture" or "harmonic"
    remove_unregistered: bool = True  #: also paint out dots detected in 2-D but not registered
    unregistered_strength: float = 0.25  #: ... when their dot strength in the view reaches this (peaks
    #:   that are no dot stayed below 0.2 on the face in all 144 views of the demo capture: docs/registration.md)
    movable_rings: int = 2          #: non-fiducial vertices this close to a margin follow it
    consensus: bool = True          #: after the progressive snap, the image-space consensus pass (.consensus)
    consensus_min_peak: float = 0.1   #: ... dots in a view: strength-map maxima at least this
    consensus_min_cos: float = 0.1    #: ... views more oblique than this (cosine) are not used
    consensus_search_px: float = 5.0  #: ... peaks this near the projected start
    consensus_max_spacing: float = 0.5  #: ... and at most this fraction of the dots' spacing (shifts: 1.5 ×)
    consensus_min_spacing_px: float = 6.0  #: ... only where the dots are at least this far apart (pixels): closer,
    #:                                        oblique views merge neighbouring dots (tiny preset: 4.6 px, off)
    consensus_taken_px: float = 1.0   #: ... a peak this near a registered fiducial's projection is taken
    consensus_shifts_px: tuple = (1.5, 3.0, 4.5, 6.0, 7.5)  #: ... hypotheses this near the start, step by step
    consensus_two_view_reproj: float = 0.3    #: ... a dot seen by two views only: they agree to this (px)
    consensus_two_view_strength: float = 0.2  #: ... and both peaks at least this
    consensus_strong: float = 0.5     #: ... or, weaker than this,
    consensus_weak_shift_px: float = 1.5  #: ... it lies this near the start
    single_view: bool = True          #: then fiducials one view alone shows: position from it, depth from the surface
    single_view_strength: float = 0.25  #: ... its dot peak at least this strong (as for 2-D dot removal)
    single_view_search_px: float = 3.0  #: ... this near the point's projection (at most the consensus' spacing cap)
    refit: bool = True                #: then one more round for the fiducials still left, from starts corrected by the
    #:   registered ones' displacement, carried over the template mesh (Registrar.refit_pass; where the
    #:   consensus pass runs)
    fit_extension_outlines: bool = True  #: a template with extensions: move their vertices (on the neutral) until
    #:   their outline in every camera lies on the subject's (.extensions.fit_extensions_to_outlines); the
    #:   registration's template.json carries the fitted positions. False: the user's positions as placed
    curved: int = 3                   #: the surface renders trace, recorded in registration.json (``surface``) and
    #:   the model: the template's Phong surface at this level (geometry.boubekeur2008; 1: flat triangles). The
    #:   extensions' outline fit is made against the same surface, or the rendered outline is off by the sag

    def __post_init__(self):
        from ..methods import lookup

        lookup(DOT_FILL_METHODS, self.dot_fill, "dot fill")   # an unknown fill fails here, not after hours
        check_curved(self.curved)


@dataclass
class Expr:
    """Working state of one expression."""

    name: str
    fields: dict = field(default_factory=dict)      # camera -> (L, H, W, 3) float16
    diffuse: dict = field(default_factory=dict)     # camera -> (H, W, 3)
    report: dict = field(default_factory=dict)
    flags: list = field(default_factory=list)


class Registrar:
    """Holds the capture, the hand inputs and the expressions registered so far."""

    def __init__(self, capture: Capture, out: Path, options: Options | None = None, log=None,
                 hand: HandInputs | None = None, fresh: bool = False):
        self.cap = capture
        self.opt = options or Options()
        self.log = log or (lambda msg: None)
        self.hand = hand or read_hand_inputs(capture.root, capture.camera_names)
        if self.hand.template is None:
            raise RegistrationInputError(
                f"{capture.root / 'hand' / 'template.json'}: no usable template "
                f"({'; '.join(self.hand.problems) or 'missing'}); registration needs the base mesh a user built "
                "on the neutral (docs/registration.md)")
        self.tpl: Template = self.hand.template
        try:   # a template whose extensions cannot be placed stops here, before any work
            self.extensions = extensions_from_template(self.tpl.raw, self.tpl.n_vertices)
            check_extensions(self.tpl.vertices, self.tpl.triangles, self.tpl.dot_ids, self.extensions)
        except ValueError as exc:
            raise RegistrationInputError(f"{capture.root / 'hand' / 'template.json'}: {exc}") from exc
        self.is_extension = np.zeros(self.tpl.n_vertices, bool)
        for ext in self.extensions:
            self.is_extension[ext.vertices] = True
        if self.extensions and self.opt.fit_extension_outlines and not fresh:
            self.tpl = self._fitted_template(Path(out)) or self.tpl   # a resumed registration keeps its fit
        self.cams = list(capture.rig.cameras)
        self.names = [c.name for c in self.cams]
        self.camd = {c.name: c for c in self.cams}
        self.fp = centre_footprint(self.cams)
        self.vis = Visibility(self.tpl.triangles, self.tpl.n_vertices, tol=max(0.5 * self.fp, 5e-4))
        self.writer = RegistrationWriter(out, capture, self.tpl.to_dict(), fresh=fresh)
        self.registered: dict[str, RegisteredExpression] = {}
        self.dots = self.tpl.dot_ids
        self.is_dot = self.tpl.is_dot
        self.neighbours = dot_graph(self.tpl.n_vertices, self.tpl.triangles, self.is_dot)
        self.rings2 = two_rings(self.neighbours)
        margins = self.tpl.margin_ids()
        self.extras = np.flatnonzero(~self.is_dot & ~self.is_extension)   # extensions: place_extensions
        if margins.size:
            dist = rings(self.tpl.n_vertices, self.tpl.triangles, margins, self.opt.movable_rings)
            self.movable = np.flatnonzero((dist >= 0) & ~self.is_dot & ~self.is_extension)
        else:
            self.movable = np.zeros(0, np.int64)
        self.neutral = next((e.name for e in capture.expressions if e.category == "neutral"),
                            capture.expression_names[0])
        self.filter: DotFilter | None = None
        if "dot_filter" in self.writer.meta:
            self.filter = DotFilter.from_dict(self.writer.meta["dot_filter"])
        self.coarse_nbhds = coarse_neighbourhoods(len(self.tpl.coarse), self.tpl.coarse_triangles)
        from scipy.spatial import cKDTree

        D = self.tpl.vertices[self.dots]
        #: median distance between neighbouring fiducials (template): bounds the snap's search
        self.spacing = float(np.median(cKDTree(D).query(D, 2)[0][:, 1])) if len(D) > 2 else np.inf

    # ------------------------------------------------------------------ inputs
    def load(self, name: str, need_fields: bool) -> Expr:
        from .proxies import load_cached

        e = Expr(name)
        for cam in self.names:
            p = load_cached(self.cap, name, cam, self.opt.cone_deg)
            f = self.cap.field(name, cam) if (need_fields or p is None) else None
            if f is not None:
                check_field(f, name, cam, lambda light: self.cap.image_path(name, cam, light))
            if p is None:
                p = proxies_for(self.cap, name, cam, f, self.opt.cone_deg)
            if need_fields:
                e.fields[cam] = f.astype(np.float16)   # kept for the dot removal (half the memory)
            e.diffuse[cam] = p.diffuse
        return e

    def coarse_points(self, name: str, flags: list) -> tuple[dict, dict]:
        """Known coarse points {vertex id: (3,)} triangulated from the user's clicks, and a summary."""
        cc = self.hand.coarse.get(name)
        summary = {"given": 0, "used": 0, "missing": [], "seen_by_fewer_than_two_cameras": [],
                   "inconsistent_clicks": []}
        known = {}
        if cc is None:
            flags.append("no coarse points for this expression (hand/coarse_points.json): no coarse morph")
            summary["missing"] = self.tpl.coarse.tolist()
            return known, summary
        for vid in self.tpl.coarse:
            vid = int(vid)
            clicks = cc.clicks.get(vid, {})
            if vid not in cc.clicks and vid not in cc.positions:
                summary["missing"].append(vid)
                continue
            summary["given"] += 1
            if len(clicks) >= 2:
                uv = np.full((len(self.cams), 1, 2), np.nan)
                for cam, p in clicks.items():
                    uv[self.names.index(cam), 0] = p
                tr = triangulate(self.cams, uv, max_error=3.0)
                if tr.ok[0] and tr.max_error[0] <= 3.0:
                    known[vid] = tr.points[0]
                    continue
                summary["inconsistent_clicks"].append(vid)
            elif vid in cc.positions:
                known[vid] = cc.positions[vid]
                continue
            else:
                summary["seen_by_fewer_than_two_cameras"].append(vid)
        summary["used"] = len(known)
        for key, what in (("missing", "missing"), ("seen_by_fewer_than_two_cameras", "seen by fewer than two cameras"),
                          ("inconsistent_clicks", "with inconsistent clicks (> 3 px apart)")):
            if summary[key]:
                flags.append(f"coarse point(s) {summary[key]} {what}: left out of the coarse mesh")
        return known, summary

    # ------------------------------------------------------------------ dots
    def ensure_filter(self, e: Expr) -> None:
        if self.filter is not None:
            return
        V = self.tpl.vertices
        vis = self.vis(V, self.cams, min_cos=0.3)
        uvs = {}
        for c, cam in enumerate(self.cams):
            ids = self.dots[vis[c, self.dots]]
            uvs[cam.name] = cam.project(V[ids])[0]
        self.filter = DotFilter.fit(e.diffuse, uvs, self.tpl.dot_radius / self.fp)
        self.writer.set_meta("dot_filter", self.filter.to_dict())

    def views(self, e: Expr) -> Views:
        return Views(self.cams, [self.filter.strength(e.diffuse[n], n) for n in self.names],
                     centroid_sigma=max(1.2, 1.5 * self.filter.sigma))

    def register_dots(self, e: Expr, views: Views, pred: np.ndarray, known: dict, radius_px: float) -> tuple:
        """The fiducials' positions (T, 3), which of them snapped (T,) and the progressive snap's result:
        one round of snaps from ``pred`` (:meth:`_snap_round`), then, for the fiducials it left, one
        more from starts the registered ones correct (:meth:`refit_pass`)."""
        X, snapped, r = self._snap_round(e, views, pred, known, radius_px, e.report)
        # like the consensus pass, only where the dots are far enough apart in the images: at the tiny
        # preset (~5 px apart) 5 of the 28 more fiducials it registered over the tiny test's three
        # expressions landed > 3 px off (a neighbour's dot): 18 %, against the first round's 7 %
        if self.opt.refit and self.spacing / self.fp >= self.opt.consensus_min_spacing_px:
            base = self.registered[self.neutral].vertices if self.neutral in self.registered else pred
            self.refit_pass(e, views, pred, base, known, radius_px, X, snapped)
        return X, snapped, r

    def refit_pass(self, e: Expr, views: Views, pred: np.ndarray, base: np.ndarray, known: dict, radius_px: float,
                   X: np.ndarray, snapped: np.ndarray) -> np.ndarray:
        """Search again for the fiducials the first round left, from better starts: the registered
        fiducials' displacement from ``base`` (T, 3) — the registered neutral; for the neutral itself
        its prediction, the user's template — carried over the template mesh by thin-plate
        interpolation (:mod:`mifacerf.geometry.harmonic`, ``order=2``: along the surface, so the open jaw's motion
        reaches the lower lip without the upper lip's standstill leaking across the mouth), added to
        ``base``. Where the first round failed the morph's prediction is off by more than the search
        radius, and its error is not smooth there; the displacement itself is smoother (embedded head
        through the loader, viseme_aa: docs/your-own-head.md). The registered fiducials are known points
        of this round.
        Updates ``X`` and ``snapped`` in place for the fiducials it registers; returns their ids."""
        from ..geometry.harmonic import harmonic_interpolation

        kid = np.array(sorted(known), np.int64)
        done = snapped.copy()
        done[kid] = True
        rest = self.dots[~done[self.dots]]
        anchors = self.dots[snapped[self.dots]]
        if rest.size == 0 or len(anchors) < 3:
            e.report["refit"] = {"tried": int(rest.size), "registered": []}
            return np.zeros(0, np.int64)
        d = harmonic_interpolation(self.tpl.n_vertices, self.tpl.triangles, anchors, X[anchors] - base[anchors],
                                   order=2)
        pred2 = base + d
        pred2[anchors] = X[anchors]
        known2 = dict(known)
        known2.update({int(v): X[v] for v in anchors})
        sub: dict = {}
        # two views alone fix a point poorly in depth (a small baseline): from these starts (a fraction of
        # a millimetre off where the first round's were several) such a snap must stay within half the
        # search radius, on the neutral too. Without this, one of head_turn_left's refitted dots in the
        # main job's capture landed 4.6 mm off from a start 0.7 mm off (docs/registration.md).
        radius = self._search_radius(radius_px)
        X2, snapped2, _ = self._snap_round(e, views, pred2, known2, radius_px, sub, targets=rest,
                                           two_view_shift=0.5 * radius)
        new = rest[snapped2[rest]]
        if new.size:   # one image dot, one fiducial: a new one on a registered one's dot is left
            from scipy.spatial import cKDTree

            dist, _ = cKDTree(X[anchors]).query(X2[new])
            new = new[dist > max(self.tpl.dot_radius, 0.5 * self.fp)]
        X[new] = X2[new]
        snapped[new] = True
        sv = np.intersect1d(np.asarray(sub.get("single_view_dots", []), np.int64), new)
        e.report["single_view_dots"] = sorted(set(e.report.get("single_view_dots", [])) | set(sv.tolist()))
        e.report["refit"] = {"tried": int(rest.size), "registered": new.tolist(), "single_view": sv.tolist(),
                             "start_moved_mm": median_p95(1000 * np.linalg.norm(pred2[rest] - pred[rest], axis=1))}
        return new

    def _search_radius(self, radius_px: float) -> float:
        """The 3-D snap's search radius (metres): ``radius_px`` pixel footprints, at most
        ``max_radius_spacing`` of the dots' spacing."""
        return min(radius_px * self.fp, self.opt.max_radius_spacing * self.spacing)

    def _snap_round(self, e: Expr, views: Views, pred: np.ndarray, known: dict, radius_px: float,
                    report: dict, targets: np.ndarray | None = None, two_view_shift: float | None = None) -> tuple:
        """One round of snaps (progressive, consensus, polish, single view) of the fiducials ``targets``
        (default all) from ``pred``; ``known`` points are fixed (coarse points; in a refit round, the
        registered fiducials, not snapped again). A fiducial two views alone triangulate must lie within
        ``two_view_shift`` (metres; default: the search radius plus a grid step, none on the neutral) of
        its start."""
        o = self.opt
        targets = self.dots if targets is None else targets
        vis = view_weights(*self.vis(pred, self.cams, min_cos=o.min_cos, return_cos=True))
        radius = self._search_radius(radius_px)
        report["search_radius_px"] = round(radius / self.fp, 3)
        r = progressive_snap(views, pred, targets, self.neighbours, known, vis, radius=radius,
                             step=o.step_px * self.fp, decay=o.decay, floor=o.floor, min_strength=o.min_strength,
                             max_reproj=o.max_reproj, min_separation=max(1.5 * self.tpl.dot_radius, self.fp),
                             two_view_max_shift=(two_view_shift if two_view_shift is not None else
                                                 None if e.name == self.neutral else radius + o.step_px * self.fp),
                             dot_holders=self.dots)
        X, snapped = r.X.copy(), r.snapped.copy()
        rescued = np.zeros(len(X), bool)
        if o.consensus and self.spacing / self.fp >= o.consensus_min_spacing_px:
            rescued = self.consensus_pass(report, views, pred, X, snapped, known)
        elif o.consensus:
            report["consensus"] = {"skipped": f"dots {self.spacing / self.fp:.1f} px apart, below "
                                              f"{o.consensus_min_spacing_px} px"}
        # polish: visibility from the registered mesh, then a small re-snap of every registered dot (those
        # the consensus pass placed are triangulated from their peaks already)
        vis2 = view_weights(*self.vis(X, self.cams, min_cos=o.min_cos, return_cos=True))
        ids = targets[snapped[targets] & ~rescued[targets]]
        p = snap(views, X[ids], vis2[:, ids], radius=1.0 * self.fp, step=0.25 * self.fp, max_reproj=o.max_reproj)
        good = p.ok & (p.strength >= 0.5 * o.min_strength)
        X[ids[good]] = p.X[good]
        reproj = np.full(len(X), np.nan)
        reproj[ids[good]] = p.reproj[good]
        nviews = np.zeros(len(X), int)
        nviews[ids[good]] = p.n_views[good]
        # two template dots on one image dot: keep the one nearer its prediction
        dup = self._duplicates(X, snapped, pred)
        if dup.size:
            snapped[dup] = False
            e.flags.append(f"dots {dup.tolist()} snapped onto a dot already taken: reverted to prediction")
            X[dup] = pred[dup]
        # like the consensus pass, only where the dots are far enough apart in the images for a lone peak to
        # be told from its neighbours' (off at the tiny preset, where dots are ~5 px apart)
        use_single = o.single_view and self.spacing / self.fp >= o.consensus_min_spacing_px
        single = self.single_view_pass(views, pred, X, snapped, known) if use_single else np.zeros(0, int)
        report["single_view_dots"] = single.tolist()
        report.update({
            "threshold_schedule": [round(float(t), 4) for t in r.schedule],
            "accepted_per_level": [int(a) for a in r.accepted_per_level],
            "snap_attempts": int(r.attempts),
            "reprojection_px": median_p95(reproj[targets]),
            "views_per_dot": median_p95(nviews[targets][nviews[targets] > 0].astype(float)),
        })
        return X, snapped, r

    def consensus_pass(self, report: dict, views: Views, pred: np.ndarray, X: np.ndarray, snapped: np.ndarray,
                       known: dict) -> np.ndarray:
        """The image-space consensus snap (:mod:`.consensus`) of the fiducials the progressive snap left, in
        the progressive snap's spirit: hypotheses near their start first (``consensus_shifts_px``, growing),
        repeated at each step while points join — every point registered improves its neighbours' starts
        and takes its own image dots. Updates ``X`` and ``snapped`` in place; returns the (T,) mask of the
        points it registered."""
        o = self.opt
        T = len(X)
        in_S = snapped.copy()
        kid = np.array(sorted(known), np.int64)
        in_S[kid] = True
        is_reg = snapped.copy()
        is_reg[kid[self.is_dot[kid]]] = True
        peaks = [view_peaks(m, o.consensus_min_peak, views.centroid_sigma) for m in views.maps]
        rescued = np.zeros(T, bool)
        per_step, rejected = [], {}
        sep = max(1.5 * self.tpl.dot_radius, self.fp)
        # at low resolutions the dots are a few pixels apart: the search and the shifts stay below the spacing
        spacing_px = self.spacing / self.fp
        search_px = min(o.consensus_search_px, o.consensus_max_spacing * spacing_px)
        shifts = sorted({min(s_, 1.5 * o.consensus_max_spacing * spacing_px) for s_ in o.consensus_shifts_px})
        for shift_px in shifts:
            n_step = 0
            for _ in range(10):
                rest = self.dots[~is_reg[self.dots]]
                if rest.size == 0:
                    break
                start, vis, cos, reg_ids, free = self._starts_and_free_peaks(pred, X, in_S, is_reg, rest, peaks)
                res = consensus_snap(self.cams, peaks, free, start, (vis & (cos > o.consensus_min_cos))[:, rest],
                                     X[reg_ids], max_shift=shift_px * self.fp,
                                     weak_shift=o.consensus_weak_shift_px * self.fp,
                                     search_px=search_px, max_reproj=o.max_reproj,
                                     two_view_reproj=o.consensus_two_view_reproj,
                                     two_view_strength=o.consensus_two_view_strength,
                                     strong=o.consensus_strong, merge_radius=sep, min_separation=sep)
                rejected = res.rejected
                if res.accepted.size == 0:
                    break
                ids = rest[res.accepted]
                X[ids] = res.X
                snapped[ids] = is_reg[ids] = in_S[ids] = rescued[ids] = True
                n_step += len(ids)
            per_step.append(n_step)
        report["consensus"] = {"search_px": round(search_px, 3), "shifts_px": [round(s_, 3) for s_ in shifts],
                                 "registered_per_step": per_step,
                                 "registered": np.flatnonzero(rescued).tolist(), "left": rejected}
        return rescued

    def _starts_and_free_peaks(self, pred, X, in_S, is_reg, rest, peaks) -> tuple:
        """For the unregistered fiducials ``rest``: their starts (prediction corrected by the neighbours in
        ``in_S``), visibility and view cosines (C, T) of the mesh with them there, the registered fiducials'
        ids, and per view the dot peaks those do not already take (:func:`.consensus.free_peaks`)."""
        start = predict_from_neighbours(pred, X, in_S, rest, self.neighbours, self.rings2)
        Xm = X.copy()
        Xm[rest] = start
        vis, cos = self.vis(Xm, self.cams, min_cos=None, return_cos=True)
        cos = np.nan_to_num(cos, nan=1.0)
        reg_ids = self.dots[is_reg[self.dots]]
        free = free_peaks(peaks, self.cams, X[reg_ids], (vis & (cos > -0.3))[:, reg_ids], self.opt.consensus_taken_px)
        return start, vis, cos, reg_ids, free

    def single_view_pass(self, views: Views, pred: np.ndarray, X: np.ndarray, snapped: np.ndarray,
                         known: dict) -> np.ndarray:
        """:func:`.single_view.single_view_snap` for the fiducials still unregistered that show as a dot in exactly
        one of the views that see them (visibility of the estimate: prediction corrected by registered
        neighbours). Updates ``X`` and ``snapped`` in place; returns the ids it registered."""
        o = self.opt
        kid = np.array(sorted(known), np.int64)
        is_reg = snapped.copy()
        is_reg[kid[self.is_dot[kid]]] = True
        rest = self.dots[~is_reg[self.dots]]
        if rest.size == 0:
            return rest
        in_S = is_reg.copy()
        in_S[kid] = True
        peaks = [view_peaks(m, o.single_view_strength, views.centroid_sigma) for m in views.maps]
        start, vis, cos, _, free = self._starts_and_free_peaks(pred, X, in_S, is_reg, rest, peaks)
        search = min(o.single_view_search_px, o.consensus_max_spacing * self.spacing / self.fp)
        r = single_view_snap(self.cams, peaks, free, start, (vis & (cos > o.min_cos))[:, rest], search,
                             o.single_view_strength)
        ids = rest[r.points]
        X[ids] = r.X
        snapped[ids] = True
        return ids

    def _duplicates(self, X, snapped, pred) -> np.ndarray:
        from scipy.spatial import cKDTree

        ids = self.dots[snapped[self.dots]]
        if len(ids) < 2:
            return np.zeros(0, np.int64)
        pairs = cKDTree(X[ids]).query_pairs(max(self.tpl.dot_radius, 0.5 * self.fp), output_type="ndarray")
        out = []
        for a, b in pairs:
            i, j = ids[a], ids[b]
            out.append(i if np.linalg.norm(X[i] - pred[i]) > np.linalg.norm(X[j] - pred[j]) else j)
        return np.unique(np.array(out, np.int64))

    # ------------------------------------------------------------------ the rest of the template
    def place_extras(self, V_src: np.ndarray, src_ok: np.ndarray, X: np.ndarray, snapped: np.ndarray,
                     ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Positions of non-fiducial vertices ``ids`` carried from ``V_src`` by the registered dots."""
        anchors = self.dots[snapped[self.dots] & src_ok[self.dots]]
        if len(ids) == 0 or len(anchors) < 4:
            return V_src[ids].copy(), np.zeros(len(ids), bool)
        P = mls_affine(V_src[anchors], X[anchors], V_src[ids], k=16)
        return P, np.ones(len(ids), bool)

    def relax_contours(self, name: str, V: np.ndarray, status: np.ndarray, e: Expr) -> np.ndarray:
        rot = self.hand.rotoscope.get(name)
        out = {}
        V0 = V.copy()
        relaxed_any = []
        for mname, ids in self.tpl.margins.items():
            views = {} if rot is None else {c: p for c, p in rot.curves.get(mname, {}).items() if c in self.camd}
            if len(views) < 2:
                out[mname] = "not rotoscoped in two views: morphed from the reference only (predicted)"
                e.flags.append(f"{mname}: not rotoscoped in ≥ 2 views; left at the morph (status 0)")
                status[ids] = 0
                continue
            before = float(np.sqrt(np.mean([np.mean(curve_residuals(self.camd[c], V[ids], p) ** 2)
                                            for c, p in views.items()])))
            Xn = relax_margin(V[ids], views, self.camd)
            after = float(np.sqrt(np.mean([np.mean(curve_residuals(self.camd[c], Xn, p) ** 2)
                                           for c, p in views.items()])))
            V[ids] = Xn
            status[ids] = 1
            relaxed_any.append(ids)
            out[mname] = {"views": sorted(views), "rms_px_before": round(before, 3), "rms_px_after": round(after, 3)}
        if relaxed_any and self.movable.size:
            margin_ids = np.unique(np.concatenate(relaxed_any))
            V = propagate(V0, V, self.tpl.triangles, margin_ids, self.movable)
        e.report["lips_eyelids"] = out
        return V

    def place_extension_vertices(self, name: str, V: np.ndarray, status: np.ndarray, T_head: np.ndarray,
                                 e: Expr) -> None:
        """The template's extensions placed in ``V`` and ``status`` (in place) from this expression's registered
        fiducials and head pose (:func:`.extensions.place_in_expression`); reported under ``extensions``,
        fall-backs also flagged."""
        if not self.extensions:
            return
        N = None if name == self.neutral else self.registered[self.neutral]
        predicted = str(e.report.get("head_pose", {}).get("source", "")).startswith("none")
        rep = place_in_expression(self.tpl.vertices, self.tpl.triangles, self.dots, self.extensions, V, status,
                                  T_head, neutral=N, head_predicted=predicted)
        e.report["extensions"] = rep
        e.flags.extend(rep["fallbacks"])

    def fit_extension_outlines(self, V: np.ndarray, status: np.ndarray, T_head: np.ndarray, e: Expr) -> None:
        """On the neutral (``V``, ``status``: its registered vertices; ``T_head`` its head pose): the template's
        extension vertices fitted to the subject's outlines in the neutral's diffuse proxies
        (:func:`.extensions.fit_extensions_to_outlines`, ``Options.fit_extension_outlines``); the template
        (``self.tpl``, the folder's ``template.json``) takes the fitted positions, which every expression then
        places. Reported under ``extension_outlines`` (the neutral's report) and in ``registration.json``."""
        if not self.extensions or not self.opt.fit_extension_outlines:
            return
        from .extensions import fit_extensions_to_outlines

        t0 = time.time()
        images = [e.diffuse[n] for n in self.names]
        rest, rep = fit_extensions_to_outlines(self.tpl.vertices, self.tpl.triangles, self.dots, self.extensions,
                                               V, status, T_head, self.cams, images, self.vis,
                                               curved=self.opt.curved)
        raw = dict(self.tpl.raw)
        raw["vertices"] = [dict(v, position=np.round(rest[i], 7).tolist()) if self.is_extension[i] else v
                           for i, v in enumerate(self.tpl.raw["vertices"])]
        self.tpl = Template.from_dict(raw, str(self.writer.root / "template.json"))
        rep = {k: rep[k] for k in ("summary", "moved_mm", "rounds", "vertices")}
        rep["time_s"] = round(time.time() - t0, 2)
        self._write_template(raw, rep)
        e.report["extension_outlines"] = rep
        self.log(f"extensions fitted to the neutral's outlines: {rep['summary']} ({rep['time_s']} s)")

    def _write_template(self, raw: dict, fit: dict) -> None:
        """The folder's template.json replaced by ``raw`` (atomic; its checksum in registration.json, written
        right after with the fit's report under ``extension_fit``)."""
        from ..formats.files import file_entry, write_json_atomic

        tpath = self.writer.root / "template.json"
        write_json_atomic(tpath, raw)
        self.writer.meta["files"]["template.json"] = file_entry(tpath)
        self.writer.set_meta("extension_fit", {"summary": fit["summary"], "moved_mm": fit["moved_mm"],
                                               "curved": int(self.opt.curved)})

    def _fitted_template(self, out: Path) -> Template | None:
        """The template of a registration in ``out`` whose extensions were fitted to the outlines: the user's
        template with only the extension vertices' positions changed (None when there is none, or the user's
        template changed since)."""
        import json

        try:
            meta = json.loads((out / "registration.json").read_text())
            d = json.loads((out / "template.json").read_text())
        except (OSError, ValueError):
            return None
        mine = self.tpl.raw
        if "extension_fit" not in meta or meta["extension_fit"].get("curved", 1) != self.opt.curved or \
                {k: v for k, v in d.items() if k != "vertices"} != \
                {k: v for k, v in json.loads(json.dumps(mine)).items() if k != "vertices"}:
            return None
        vs, ws = d.get("vertices", []), json.loads(json.dumps(mine["vertices"]))
        if len(vs) != len(ws) or any({k: x for k, x in a.items() if k != "position" or not ext} !=
                                     {k: x for k, x in b.items() if k != "position" or not ext}
                                     for a, b, ext in zip(vs, ws, self.is_extension)):
            return None
        try:
            return Template.from_dict(d, str(out / "template.json"))
        except ValueError:
            return None

    def head_points(self, name: str, V: np.ndarray, status: np.ndarray, known: dict) -> dict:
        """Ear / nose-bridge points of an expression {name: (3,)}: the user's marks (rotoscope
        points, or the coarse points when those are the head points), else registered vertices."""
        rot = self.hand.rotoscope.get(name)
        out = {}
        for pname in ("ear_L", "ear_R", "nose_bridge"):
            if rot is not None and pname in rot.points:
                p = ET.triangulate_marks(self.cams, rot.points[pname])
                if p is not None:
                    out[pname] = p
                    continue
            vid = self.tpl.head_points.get(pname)
            if vid is None:
                continue
            if vid in known:
                out[pname] = np.asarray(known[vid], np.float64)
            elif status[vid] == 1 and self.is_dot[vid]:
                out[pname] = V[vid].copy()
        return out

    def head_pose(self, name: str, X: np.ndarray, status: np.ndarray, known: dict, e: Expr) -> np.ndarray:
        if name == self.neutral:
            e.report["head_pose"] = {"source": "the neutral defines the head frame"}
            return np.eye(4)
        ref = {k: np.asarray(v) for k, v in self.writer.meta.get("head_points_neutral", {}).items()}
        marks = self.head_points(name, X, status, known)
        common = [k for k in ("ear_L", "ear_R", "nose_bridge") if k in marks and k in ref]
        N = self.registered[self.neutral]
        both = self.dots[(status[self.dots] == 1) & (N.status[self.dots] == 1)]
        rigid = np.intersect1d(both, np.concatenate([self.tpl.regions.get(k, np.zeros(0, np.int64))
                                                     for k in RIGID_REGIONS])) if self.tpl.regions else both
        if len(common) == 3:
            P = np.array([ref[k] for k in common])
            Q = np.array([marks[k] for k in common])
            T3 = rigid_from_points(P, Q)
            T, n_used = ET.refine_rigid(T3, P, Q, N.vertices[rigid], X[rigid], self.fp)
            dR = T3[:3, :3].T @ T[:3, :3]
            e.report["head_pose"] = {
                "source": f"ear and nose-bridge points, refined with {n_used} rigidly moving fiducials "
                          "(forehead, nose)",
                "refinement_deg": round(rotation_angle_deg(dR), 4)}
            return T
        if len(both) < 3:
            e.flags.append("head pose: no ear / nose-bridge points and fewer than three registered fiducials; "
                           "identity (predicted)")
            e.report["head_pose"] = {"source": "none (identity, predicted)"}
            return np.eye(4)
        e.flags.append(f"head pose: ear / nose-bridge points missing ({sorted(set(HEAD) - set(common))}); "
                       "fitted rigidly to the most rigid third of the registered fiducials instead")
        e.report["head_pose"] = {"source": "robust rigid fit to registered fiducials (no ear / nose marks)"}
        return robust_rigid(N.vertices[both], X[both])

    def jaw_pose(self, X: np.ndarray, status: np.ndarray) -> tuple[np.ndarray | None, int]:
        """Rigid fit (4, 4) neutral → expression of the registered fiducials of the jaw regions
        (``JAW_REGIONS``), and how many were used; (None, n) with fewer than three, or with points
        (nearly) on one line, which leave a rotation about that line undetermined."""
        if not self.tpl.regions:
            return None, 0
        ids = np.concatenate([np.asarray(self.tpl.regions.get(k, []), np.int64) for k in JAW_REGIONS])
        N = self.registered[self.neutral]
        ids = np.intersect1d(ids, self.dots)
        ids = ids[(status[ids] == 1) & (N.status[ids] == 1)]
        if len(ids) < 3 or np.linalg.svd(N.vertices[ids] - N.vertices[ids].mean(0), compute_uv=False)[1] < 2e-3:
            return None, len(ids)
        return rigid_from_points(N.vertices[ids], X[ids]), len(ids)

    def place_teeth(self, name: str, T_head: np.ndarray, e: Expr, X: np.ndarray, status: np.ndarray) -> np.ndarray:
        """Rigid transforms (2, 4, 4) of the upper and lower teeth (template rest frame → world).

        Lower teeth, beyond the paper (which takes the head's rotation): the rotation of the jaw,
        fitted to the registered chin fiducials (an open jaw turns the lower teeth by up to 20°
        relative to the head), with the translation from the marked point."""
        teeth = np.full((2, 4, 4), np.nan)
        if not self.tpl.teeth:
            e.report["teeth"] = "the template has no teeth"
            return teeth
        teeth[0] = T_head
        info = {"upper": "rigid with the head"}
        if name == self.neutral:
            teeth[1] = np.eye(4)
            info["lower"] = "the template (neutral)"
        else:
            rot = self.hand.rotoscope.get(name)
            mark = None
            if rot is not None and "lower_teeth" in rot.points:
                mark = ET.triangulate_marks(self.cams, rot.points["lower_teeth"])
            ref = self.tpl.lower_teeth_point
            T_jaw, n_jaw = self.jaw_pose(X, status)
            turn = "head" if T_jaw is None else f"jaw (rigid fit to {n_jaw} registered chin fiducials)"
            if mark is not None and ref is not None:
                teeth[1] = ET.lower_teeth_transform(T_head if T_jaw is None else T_jaw, ref, mark)
                info["lower"] = f"marked point + rotation of the {turn}"
            else:
                teeth[1] = T_head if T_jaw is None else T_jaw
                info["lower"] = f"predicted: no lower-teeth mark in ≥ 2 views; moved with the {turn}"
                e.flags.append(f"lower teeth: no marked point in ≥ 2 views; moved with the {turn} (predicted)")
        e.report["teeth"] = info
        return teeth

    def eye_centres(self, T_head: np.ndarray) -> np.ndarray:
        rel = self.writer.meta.get("eyes_head_frame")
        out = np.full((2, 3), np.nan)
        for i, side in enumerate(("L", "R")):
            if rel and rel.get(side) is not None:
                out[i] = apply_T(T_head, np.asarray(rel[side])[None])[0]
            elif side in self.tpl.eyes and "centre" in self.tpl.eyes[side]:
                out[i] = apply_T(T_head, np.asarray(self.tpl.eyes[side]["centre"])[None])[0]
        return out

    # ------------------------------------------------------------------ one expression
    def register(self, name: str) -> RegisteredExpression:
        t0 = time.time()
        o = self.opt
        e = self.load(name, need_fields=o.remove_dots)
        cat = self.cap.expressions[self.cap.expression_index(name)].category
        e.report.update({"category": cat})
        self.ensure_filter(e)
        views = self.views(e)
        known, csum = self.coarse_points(name, e.flags)
        e.report["coarse_points"] = csum
        T = self.tpl.n_vertices
        if name == self.neutral:
            pred = self.tpl.vertices.copy()
            src = self.tpl.vertices
            src_ok = np.ones(T, bool)
            choice_names = ["template (user-placed on the neutral)"]
            choice = np.zeros(T, int)
            radius = o.neutral_radius_px
            sources = {0: (src, src_ok)}
        else:
            pred, choice, choice_names, radius = self.predict(name, known, e)
            sources = {k: (self.registered[n].vertices, self.registered[n].status == 1)
                       for k, n in enumerate(choice_names)}
        e.report["reference"] = {n: int((choice == k).sum()) for k, n in enumerate(choice_names)}
        X, snapped, _ = self.register_dots(e, views, pred, known, radius)
        fixed = fixed_positions(self.cap.root, name, self.cams, T, e.flags)   # hand fixes (hand/overrides.json)
        for vid, p in fixed.items():
            X[vid], snapped[vid] = p, True
        if fixed:
            e.report["hand_fixed"] = sorted(fixed)
        status = np.zeros(T, np.int8)
        status[self.dots[snapped[self.dots]]] = 1
        unsnapped_known = [int(v) for v in known if self.is_dot[v] and not snapped[v]]
        if unsnapped_known:
            e.flags.append(f"coarse fiducial(s) {unsnapped_known} did not snap to their dot: kept at the "
                           "user's clicks")
        for vid in known:  # coarse points placed from the user's clicks
            status[vid] = 1
        not_reg = self.dots[status[self.dots] != 1]
        if not_reg.size:
            e.flags.append(f"{len(not_reg)} fiducial(s) could not be registered (no dot found above the "
                           f"strength floor in ≥ 2 views, nor in exactly one): kept at the "
                           f"morph prediction with status 0")
        # extras relative to the registered dots (per reference expression)
        V = X.copy()
        ex = self.extras
        ex_status = np.zeros(len(ex), bool)
        for k, (Vs, ok) in sources.items():
            sel = choice[ex] == k
            if sel.any():
                P, placed = self.place_extras(Vs, ok, X, snapped, ex[sel])
                V[ex[sel]] = P
                ex_status[sel] = placed
        status[ex] = ex_status.astype(np.int8)
        for vid, p in known.items():  # non-fiducial coarse points (ears, mouth corners...): the clicks
            if not self.is_dot[vid]:
                V[vid] = p
                status[vid] = 1
        for vid, p in fixed.items():   # the user's fixes win over the placement of extras
            V[vid], status[vid] = p, 1
        V = self.relax_contours(name, V, status, e)
        T_head = self.head_pose(name, V, status, known, e)
        if name == self.neutral:
            self.fit_extension_outlines(V, status, T_head, e)
        self.place_extension_vertices(name, V, status, T_head, e)
        if name == self.neutral:
            hp = self.head_points(name, V, status, known)
            for k, vid in self.tpl.head_points.items():
                hp.setdefault(k, V[vid])
            self.writer.set_meta("head_points_neutral", {k: np.asarray(v).tolist() for k, v in hp.items()})
        teeth = self.place_teeth(name, T_head, e, V, status)
        eyes = self.eye_centres(T_head)
        uv, visible = texture_coordinates(V, self.cams, self.vis)
        reg = RegisteredExpression(name, V, status, uv, visible, eyes, teeth, T_head)
        nd = len(self.dots)
        e.report.update({
            "n_dots": int(nd),
            "dots_registered": int((status[self.dots] == 1).sum()),
            "dots_single_view": len(e.report.get("single_view_dots", [])),
            "registered_fraction": round(float((status[self.dots] == 1).mean()) if nd else 1.0, 4),
            "dots_not_registered": not_reg.tolist(),
            "vertices_predicted_only": int((status == 0).sum()),
        })
        if o.remove_dots:
            e.report["dot_removal"] = self.remove_dots(e, reg)
        e.report["flags"] = e.flags
        e.report["time_s"] = round(time.time() - t0, 2)
        self.writer.write_expression(reg, e.report)
        self.registered[name] = reg
        return reg

    def predict(self, name: str, known: dict, e: Expr):
        """Initial estimate: per point, a 3-D morph of the coarse mesh from the most similar registered expression."""
        o = self.opt
        regs = list(self.registered)
        coarse = self.tpl.coarse
        N = self.registered[self.neutral]
        cN = np.full((len(coarse), 3), np.nan)
        for j, vid in enumerate(coarse):
            if int(vid) in known:
                cN[j] = known[int(vid)]
        usable = np.isfinite(cN).all(1)
        tris_ok = usable[self.tpl.coarse_triangles].all(1).sum() if len(self.tpl.coarse_triangles) else 0
        if usable.sum() < 3 or tris_ok == 0:
            # no coarse mesh: the most similar expression by whatever coarse points exist, else the neutral
            e.flags.append("coarse mesh unusable (fewer than three coarse points / no complete triangle): "
                           "initial estimate = neutral (rigidly aligned to the known points if ≥ 3)")
            pred = N.vertices.copy()
            if usable.sum() >= 3:
                Tr = rigid_from_points(N.vertices[coarse[usable]], cN[usable])
                pred = apply_T(Tr, pred)
            return pred, np.zeros(len(pred), int), [self.neutral], o.radius_px
        cn = N.vertices[coarse]
        D = np.stack([deformation_distances(cn, self.registered[r].vertices[coarse], cN, self.coarse_nbhds)
                      for r in regs])
        choice = choose_references(N.vertices, cn, D)
        pred = np.empty_like(N.vertices)
        missing = ~usable
        if missing.any():
            e.report["coarse_points"]["filled_for_the_morph"] = coarse[missing].tolist()
        for k, r in enumerate(regs):
            sel = choice == k
            if sel.any():
                cR = self.registered[r].vertices[coarse]
                cNk = cN.copy()
                if missing.any():
                    # a coarse point the user could not click still shapes the morph: its position is
                    # carried from R by its clicked neighbours (initial estimate only, never data)
                    cNk[missing] = mls_affine(cR[usable], cN[usable], cR[missing], k=6, eps=0.01)
                m = CoarseMorph(cR, cNk, self.tpl.coarse_triangles)
                pred[sel] = m(self.registered[r].vertices[sel])
        return pred, choice, regs, o.radius_px

    # ------------------------------------------------------------------ dot removal
    def remove_dots(self, e: Expr, reg: RegisteredExpression) -> dict:
        """Dot-free patches of every view: the registered fiducials' discs, then (``remove_unregistered``)
        any dot still detected in 2-D after that (a fiducial that could not be registered in 3-D is
        still a yellow dot in the images). The views are filled in parallel threads (OpenCV's inpainting
        and NumPy release the GIL) and written in camera order."""
        from concurrent.futures import ThreadPoolExecutor

        ids = self.dots[reg.status[self.dots] == 1]
        before, after, npix, extra = [], [], 0, 0
        workers = max(1, min(len(self.cams), os.cpu_count() or 1))
        with ThreadPoolExecutor(max_workers=workers) as pool:
            views = pool.map(lambda c: self._dot_free_view(e, reg, ids, c), range(len(self.cams)))
            for cam, (inp, values, b, a, x) in zip(self.cams, views):
                self.writer.write_dotfree(e.name, cam.name, inp.pixels, values)
                npix += len(inp)
                extra += x
                if b is not None:
                    before.append(b)
                    after.append(a)
        b = float(np.mean(np.concatenate(before))) if before else float("nan")
        a = float(np.mean(np.concatenate(after))) if after else float("nan")
        if extra:
            e.report["unregistered_dots_removed_2d"] = int(extra)
        return {"pixels": int(npix), "response_before": round(b, 4), "response_after": round(a, 4)}

    def _dot_free_view(self, e: Expr, reg: RegisteredExpression, ids: np.ndarray, c: int):
        """One view's dot removal: (Inpainter, fill values (L, P, 3), dot responses before and after at the
        registered dots (None when the view sees none), dots removed from 2-D detections only)."""
        cam = self.cams[c]
        sel = ids[reg.visible[c, ids]]
        uv, depth = cam.project(reg.vertices[sel])
        focal = np.sqrt(cam.K[0, 0] * cam.K[1, 1])
        r_px = self.tpl.dot_radius * focal / depth + self.opt.removal_margin_px
        shape = (cam.height, cam.width)
        mask = dot_mask(shape, uv, r_px)
        valid = face_mask(e.diffuse[cam.name], 0.01)
        d0 = e.diffuse[cam.name]
        s = self.filter.scales.get(cam.name, 1.0)
        extra = 0
        if self.opt.remove_unregistered:
            # 2-D detections left once the registered dots are painted out
            left = np.maximum(self.filter.response(Inpainter(mask, valid).apply(d0)), 0) / s
            peaks = local_maxima(left, self.opt.unregistered_strength) & valid & ~mask
            pk = np.argwhere(peaks)[:, ::-1].astype(np.float64)
            if len(pk):
                r_typ = self.tpl.dot_radius * focal / float(np.median(depth) if len(depth) else 1.3)
                mask |= dot_mask(shape, pk, r_typ + self.opt.removal_margin_px + 0.5)
                extra = len(pk)
        inp = Inpainter(mask, valid)
        values = self._dot_fill(inp, e.fields[cam.name], valid)
        if not len(uv):
            return inp, values, None, None, extra
        # the diffuse proxy of the dot-free images (the same linear combination of the lights as d0, over
        # the filled values): the residual dot response of what is stored
        d1 = np.array(d0, copy=True)
        w = cone_weights(self.cap.rig.lights, cam, self.opt.cone_deg).astype(np.float32)
        d1[inp.pixels[:, 0], inp.pixels[:, 1]] = np.tensordot(w, np.asarray(values, np.float32), axes=(0, 0))
        r0 = np.maximum(self.filter.response(d0), 0) / s
        r1 = np.maximum(self.filter.response(d1), 0) / s
        return inp, values, peak_near(r0, uv, 1.0)[1], peak_near(r1, uv, 1.0)[1], extra

    def _dot_fill(self, inp: Inpainter, images: np.ndarray, valid: np.ndarray) -> np.ndarray:
        """Values (L, P, 3) filling ``inp``'s pixels of ``images`` (L, H, W, 3) by ``Options.dot_fill``."""
        return fill_dots(inp, images, valid, method=self.opt.dot_fill)

    # ------------------------------------------------------------------ eyes (after all expressions)
    def finish_eyes(self) -> dict:
        """Average eye centres in the head frame over the expressions looking along a known direction."""
        est = {"L": [], "R": []}
        used = []
        for name, reg in self.registered.items():
            rot = self.hand.rotoscope.get(name)
            if rot is None or not rot.eyes_look_at:
                continue
            Tinv = np.linalg.inv(reg.head_pose)
            for side in ("L", "R"):
                views = {c: p for c, p in rot.curves.get(f"iris_{side}", {}).items() if c in self.camd}
                if len(views) < 2:
                    continue
                c3 = ET.iris_centre(self.cams, views)
                if c3 is None:
                    continue
                d = ET.gaze_direction(rot.eyes_look_at, reg.head_pose, c3, self.cams)
                if d is None:
                    continue
                depth = ET.eye_depth(self.tpl.eyes.get(side, {}))
                est[side].append(apply_T(Tinv, (c3 - depth * d)[None])[0])
                used.append(f"{name}:{side}")
        rel = {}
        for side, v in est.items():
            if not v:
                rel[side] = None
                continue
            v = np.asarray(v)
            med = np.median(v, axis=0)
            keep = np.linalg.norm(v - med, axis=1) <= max(3 * self.fp, 0.002)   # drop wild marks
            rel[side] = v[keep].mean(0).tolist()
        info = {"head_frame_centres": rel, "from": used,
                "spread_m": {s: (float(np.linalg.norm(np.std(v, axis=0))) if len(v) > 1 else None)
                             for s, v in est.items()}}
        self.writer.set_meta("eyes_head_frame", rel)
        self.writer.set_meta("eyes", info)
        # update every registered expression's eye centres
        for name, reg in self.registered.items():
            ec = self.eye_centres(reg.head_pose)
            if not np.allclose(np.nan_to_num(ec, nan=1e9), np.nan_to_num(reg.eye_centres, nan=1e9)):
                reg.eye_centres = ec
                self.writer.write_expression(reg, self.writer.meta["expressions"][name], keep_dotfree=True)
        return info


def order_expressions(reg: Registrar, todo: list[str]) -> list[str]:
    """Greedy order: next the expression whose coarse points are closest (after a rigid alignment)
    to one already registered (a proxy for the paper's 'expands ... one at a time')."""
    coarse = reg.tpl.coarse
    pts = {}
    for n in todo + list(reg.registered):
        cc = reg.hand.coarse.get(n)
        P = np.full((len(coarse), 3), np.nan)
        if cc is not None:
            for j, vid in enumerate(coarse):
                if int(vid) in cc.positions:
                    P[j] = cc.positions[int(vid)]
        pts[n] = P

    def dist(a, b):
        m = np.isfinite(pts[a]).all(1) & np.isfinite(pts[b]).all(1)
        if m.sum() < 3:
            return np.inf
        T = rigid_from_points(pts[a][m], pts[b][m])
        return float(np.sqrt(np.mean(np.sum((apply_T(T, pts[a][m]) - pts[b][m]) ** 2, 1))))

    done = list(reg.registered) or [reg.neutral]
    order, left = [], [n for n in todo if n not in done]
    while left:
        best = min(left, key=lambda n: (min(dist(d, n) for d in done), todo.index(n)))
        order.append(best)
        done.append(best)
        left.remove(best)
    return order


def register_capture(capture, out=None, expressions=None, force: bool = False, options: Options | None = None,
                     progress: bool = True, log=None) -> Path:
    """Register ``capture`` (a path or :class:`Capture`); returns the registration folder."""
    from tqdm.auto import tqdm

    cap = capture if isinstance(capture, Capture) else Capture(capture)
    out = Path(out) if out is not None else cap.root / "registration"
    names = list(expressions) if expressions else cap.expression_names
    unknown = [n for n in names if n not in cap.expression_names]
    if unknown:
        raise RegistrationInputError(f"unknown expression(s): {', '.join(unknown)}")
    # --force without --expressions starts over in a new folder, swapped in when complete; with
    # --expressions only those are redone, each replacing its old registration when it is complete
    redo = set(names) if force else set()
    reg = Registrar(cap, out, options, log, fresh=force and not expressions)
    try:
        reg.writer.set_meta("options", asdict(reg.opt))
        reg.writer.set_meta("surface", surface_entry(reg.opt.curved))
        reg.writer.set_meta("hand_input_problems", reg.hand.problems)
        for n in cap.expression_names:
            if reg.writer.done(n) and n not in redo:
                reg.registered[n] = reg.writer.load(n)
        todo = [n for n in names if n not in reg.registered]
        if reg.neutral not in reg.registered and reg.neutral not in todo:
            todo.insert(0, reg.neutral)  # everything is registered relative to the neutral
        bar = tqdm(total=len(todo), desc="register", unit="expr", disable=not progress)
        if reg.neutral in todo:
            bar.set_postfix_str(reg.neutral)
            reg.register(reg.neutral)
            todo.remove(reg.neutral)
            bar.update(1)
        for n in order_expressions(reg, todo):
            bar.set_postfix_str(n)
            reg.register(n)
            bar.update(1)
        bar.close()
        reg.finish_eyes()
    except BaseException:
        reg.writer.abort()       # what was committed stays; nothing half-written does
        raise
    return reg.writer.finish()
