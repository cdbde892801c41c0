"""Template extensions for a synthetic subject: the surfaces the cameras see beyond the fiducials
(paper §3 "extensions"; issue 16) — scalp and hair cap, ears, the neck down to a cut, the sides and
the back of the head — meshed on the subject's skin and stitched to the face template's border.

What a user of the real system builds by hand around the dots (a mesh over the scalp, the ears and
the neck sharing the face mesh's border vertices), here made from a skin surface and nothing else,
so it serves the procedural subject (:func:`mifacerf.synthetic.template.build_template`) and any
bring-your-own skin mesh alike (:func:`add_extensions`).

Method (all lengths metres, head frame):

1. **Where**: skin vertices above the neck cut (``neck_cut_y``), within ``max_azimuth_deg`` of the
   front about the vertical axis through the skin's centroid (what a ring of capture cameras in
   front can see; ``seen`` overrides it with any per-vertex mask), and not covered by the face
   template (closest point on the face mesh inside it, or on a mouth/eye opening's rim).
2. **Samples**: greedy Poisson-disc sampling of those skin vertices at ``spacing`` (``ear_spacing``
   within ``ear_radius`` of an ear mark), the region's outer border (the cut, the azimuth limit)
   first so the cut is a clean row; nothing closer than 0.75 spacing to the face's border vertices.
3. **Mesh**: the dual of the geodesic Voronoi diagram of the samples and the face's border vertices
   on the skin's edge graph (a triangle wherever three cells meet, oriented as the skin), so the
   extension shares the face's border vertices (no gap) and fills the notches of its jagged edge;
   non-manifold triangles are dropped and small holes filled by ear clipping.
4. **Extensions** (each its own region; modes per :mod:`mifacerf.registration.extensions`):
   ``ear_left`` / ``ear_right`` (rigid; near the ear marks), ``neck_lower`` (below ``neck_top_y``:
   driven by the neck fiducials, anchored to the body beyond the falloff — the neck's base does not
   turn with the head), ``border_left`` / ``border_right`` (within ``border`` of a fiducial: temple,
   the hairline, the jaw's underside; driven, anchored to the head) and ``scalp`` (the rest: rigid).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

NECK_CUT_Y = -0.216        #: default cut of the neck (m, head frame; the procedural neck ends at -0.22)
SPACING = 0.014            #: sample spacing of the extension mesh (m)
EAR_SPACING = 0.005        #: ... near the ears
EAR_RADIUS = 0.035         #: ... within this of an ear mark
MAX_AZIMUTH_DEG = 180.0    #: the back of the head beyond this azimuth (from the front) is left out
BORDER = 0.022             #: extension vertices this near a fiducial are driven by them
NECK_TOP_DROP = 0.105      #: the lower neck starts this far below the ear marks
FALLOFF = {"border": 0.03, "neck_lower": 0.06}

#: (name, mode, anchor) of the extensions this module makes, in order
EXTENSION_KINDS = (("scalp", "rigid", "head"), ("ear_left", "rigid", "head"), ("ear_right", "rigid", "head"),
                   ("border_left", "driven", "head"), ("border_right", "driven", "head"),
                   ("neck_lower", "driven", "body"))


@dataclass
class ExtensionMesh:
    """What :func:`extension_mesh` makes: ``skin_vertices`` (E,) the skin vertex each new template
    vertex sits on (positions ``positions`` (E, 3)); ``triangles`` (M, 3) over template ids, the new
    vertices numbered ``n_face ..``; ``extensions`` {name: {"vertices", "mode", "anchor", "falloff"}}
    (template ids); ``report``: counts, holes filled, triangles dropped."""

    skin_vertices: np.ndarray
    positions: np.ndarray
    triangles: np.ndarray
    extensions: dict
    report: dict


def _edges(F):
    e = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    return np.unique(np.sort(e, axis=1), axis=0)


def outer_border(face_tri, holes) -> tuple[np.ndarray, np.ndarray]:
    """(directed boundary edges (B, 2) of the face mesh that are not on a mouth/eye opening, their
    vertices). An edge whose two ends lie on one opening's loop is the opening's."""
    F = np.asarray(face_tri, np.int64)
    d = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    key = {(int(a), int(b)) for a, b in d}
    bnd = np.array([(a, b) for a, b in d if (int(b), int(a)) not in key], np.int64).reshape(-1, 2)
    hole_of = {}
    for k, loop in enumerate((holes or {}).values()):
        for v in loop:
            hole_of[int(v)] = k
    keep = [not (int(a) in hole_of and hole_of.get(int(b)) == hole_of[int(a)]) for a, b in bnd]
    bnd = bnd[np.asarray(keep, bool)] if len(bnd) else bnd
    return bnd, np.unique(bnd)


def _closest_on_triangles(P, A, B, C):
    """Closest points of P (N, 3) on triangles (N, 3) each: (distance (N,), barycentrics (N, 3))."""
    from ..geometry.ericson2004 import region_barycentrics

    ab, ac = B - A, C - A
    ap, bp, cp = P - A, P - B, P - C
    dot = lambda u, v: np.einsum("ij,ij->i", u, v)  # noqa: E731
    u, v, w = region_barycentrics(dot(ab, ap), dot(ac, ap), dot(ab, bp), dot(ac, bp), dot(ab, cp), dot(ac, cp),
                                  np.where)
    Q = u[:, None] * A + v[:, None] * B + w[:, None] * C
    return np.linalg.norm(P - Q, axis=1), np.stack([u, v, w], 1)


def face_covered(points, face_pos, face_tri, holes, inside_tol: float = 0.008, hole_tol: float = 0.02,
                 k: int = 10) -> np.ndarray:
    """(N,) bool: points (skin vertices) the face template covers — their closest point on the face mesh
    lies inside it (not on its outer border) within ``inside_tol``, or on a mouth/eye opening's rim
    within ``hole_tol`` (the lips' and lids' inner skin)."""
    from scipy.spatial import cKDTree

    P = np.asarray(points, np.float64)
    X = np.asarray(face_pos, np.float64)
    F = np.asarray(face_tri, np.int64)
    bnd, bverts = outer_border(F, holes)
    bset = {tuple(sorted((int(a), int(b)))) for a, b in bnd}
    on_border_vertex = np.zeros(len(X), bool)
    on_border_vertex[bverts] = True
    hole_vertex = np.zeros(len(X), bool)
    for loop in (holes or {}).values():
        hole_vertex[np.asarray(loop, np.int64)] = True
    k = min(k, len(F))
    _, cand = cKDTree(X[F].mean(axis=1)).query(P, k=k)
    cand = cand.reshape(len(P), k)
    best_d = np.full(len(P), np.inf)
    best_t = np.zeros(len(P), np.int64)
    best_b = np.zeros((len(P), 3))
    for j in range(k):
        t = cand[:, j]
        d, b = _closest_on_triangles(P, X[F[t, 0]], X[F[t, 1]], X[F[t, 2]])
        better = d < best_d - 1e-12
        best_d[better], best_t[better], best_b[better] = d[better], t[better], b[better]
    tri = F[best_t]
    zero = best_b < 1e-9
    nz = zero.sum(1)
    border = np.zeros(len(P), bool)
    rim = np.zeros(len(P), bool)
    one = np.flatnonzero(nz == 1)          # on an edge: the one opposite the zero corner
    if one.size:
        c = np.argmax(zero[one], axis=1)
        a, b = tri[one, (c + 1) % 3], tri[one, (c + 2) % 3]
        border[one] = [tuple(sorted((int(x), int(y)))) in bset for x, y in zip(a, b)]
        rim[one] = hole_vertex[a] & hole_vertex[b]
    two = np.flatnonzero(nz >= 2)          # on a corner
    if two.size:
        v = tri[two, np.argmin(zero[two], axis=1)]
        border[two] = on_border_vertex[v]
        rim[two] = hole_vertex[v]
    return (~border & (best_d < inside_tol)) | (rim & (best_d < hole_tol))


def _poisson(P, order, radius, blocked) -> np.ndarray:
    """Greedy Poisson-disc selection of ``P`` in ``order``: a point is taken unless a taken point lies
    within that one's ``radius``; ``blocked`` (N,) bool points are never taken."""
    from scipy.spatial import cKDTree

    tree = cKDTree(P)
    dead = np.asarray(blocked, bool).copy()
    taken = []
    for i in order:
        if dead[i]:
            continue
        taken.append(int(i))
        dead[tree.query_ball_point(P[i], radius[i])] = True
    return np.asarray(taken, np.int64)


def boundary_loops(F) -> list:
    """Simple boundary loops (vertex ids in the faces' winding order) of a triangle mesh ``F`` (M, 3): the
    boundary walked edge by edge, each closed walk split at the vertices it passes twice (where loops
    touch or a boundary is pinched)."""
    F = np.asarray(F, np.int64).reshape(-1, 3)
    dset = {(int(a), int(b)) for a, b in np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])}
    directed = [(a, b) for a, b in dset if (b, a) not in dset]
    out = {}
    for a, b in directed:
        out.setdefault(int(a), []).append(int(b))
    loops = []
    for start in list(out):
        while out.get(start):
            walk, v = [start], out[start].pop()
            while v != start and out.get(v):
                walk.append(v)
                v = out[v].pop()
            if v != start:
                break
            stack, pos = [], {}
            for u in walk:                      # split at repeated vertices
                if u in pos:
                    k = pos[u]
                    loops.append(stack[k:])
                    for w in stack[k:]:
                        pos.pop(w, None)
                    del stack[k:]
                pos[u] = len(stack)
                stack.append(u)
            if len(stack) >= 3:
                loops.append(stack)
    return [lp for lp in loops if len(lp) >= 3]


def _ear_clip(P3, loop) -> list:
    """Triangles filling a small hole bounded by ``loop`` (vertex ids, in the order of the boundary's
    half-edges, so the fill uses them reversed): ear clipping in the loop's best-fit plane."""
    Q = P3[loop] - P3[loop].mean(0)
    _, _, vt = np.linalg.svd(Q, full_matrices=False)
    xy = Q @ vt[:2].T
    idx = list(range(len(loop)))
    area = 0.5 * np.sum(xy[:, 0] * np.roll(xy[:, 1], -1) - np.roll(xy[:, 0], -1) * xy[:, 1])
    sign = -1.0 if area > 0 else 1.0        # the fill runs against the boundary's direction
    out = []

    def cross(o, a, b):
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    guard = 0
    while len(idx) > 3 and guard < 200:
        guard += 1
        for j in range(len(idx)):
            i0, i1, i2 = idx[j - 1], idx[j], idx[(j + 1) % len(idx)]
            if sign * cross(xy[i0], xy[i2], xy[i1]) <= 1e-14:
                continue
            tri = (xy[i0], xy[i2], xy[i1])
            inside = False
            for m in idx:
                if m in (i0, i1, i2):
                    continue
                s1, s2, s3 = cross(tri[0], tri[1], xy[m]), cross(tri[1], tri[2], xy[m]), cross(tri[2], tri[0], xy[m])
                if (s1 > 0 and s2 > 0 and s3 > 0) or (s1 < 0 and s2 < 0 and s3 < 0):
                    inside = True
                    break
            if not inside:
                out.append((loop[i0], loop[i2], loop[i1]))
                idx.pop(j)
                break
        else:
            break
    if len(idx) == 3:
        out.append((loop[idx[0]], loop[idx[2]], loop[idx[1]]))
    return out


def _clean(P3, face_tri, ext_tri, holes, max_hole: int, max_perimeter: float, on_rim=None) -> tuple[np.ndarray, dict]:
    """Drop extension triangles on non-manifold or wrongly oriented edges; fill small holes."""
    F = np.asarray(face_tri, np.int64)
    E = np.asarray(ext_tri, np.int64).reshape(-1, 3)
    dropped = 0
    face_dir = {(int(a), int(b)) for t in F for a, b in ((t[0], t[1]), (t[1], t[2]), (t[2], t[0]))}
    for _ in range(10):
        allt = np.concatenate([F, E])
        d = np.concatenate([allt[:, [0, 1]], allt[:, [1, 2]], allt[:, [2, 0]]])
        und = np.sort(d, axis=1)
        _, inv_d, cnt_d = np.unique(d, axis=0, return_inverse=True, return_counts=True)
        _, inv_u, cnt_u = np.unique(und, axis=0, return_inverse=True, return_counts=True)
        bad_edge = (cnt_d[inv_d.ravel()] > 1) | (cnt_u[inv_u.ravel()] > 2)
        tri_bad = bad_edge.reshape(3, -1).any(0)[len(F):]
        if not tri_bad.any():
            break
        dropped += int(tri_bad.sum())
        E = E[~tri_bad]
    hole_sets = [set(int(v) for v in loop) for loop in (holes or {}).values()]
    filled = 0
    loops = boundary_loops(np.concatenate([F, E]))
    on_rim = np.zeros(len(P3), bool) if on_rim is None else on_rim
    if loops:
        new = []
        for loop in loops:
            if len(loop) > max_hole or set(loop) in hole_sets or on_rim[loop].any():
                continue
            if any(set(loop) <= h for h in hole_sets):
                continue
            per = np.sum(np.linalg.norm(P3[loop] - P3[np.roll(loop, -1)], axis=1))
            if per > max_perimeter:
                continue
            tris = _ear_clip(P3, loop)
            if tris and all((int(a), int(b)) not in face_dir for t in tris for a, b in ((t[0], t[1]),)):
                new.extend(tris)
                filled += 1
        if new:
            E = np.concatenate([E, np.asarray(new, np.int64)])
    return E, {"triangles_dropped": dropped, "holes_filled": filled}


def _fill_notches(face_tri, ext_tri, on_rim, passes: int = 3) -> tuple[np.ndarray, int]:
    """Straighten the outer border (the cut): where the border runs rim sample ``a`` → inner vertex ``i`` →
    rim sample ``b``, the triangle (i, a, b) closes the notch."""
    F = np.asarray(face_tri, np.int64)
    E = np.asarray(ext_tri, np.int64).reshape(-1, 3)
    added = 0
    for _ in range(passes):
        allt = np.concatenate([F, E])
        d = np.concatenate([allt[:, [0, 1]], allt[:, [1, 2]], allt[:, [2, 0]]])
        dset = {(int(a), int(b)) for a, b in d}
        und = {tuple(sorted(e)) for e in dset}
        inc, out = {}, {}
        for a, b in dset:
            if (b, a) not in dset:
                out.setdefault(a, []).append(b)
                inc.setdefault(b, []).append(a)
        new = []
        used = set()
        for i, bs in out.items():
            if on_rim[i] or len(bs) != 1 or len(inc.get(i, [])) != 1:
                continue
            a, b = inc[i][0], bs[0]
            if not (on_rim[a] and on_rim[b]) or a == b or tuple(sorted((a, b))) in und or {a, b, i} & used:
                continue
            new.append((i, a, b))
            used |= {a, b, i}
        if not new:
            break
        E = np.concatenate([E, np.asarray(new, np.int64)])
        added += len(new)
    return E, added


def extension_mesh(skin_V, skin_F, face_pos, face_tri, holes=None, ear_points=None, fiducials=None,
                   neck_cut_y: float = NECK_CUT_Y, spacing: float = SPACING, ear_spacing: float = EAR_SPACING,
                   ear_radius: float = EAR_RADIUS, max_azimuth_deg: float = MAX_AZIMUTH_DEG, seen=None,
                   border: float = BORDER, neck_top_y: float | None = None) -> ExtensionMesh:
    """Mesh the extensions of a face template on a skin surface (method in the module docstring).

    ``skin_V`` (V, 3), ``skin_F`` (F, 3) the skin at the neutral (outward counter-clockwise);
    ``face_pos`` (T, 3), ``face_tri`` (M, 3) the face template; ``holes`` {name: loop ids} its
    openings; ``ear_points`` {"ear_left"/"ear_right": (3,)}; ``fiducials`` (K,) template ids of the
    dots (default: every face template vertex); ``seen`` optional (V,) bool: the skin vertices some
    capture camera sees (replaces the azimuth rule).
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import dijkstra
    from scipy.spatial import cKDTree

    SV = np.asarray(skin_V, np.float64)
    SF = np.asarray(skin_F, np.int64)
    X = np.asarray(face_pos, np.float64)
    FT = np.asarray(face_tri, np.int64)
    n_face = len(X)
    ear_points = {k: np.asarray(v, np.float64) for k, v in (ear_points or {}).items()}
    fid = np.arange(n_face) if fiducials is None else np.asarray(fiducials, np.int64)
    if neck_cut_y >= X[:, 1].min():
        raise ValueError(f"neck cut at y = {neck_cut_y:.3f} m is above the face template's lowest vertex "
                         f"(y = {X[:, 1].min():.3f} m): choose a cut below the face")

    # 1. where
    covered = face_covered(SV, X, FT, holes)
    c = SV.mean(0)
    if seen is None:
        az = np.degrees(np.abs(np.arctan2(SV[:, 0] - c[0], SV[:, 2] - c[2])))
        seen = az <= max_azimuth_deg
    allowed = ~covered & (SV[:, 1] >= neck_cut_y) & np.asarray(seen, bool)
    edges = _edges(SF)
    ok_e = allowed[edges].all(1)
    # the region's outer border: allowed vertices next to a vertex left out for another reason than the face
    other = ~allowed & ~covered
    rim = np.zeros(len(SV), bool)
    m = allowed[edges[:, 0]] & other[edges[:, 1]]
    rim[edges[m, 0]] = True
    m = allowed[edges[:, 1]] & other[edges[:, 0]]
    rim[edges[m, 1]] = True

    # 2. samples
    bnd, bverts = outer_border(FT, holes)
    rad = np.full(len(SV), spacing)
    for p in ear_points.values():
        rad[np.linalg.norm(SV - p, axis=1) < ear_radius] = ear_spacing
    near_face = np.zeros(len(SV), bool)
    if len(bverts):
        d_b, _ = cKDTree(X[bverts]).query(SV)
        near_face = d_b < 0.75 * rad
    d_f, _ = cKDTree(X).query(SV)
    near_face |= d_f < 0.5 * rad
    rng = np.random.default_rng(0)
    perm = rng.permutation(len(SV))
    order = np.concatenate([perm[rim[perm]], perm[~rim[perm]]])
    samples = _poisson(SV, order, rad, ~allowed | near_face)

    # 3. geodesic Voronoi of samples + face border vertices on the allowed skin graph, and its dual
    n = len(SV)
    nb = len(bverts)
    src_nodes = np.arange(n, n + nb)
    rows, cols, w = list(edges[ok_e, 0]), list(edges[ok_e, 1]), list(np.linalg.norm(SV[edges[ok_e, 0]] - SV[edges[ok_e, 1]], axis=1))
    tree_allowed = cKDTree(SV[allowed]) if allowed.any() else None
    allowed_ids = np.flatnonzero(allowed)
    for j, b in enumerate(bverts):
        if tree_allowed is None:
            break
        d, i = tree_allowed.query(X[b], k=min(8, len(allowed_ids)))
        d, i = np.atleast_1d(d), np.atleast_1d(i)
        sel = d < max(0.006, 1.5 * d.min())
        for dd, ii in zip(d[sel], i[sel]):
            rows.append(n + j)
            cols.append(int(allowed_ids[ii]))
            w.append(float(dd) + 1e-9)
    G = coo_matrix((np.asarray(w, float), (np.asarray(rows, int), np.asarray(cols, int))), shape=(n + nb, n + nb)).tocsr()
    sources = np.concatenate([samples, src_nodes])
    _, _, owner = dijkstra(G, directed=False, indices=sources, min_only=True, return_predecessors=True)
    owner = np.asarray(owner[:n], np.int64)          # node id of the source, -9999 where unreached
    # label: template id of the owning source
    label = np.full(n, -1, np.int64)
    samp_id = {int(s): n_face + k for k, s in enumerate(samples)}
    for node in np.unique(owner[owner >= 0]):
        label[owner == node] = samp_id[int(node)] if node < n else int(bverts[int(node) - n])
    L = label[SF]
    ok = (L >= 0).all(1) & (L[:, 0] != L[:, 1]) & (L[:, 1] != L[:, 2]) & (L[:, 0] != L[:, 2])
    dual = L[ok]
    _, first = np.unique(np.sort(dual, axis=1), axis=0, return_index=True)
    dual = dual[np.sort(first)]
    face_keys = {tuple(sorted(map(int, t))) for t in FT}
    dual = np.array([t for t in dual if tuple(sorted(map(int, t))) not in face_keys], np.int64).reshape(-1, 3)

    P3 = np.concatenate([X, SV[samples]])
    on_rim = np.zeros(len(P3), bool)
    on_rim[n_face + np.flatnonzero(rim[samples])] = True
    E, info = _clean(P3, FT, dual, holes, max_hole=16, max_perimeter=8 * spacing, on_rim=on_rim)
    E, info["notches_filled"] = _fill_notches(FT, E, on_rim)
    from .template import flip_improve

    E = flip_improve(P3, None, E)       # better-shaped triangles; the face's border edges never flip
    # vertices no triangle uses are left out (renumbered)
    used = np.unique(E)
    keep = np.flatnonzero(np.isin(np.arange(len(samples)) + n_face, used))
    remap = np.arange(len(P3))
    remap[n_face + keep] = n_face + np.arange(len(keep))
    E = remap[E]
    samples = samples[keep]
    P = SV[samples]

    # 4. which extension each new vertex belongs to
    ext_ids = n_face + np.arange(len(samples))
    if neck_top_y is None:
        neck_top_y = (min(p[1] for p in ear_points.values()) - NECK_TOP_DROP) if ear_points else \
            float(X[:, 1].min() + 0.06)
    d_fid, _ = cKDTree(X[fid]).query(P) if len(fid) else (np.full(len(P), np.inf), None)
    name = np.full(len(P), "scalp", dtype=object)
    name[d_fid < border] = np.where(P[d_fid < border, 0] - c[0] >= 0, "border_left", "border_right")
    for side, key in (("ear_left", "ear_left"), ("ear_right", "ear_right")):
        if key in ear_points:
            p = ear_points[key]
            near = (np.linalg.norm(P - p, axis=1) < ear_radius) & (np.abs(P[:, 0] - c[0]) > abs(p[0] - c[0]) - 0.012)
            name[near] = side
    name[P[:, 1] < neck_top_y] = "neck_lower"
    exts = {}
    for nm, mode, anchor in EXTENSION_KINDS:
        ids = ext_ids[name == nm]
        if not len(ids):
            continue
        e = {"vertices": ids, "mode": mode, "anchor": anchor, "region": nm}
        if mode == "driven":
            e["falloff"] = FALLOFF["neck_lower" if nm == "neck_lower" else "border"]
        exts[nm] = e
    info.update({"vertices": int(len(samples)), "triangles": int(len(E)), "neck_cut_y": float(neck_cut_y),
                 "spacing": float(spacing)})
    return ExtensionMesh(samples, P, E, exts, info)


def add_extensions(tpl, skin_V, skin_F, **options):
    """The template ``tpl`` (:class:`mifacerf.synthetic.template.Template`, bound to the skin ``skin_V``,
    ``skin_F`` at the neutral) with extensions: new vertices (kind ``extension``, truth-bound to the skin
    vertex they sit on) after the face's, their triangles after the face's, one region per extension
    and the ``extensions`` declarations. ``options``: :func:`extension_mesh`'s (``neck_cut_y``,
    ``spacing``, ``seen`` ...). For helper code that builds templates of other skins (a scanned head)."""
    from dataclasses import replace

    from .template import _vertex_binding

    ears = {}
    for i, nm in enumerate(tpl.names):
        if nm in ("ear_L", "ear_R"):
            ears["ear_left" if nm == "ear_L" else "ear_right"] = tpl.neutral[i]
    em = extension_mesh(skin_V, skin_F, tpl.neutral, tpl.triangles, tpl.holes, ears,
                        fiducials=tpl.dot_ids, **options)
    n = len(em.skin_vertices)
    kinds = list(tpl.kinds) + ["extension"] * n
    names = list(tpl.names) + [""] * n
    regions = dict(tpl.regions)
    exts = {}
    for nm, e in em.extensions.items():
        regions[e["region"]] = np.asarray(e["vertices"], np.int64)
        exts[nm] = {k: v for k, v in e.items()}
    out = replace(tpl, kinds=kinds, names=names, neutral=np.concatenate([tpl.neutral, em.positions]),
                  triangles=np.concatenate([np.asarray(tpl.triangles, np.int64), em.triangles]),
                  regions=regions, extensions=exts, extra=dict(tpl.extra, extension_report=em.report,
                                                          n_face_triangles=len(tpl.triangles)))
    if tpl.tri is not None:
        t, b = _vertex_binding(skin_F, em.skin_vertices)
        out.part = list(tpl.part) + ["skin"] * n
        out.tri = np.concatenate([tpl.tri, t])
        out.bary = np.concatenate([tpl.bary, b])
    return out
