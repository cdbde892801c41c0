"""The registration template (Hawkins et al. 2004, §3–§5): what a user of the real system builds by
hand, here derived from the synthetic subject's truth.

A :class:`Template` holds

* **vertices**: every fiducial dot, plus extra vertices on the lip margins (upper, lower, the two
  corners), the eyelid margins, round the nostrils, one marked point per ear and one on the nose
  bridge. Each has a ``kind`` and a neutral position (head frame = world at the neutral pose); the
  *truth binding* (``part``, ``triangle``, ``bary``: a surface point of a subject part) makes its
  position exact in every expression;
* **triangles**: a triangle mesh over the face and neck (constrained Delaunay in the skin's
  parameter chart), consistently oriented (outward), with the mouth and both eye openings as holes;
* **coarse points** (18 template vertex ids, named) and the **coarse triangles** over them (indices
  into ``coarse_points``), the §4.1 coarse registration mesh;
* **regions** for §5.1 culling: ``forehead``, ``mouth``, ``neck``, ``throat``, ``chin``,
  ``cheek_left``, ``cheek_right``, ``eye_left``, ``eye_right``, ``nose`` (a partition of the vertices);
* **teeth** strips (``upper``, ``lower``): vertices in the teeth parts' rigid rest frames
  (alternating incisal edge / gum line at tooth boundaries) and two triangles per tooth;
* **eyes**: eyeball centre (head frame) and radius per eye; **holes**: the vertex loops round the
  openings.

JSON schema (``schema = "mifacerf.template/1"``)::

    {
      "schema": "mifacerf.template/1",
      "subject": str,                         # e.g. "procedural"
      "units": "m", "frame": "head (= world at the neutral head pose)",
      "vertices": [{"kind": str, "name": str, "position": [x, y, z],
                    # only with include_truth=True:
                    "part": str, "triangle": int, "bary": [b0, b1, b2]}, ...],
      "triangles": [[i, j, k], ...],           # template vertex ids, counter-clockwise from outside
      "coarse_points": [id, ...], "coarse_names": [str, ...],
      "coarse_triangles": [[a, b, c], ...],    # indices into coarse_points
      "regions": {name: [id, ...], ...},
      "holes": {"mouth": [id, ...], "eye_left": [...], "eye_right": [...]},   # boundary loops
      "teeth": {"upper": {"part": "teeth_upper", "vertices": [[x, y, z], ...], "triangles": [[...]]},
                "lower": {...}},               # in the part's rigid rest frame
      "eyes": {"eye_left": {"centre": [x, y, z], "radius": r}, "eye_right": {...}}
    }

Vertex kinds: ``dot``, ``lip_upper``, ``lip_lower``, ``lip_corner``, ``lid_upper``, ``lid_lower``,
``lid_corner``, ``nostril``, ``ear``, ``nose_bridge``.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import Delaunay

from . import head as H

SCHEMA = "mifacerf.template/1"
REGION_NAMES = ("forehead", "mouth", "neck", "throat", "chin", "cheek_left", "cheek_right",
                "eye_left", "eye_right", "nose")
COARSE_NAMES = ("forehead", "brow_L", "brow_R", "nose_bridge", "nose_tip", "cheek_L", "cheek_R",
                "ear_L", "ear_R", "mouth_corner_L", "mouth_corner_R", "philtrum", "under_lip", "chin",
                "jaw_L", "jaw_R", "throat", "neck_low")


@dataclass
class Template:
    kinds: list
    names: list
    neutral: np.ndarray                       # (T, 3)
    triangles: np.ndarray                     # (M, 3)
    coarse_points: np.ndarray                 # (18,)
    coarse_names: list
    coarse_triangles: np.ndarray              # (K, 3) into coarse_points
    regions: dict
    holes: dict
    teeth: dict                               # 'upper'/'lower' -> dict(part, vertices, triangles)
    eyes: dict                                # name -> dict(centre, radius)
    part: list | None = None                  # truth binding
    tri: np.ndarray | None = None
    bary: np.ndarray | None = None
    subject: str = "procedural"
    extra: dict = field(default_factory=dict)
    #: name -> {"vertices": ids, "mode": "rigid"|"driven", "anchor": "head"|"body", "falloff": m, "region"}
    extensions: dict = field(default_factory=dict)

    @property
    def n_vertices(self) -> int:
        return len(self.kinds)

    @property
    def dot_ids(self) -> np.ndarray:
        return np.array([i for i, k in enumerate(self.kinds) if k == "dot"], int)

    @property
    def extension_ids(self) -> np.ndarray:
        """Template ids of every extension vertex (sorted)."""
        ids = [np.asarray(e["vertices"], int) for e in self.extensions.values()]
        return np.unique(np.concatenate(ids)) if ids else np.zeros(0, int)

    @property
    def face_triangles(self) -> np.ndarray:
        """The triangles of the face alone: the mesh over the fiducials (those before the extensions' when
        this template made them; read from JSON: those with no extension vertex)."""
        T = np.asarray(self.triangles, int)
        if "n_face_triangles" in self.extra:
            return T[:self.extra["n_face_triangles"]]
        ext = np.zeros(len(self.kinds), bool)
        ext[self.extension_ids] = True
        return T[~ext[T].any(1)]

    @property
    def coarse_triangles_template(self) -> np.ndarray:
        """Coarse triangles as template vertex ids."""
        return np.asarray(self.coarse_points)[self.coarse_triangles]

    def has_truth(self) -> bool:
        return self.tri is not None

    def positions(self, skin_vertices, parts=None, skin_faces=None) -> np.ndarray:
        """Exact positions in one pose from the truth binding (skin vertices (V, 3) of that pose;
        ``parts`` maps part names to objects with ``vertices`` and ``faces``)."""
        if self.tri is None:
            raise ValueError("this template has no truth binding (loaded without include_truth)")
        out = np.zeros((len(self.kinds), 3))
        F = skin_faces if skin_faces is not None else self.extra["skin_faces"]
        part = np.asarray(self.part)
        sk = part == "skin"
        out[sk] = np.einsum("nk,nkj->nj", self.bary[sk], skin_vertices[F[self.tri[sk]]])
        for name in set(part[~sk]):
            m = part == name
            pv, pf = parts[name].vertices, parts[name].faces
            out[m] = np.einsum("nk,nkj->nj", self.bary[m], pv[pf[self.tri[m]]])
        return out

    def teeth_positions(self, transforms: dict) -> dict:
        """Teeth strip vertices in world for a pose's transforms ('teeth_upper', 'teeth_lower')."""
        out = {}
        for k, t in self.teeth.items():
            T = transforms[t["part"]]
            out[k] = np.asarray(t["vertices"]) @ T[:3, :3].T + T[:3, 3]
        return out

    # ------------------------------------------------------------------------------------------
    def to_json(self, include_truth: bool = False, indent=None) -> str:
        verts = []
        for i, (k, n) in enumerate(zip(self.kinds, self.names)):
            v = {"kind": k, "name": n, "position": [float(c) for c in self.neutral[i]]}
            if include_truth:
                if self.tri is None:
                    raise ValueError("no truth binding to include")
                v.update(part=str(self.part[i]), triangle=int(self.tri[i]),
                         bary=[float(b) for b in self.bary[i]])
            verts.append(v)
        doc = {
            "schema": SCHEMA, "subject": self.subject, "units": "m",
            "frame": "head (= world at the neutral head pose)",
            "vertices": verts,
            "triangles": np.asarray(self.triangles, int).tolist(),
            "coarse_points": [int(i) for i in self.coarse_points],
            "coarse_names": list(self.coarse_names),
            "coarse_triangles": np.asarray(self.coarse_triangles, int).tolist(),
            "regions": {k: [int(i) for i in v] for k, v in self.regions.items()},
            "holes": {k: [int(i) for i in v] for k, v in self.holes.items()},
            "teeth": {k: {"part": t["part"], "vertices": np.asarray(t["vertices"], float).tolist(),
                          "triangles": np.asarray(t["triangles"], int).tolist()}
                      for k, t in self.teeth.items()},
            "eyes": {k: {"centre": [float(c) for c in e["centre"]], "radius": float(e["radius"])}
                     for k, e in self.eyes.items()},
        }
        if self.extensions:
            doc["extensions"] = extensions_to_json(self.extensions)
        return json.dumps(doc, indent=indent)

    @classmethod
    def from_json(cls, text: str) -> "Template":
        d = json.loads(text)
        if d.get("schema") != SCHEMA:
            raise ValueError(f"not a {SCHEMA} document (schema={d.get('schema')!r})")
        vs = d["vertices"]
        truth = all("triangle" in v for v in vs) and len(vs) > 0
        return cls(
            kinds=[v["kind"] for v in vs], names=[v.get("name", "") for v in vs],
            neutral=np.array([v["position"] for v in vs], float).reshape(-1, 3),
            triangles=np.array(d["triangles"], int).reshape(-1, 3),
            coarse_points=np.array(d["coarse_points"], int),
            coarse_names=list(d["coarse_names"]),
            coarse_triangles=np.array(d["coarse_triangles"], int).reshape(-1, 3),
            regions={k: np.array(v, int) for k, v in d["regions"].items()},
            holes={k: np.array(v, int) for k, v in d.get("holes", {}).items()},
            teeth={k: {"part": t["part"], "vertices": np.array(t["vertices"], float).reshape(-1, 3),
                       "triangles": np.array(t["triangles"], int).reshape(-1, 3)}
                   for k, t in d.get("teeth", {}).items()},
            eyes={k: {"centre": np.array(e["centre"], float), "radius": float(e["radius"])}
                  for k, e in d.get("eyes", {}).items()},
            part=[v["part"] for v in vs] if truth else None,
            tri=np.array([v["triangle"] for v in vs], int) if truth else None,
            bary=np.array([v["bary"] for v in vs], float) if truth else None,
            subject=d.get("subject", ""),
            extensions={k: dict(e, vertices=np.array(e["vertices"], int)) for k, e in (d.get("extensions") or {}).items()},
        )


def extensions_to_json(extensions: dict) -> dict:
    """The template's ``extensions`` member (docs/registration.md): per name its vertex ids, mode, anchor,
    falloff (driven) and region."""
    out = {}
    for k, e in extensions.items():
        d = {"vertices": [int(i) for i in e["vertices"]], "mode": str(e.get("mode", "rigid")),
             "anchor": str(e.get("anchor", "head")), "region": str(e.get("region", k))}
        if "falloff" in e:
            d["falloff"] = float(e["falloff"])
        out[k] = d
    return out


# --------------------------------------------------------------------------------------------
# triangulation helpers
# --------------------------------------------------------------------------------------------
def _angles(P2):
    """Interior angles (M, 3) of triangles given as (M, 3, 2) or (M, 3, 3) points."""
    a = np.linalg.norm(P2[:, 1] - P2[:, 2], axis=1)
    b = np.linalg.norm(P2[:, 2] - P2[:, 0], axis=1)
    c = np.linalg.norm(P2[:, 0] - P2[:, 1], axis=1)
    A = np.arccos(np.clip((b * b + c * c - a * a) / np.maximum(2 * b * c, 1e-30), -1, 1))
    B = np.arccos(np.clip((a * a + c * c - b * b) / np.maximum(2 * a * c, 1e-30), -1, 1))
    return np.stack([A, B, np.pi - A - B], 1)


def triangle_quality(P, T):
    """Min and max interior angles (degrees) of triangles ``T`` over points ``P`` (2-D or 3-D)."""
    ang = np.degrees(_angles(P[T]))
    return ang.min(axis=1), ang.max(axis=1)


def _point_in_poly(pts, poly):
    x, y = pts[:, 0], pts[:, 1]
    inside = np.zeros(len(pts), bool)
    n = len(poly)
    for i in range(n):
        x1, y1 = poly[i]
        x2, y2 = poly[(i + 1) % n]
        cond = ((y1 > y) != (y2 > y)) & (x < (x2 - x1) * (y - y1) / np.where(y2 == y1, 1e-30, y2 - y1) + x1)
        inside ^= cond
    return inside


def _boundary_edges(T):
    e = np.concatenate([T[:, [0, 1]], T[:, [1, 2]], T[:, [2, 0]]])
    tid = np.tile(np.arange(len(T)), 3)
    key = np.sort(e, axis=1)
    _, inv, cnt = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    inv = inv.ravel()
    return tid[cnt[inv] == 1], e[cnt[inv] == 1]


def delaunay_with_holes(X, holes, peel_ratio=2.6, max_edge=None):
    """Delaunay of chart points ``X`` (n, 2); drop triangles inside ``holes`` (lists of vertex-id
    loops) and peel thin triangles off the outer boundary. Returns (triangles (M, 3) CCW, kept mask
    over the full Delaunay's simplices, the Delaunay object)."""
    dl = Delaunay(X)
    T = dl.simplices.copy()
    keep = np.ones(len(T), bool)
    cen = X[T].mean(axis=1)
    for loop in holes:
        keep &= ~_point_in_poly(cen, X[np.asarray(loop)])
    # triangles using only hole-boundary vertices of one hole that span it are also inside: the
    # centroid test covers them; peel slivers on the outer boundary
    med = np.median(np.linalg.norm(X[T[:, 0]] - X[T[:, 1]], axis=1))
    hole_verts = set(int(i) for loop in holes for i in loop)
    for _ in range(50):
        Tk = np.nonzero(keep)[0]
        bt, be = _boundary_edges(T[Tk])
        changed = False
        for t_local, e in zip(bt, be):
            t = Tk[t_local]
            if int(e[0]) in hole_verts and int(e[1]) in hole_verts:
                continue
            P = X[T[t]]
            mn = np.degrees(_angles(P[None])[0]).min()
            mx = np.degrees(_angles(P[None])[0]).max()
            L = np.linalg.norm(X[e[0]] - X[e[1]])
            if mn < 18.0 or mx > 125.0 or L > peel_ratio * med or (max_edge and L > max_edge):
                keep[t] = False
                changed = True
        if not changed:
            break
    T = T[keep]
    # counter-clockwise
    P = X[T]
    cross = (P[:, 1, 0] - P[:, 0, 0]) * (P[:, 2, 1] - P[:, 0, 1]) - (P[:, 1, 1] - P[:, 0, 1]) * (P[:, 2, 0] - P[:, 0, 0])
    T[cross < 0] = T[cross < 0][:, [0, 2, 1]]
    return T, keep, dl


# --------------------------------------------------------------------------------------------
# the procedural subject's template
# --------------------------------------------------------------------------------------------
def _vertex_binding(F, vids):
    """(tri, bary) for skin vertices: an incident face with a one-hot barycentric."""
    flat = np.asarray(F).ravel()
    order = np.argsort(flat, kind="stable")
    sv = flat[order]
    vids = np.asarray(vids, int)
    pos = np.searchsorted(sv, vids)
    if np.any(pos >= len(sv)) or np.any(sv[np.minimum(pos, len(sv) - 1)] != vids):
        raise ValueError("vertex not used by any face")
    corner = order[pos]
    tri = corner // 3
    bary = np.zeros((len(vids), 3))
    bary[np.arange(len(vids)), corner % 3] = 1.0
    return tri.astype(int), bary


class SkinChart:
    """2-D chart of the skin's parameter grid: x = azimuth × row radius, y = −arc length down the
    front meridian (metres, roughly isometric on the face and neck)."""

    def __init__(self, grid, rest):
        self.grid = grid
        R = grid.n_rows
        P = rest[grid.grid_index]                          # (R, C, 3)
        front = np.abs(grid.phis) < np.radians(60)
        rho = np.hypot(P[..., 0], P[..., 2] - H.AXIS_Z)
        self.rho_row = np.median(rho[:, front], axis=1)
        self.row_arc = grid.row_arc
        self.phis = grid.phis

    def rc_to_xy(self, rc):
        r = np.clip(rc[:, 0], 0, self.grid.n_rows - 1)
        c = rc[:, 1]
        phi = np.interp(c, np.arange(len(self.phis)), self.phis)
        rho = np.interp(r, np.arange(len(self.rho_row)), self.rho_row)
        arc = np.interp(r, np.arange(len(self.row_arc)), self.row_arc)
        return np.stack([phi * rho, -arc], 1)

    def points(self, F, tri, bary):
        rc = np.einsum("nk,nkj->nj", bary, self.grid.vertex_rc[F[tri]])
        return self.rc_to_xy(rc)


MARKED_TARGETS = (
    ("nostril", "nostril_L", (0.0068, -0.0460, 0.0975)),
    ("nostril", "alar_base_L", (0.0190, -0.0420, 0.0840)),
    ("nostril", "nostril_R", (-0.0068, -0.0460, 0.0975)),
    ("nostril", "alar_base_R", (-0.0190, -0.0420, 0.0840)),
    ("ear", "ear_L", (0.0820, -0.0060, -0.0040)),
    ("ear", "ear_R", (-0.0820, -0.0060, -0.0040)),
    ("nose_bridge", "nose_bridge", (0.0, 0.0070, 0.0900)),
)


def marked_vertices(neutral):
    """(kind, name, skin vertex id) of the template's marked non-dot points (nearest neutral vertex
    to anatomical targets: round the nostrils, one per ear, the nose bridge)."""
    out = []
    for kind, name, tgt in MARKED_TARGETS:
        out.append((kind, name, int(np.argmin(np.linalg.norm(neutral - np.asarray(tgt), axis=1)))))
    return out


def flip_improve(P3, X2, T, max_passes=60):
    """Intrinsic-Delaunay edge flips on 3-D positions: flip an interior edge when the two angles
    opposite it sum to more than π, if the flipped pair is valid (positive area in the 2-D chart
    ``X2``, no fold in 3-D; without a chart, ``X2=None``, both new triangles face within 60° of the
    old pair's normal). Boundary (hole and outer) edges never flip; orientation is kept.
    Each sweep flips non-adjacent edges in one go; sweeps repeat until none applies."""
    T = np.array(T, int)

    def angle(p, a, b):
        u, v = a - p, b - p
        c = np.einsum("ij,ij->i", u, v) / (np.linalg.norm(u, axis=1) * np.linalg.norm(v, axis=1) + 1e-30)
        return np.arccos(np.clip(c, -1.0, 1.0))

    for _ in range(max_passes):
        # directed edges -> (triangle, opposite vertex)
        e_u = T.ravel()
        e_v = np.roll(T, -1, axis=1).ravel()
        opp = np.roll(T, -2, axis=1).ravel()
        tri = np.repeat(np.arange(len(T)), 3)
        key = {(int(u), int(v)): i for i, (u, v) in enumerate(zip(e_u, e_v))}
        i1, i2 = [], []
        for i, (u, v) in enumerate(zip(e_u, e_v)):
            j = key.get((int(v), int(u)))
            if j is not None and u < v:
                i1.append(i)
                i2.append(j)
        i1, i2 = np.array(i1, int), np.array(i2, int)
        u, v, c, d = e_u[i1], e_v[i1], opp[i1], opp[i2]
        tot = angle(P3[c], P3[u], P3[v]) + angle(P3[d], P3[u], P3[v])
        order = np.nonzero(tot > np.pi + 1e-9)[0]
        order = order[np.argsort(-tot[order])]      # worst first
        if len(order) == 0:
            break
        touched = np.zeros(len(T), bool)
        flipped = 0
        for k in order:
            t1, t2 = tri[i1[k]], tri[i2[k]]
            if touched[t1] or touched[t2]:
                continue
            uu, vv, cc, dd = int(u[k]), int(v[k]), int(c[k]), int(d[k])
            n1, n2 = (uu, dd, cc), (dd, vv, cc)       # quad u-d-v-c, counter-clockwise

            def area2(tr):
                p = X2[list(tr)]
                return (p[1, 0] - p[0, 0]) * (p[2, 1] - p[0, 1]) - (p[1, 1] - p[0, 1]) * (p[2, 0] - p[0, 0])

            if X2 is not None and (area2(n1) <= 0 or area2(n2) <= 0):
                continue
            nn1 = np.cross(P3[n1[1]] - P3[n1[0]], P3[n1[2]] - P3[n1[0]])
            nn2 = np.cross(P3[n2[1]] - P3[n2[0]], P3[n2[2]] - P3[n2[0]])
            if nn1 @ nn2 <= 0:
                continue
            if X2 is None:      # no chart: the new pair must face the way the old pair did
                old = np.cross(P3[T[t1][1]] - P3[T[t1][0]], P3[T[t1][2]] - P3[T[t1][0]]) + \
                    np.cross(P3[T[t2][1]] - P3[T[t2][0]], P3[T[t2][2]] - P3[T[t2][0]])
                unit = lambda v: v / max(np.linalg.norm(v), 1e-30)  # noqa: E731
                if min(unit(nn1) @ unit(old), unit(nn2) @ unit(old)) < 0.5:
                    continue
            T[t1], T[t2] = n1, n2
            touched[t1] = touched[t2] = True
            flipped += 1
        if not flipped:
            break
    return T


def improve(P3, X2, T):
    """:func:`flip_improve` (kept as the public name used by the mesh subject)."""
    return flip_improve(P3, X2, T)


def build_template(subj, extensions: bool = True, **extension_options) -> Template:
    """The procedural subject's template: the face mesh over the fiducials and marked points and, with
    ``extensions`` (default), the scalp, ears, sides and neck down to a cut
    (:func:`.template_extensions.add_extensions`; ``extension_options`` e.g. ``neck_cut_y``, ``spacing``)."""
    grid = subj.grid
    F = subj.skin_faces
    Vn = subj.neutral_skin
    chart = SkinChart(grid, grid.vertices)

    kinds, names, tri_l, bary_l = [], [], [], []

    def add(kind, name, tri, bary):
        kinds.append(kind)
        names.append(name)
        tri_l.append(int(tri))
        bary_l.append(np.asarray(bary, float))
        return len(kinds) - 1

    for t, b, n in zip(subj.dot_tri, subj.dot_bary, subj.dot_names):
        add("dot", n, t, b)
    opening = {}   # chart offsets to open the slits

    # lip margins: every other inner column (densified below if a hole edge is missing)
    holes = {}
    ms = grid.slits["mouth"]
    hw = subj.rig.mouth_half_width
    ids = {}
    for v, kind, nm in ((ms.corners[0], "lip_corner", "mouth_corner_R"), (ms.corners[1], "lip_corner", "mouth_corner_L")):
        t, b = _vertex_binding(F, [v])
        ids[v] = add(kind, nm, t[0], b[0])
    sel = np.arange(1, len(ms.upper), 2) if len(ms.upper) > 4 else np.arange(len(ms.upper))
    for kind, arr in (("lip_upper", ms.upper), ("lip_lower", ms.lower)):
        t, b = _vertex_binding(F, arr[sel])
        for v, tt, bb in zip(arr[sel], t, b):
            ids[int(v)] = add(kind, "", tt, bb)
            x = grid.vertices[v, 0]
            opening[ids[int(v)]] = (0.0012 if kind == "lip_upper" else -0.0012) * max(0.15, 1 - (x / hw) ** 2) ** 0.5
    holes["mouth"] = [ids[ms.corners[0]]] + [ids[int(v)] for v in ms.upper[sel]] + \
                     [ids[ms.corners[1]]] + [ids[int(v)] for v in ms.lower[sel][::-1]]

    for eye in ("eye_left", "eye_right"):
        es = grid.slits[eye]
        sfx = "L" if eye == "eye_left" else "R"
        ids = {}
        for v in es.corners:
            t, b = _vertex_binding(F, [v])
            ids[v] = add("lid_corner", f"{eye}_corner", t[0], b[0])
        sel = np.arange(len(es.upper))
        sel = sel[1::2] if len(sel) > 8 else sel
        xs = grid.vertices[es.upper[sel], 0]
        xm, xr = 0.5 * (xs.min() + xs.max()), 0.5 * (xs.max() - xs.min()) + 1e-9
        for kind, arr, amp in (("lid_upper", es.upper, 0.0030), ("lid_lower", es.lower, -0.0020)):
            t, b = _vertex_binding(F, arr[sel])
            for v, tt, bb in zip(arr[sel], t, b):
                ids[int(v)] = add(kind, "", tt, bb)
                x = grid.vertices[v, 0]
                opening[ids[int(v)]] = amp * max(0.15, 1 - ((x - xm) / (1.15 * xr)) ** 2) ** 0.5
        holes[eye] = [ids[es.corners[0]]] + [ids[int(v)] for v in es.upper[sel]] + \
                     [ids[es.corners[1]]] + [ids[int(v)] for v in es.lower[sel][::-1]]

    # nostrils, ears, nose bridge: marked skin vertices
    for kind, nm, v in marked_vertices(Vn):
        t, b = _vertex_binding(F, [v])
        add(kind, nm, t[0], b[0])

    tri = np.array(tri_l, int)
    bary = np.array(bary_l)
    neutral = np.einsum("nk,nkj->nj", bary, Vn[F[tri]])
    X = chart.points(F, tri, bary)
    for i, off in opening.items():
        X[i, 1] += off
    T, keep, dl = delaunay_with_holes(X, list(holes.values()))
    T = improve(neutral, X, T)
    T = _peel3d(neutral, T, holes)

    # coarse points
    by_name = {n: i for i, n in enumerate(names) if n}
    coarse = np.array([by_name[n] for n in COARSE_NAMES], int)
    Tc, _, _ = delaunay_with_holes(X[coarse], [], peel_ratio=3.0)

    regions = assign_regions(neutral, kinds)
    teeth = {}
    from .parts import LOWER, UPPER, teeth_strip

    for k, spec, part in (("upper", UPPER, "teeth_upper"), ("lower", LOWER, "teeth_lower")):
        tv, tf = teeth_strip(spec)
        teeth[k] = {"part": part, "vertices": tv, "triangles": tf}
    eyes = {n: {"centre": subj.eye_centres[n], "radius": subj.eye_radius} for n in ("eye_left", "eye_right")}
    tpl = Template(kinds, names, neutral, T, coarse, list(COARSE_NAMES), Tc, regions, holes, teeth, eyes,
                   ["skin"] * len(kinds), tri, bary, "procedural",
                   extra={"skin_faces": F, "chart": X, "delaunay": dl, "delaunay_keep": keep})
    if extensions:
        from .template_extensions import add_extensions

        tpl = add_extensions(tpl, Vn, F, **extension_options)
        new = tpl.tri[len(X):]
        tpl.extra["chart"] = np.concatenate([X, chart.points(F, new, tpl.bary[len(X):])])
    return tpl


def _peel3d(P3, T, holes, min_angle=12.0, max_angle=145.0):
    """Drop bad triangles on the outer boundary (3-D angles), repeatedly."""
    hole_verts = set(int(i) for loop in holes.values() for i in loop)
    T = np.asarray(T)
    for _ in range(20):
        bt, be = _boundary_edges(T)
        mn, mx = triangle_quality(P3, T)
        bad = set()
        for t, e in zip(bt, be):
            if int(e[0]) in hole_verts and int(e[1]) in hole_verts:
                continue
            if mn[t] < min_angle or mx[t] > max_angle:
                bad.add(int(t))
        if not bad:
            break
        T = np.delete(T, sorted(bad), axis=0)
    return T


def assign_regions(P, kinds) -> dict:
    """Partition template vertices into the §5.1 culling regions from neutral positions."""
    x, y, z = P[:, 0], P[:, 1], P[:, 2]
    out = {k: [] for k in REGION_NAMES}
    for i in range(len(P)):
        k = kinds[i]
        xi, yi, zi = x[i], y[i], z[i]
        if k.startswith("lip"):
            r = "mouth"
        elif k.startswith("lid"):
            r = "eye_left" if xi > 0 else "eye_right"
        elif k == "nostril" or k == "nose_bridge":
            r = "nose"
        elif yi < -0.105 or (yi < -0.085 and zi < 0.045):
            r = "throat" if (abs(np.arctan2(xi, zi - H.AXIS_Z)) < np.radians(38)) else "neck"
        elif yi > 0.034:
            r = "forehead"
        elif abs(xi) < 0.016 and -0.050 < yi < 0.012 and zi > 0.07:
            r = "nose"
        elif np.linalg.norm(P[i] - H.EYE_CENTRE * np.array([np.sign(xi) or 1, 1, 1])) < 0.030 and yi > -0.010:
            r = "eye_left" if xi > 0 else "eye_right"
        elif abs(xi) < 0.036 and H.Y_MOUTH - 0.013 < yi < -0.044 and zi > 0.05:
            r = "mouth"
        elif abs(xi) < 0.036 and yi <= H.Y_MOUTH - 0.013 and zi > 0.04:
            r = "chin"
        else:
            r = "cheek_left" if xi > 0 else "cheek_right"
        out[r].append(i)
    return {k: np.array(v, int) for k, v in out.items()}
