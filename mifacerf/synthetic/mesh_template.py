"""The registration template of a user's own head, made on its skin where the capture cameras see it.

The procedural head's template (:mod:`.template`) is laid out in its skin's parameter chart. A
user's mesh has no such chart (the cylindrical chart of earlier versions inverted neck triangles and
spanned holes), so here everything is done on the surface itself:

1. **Visible skin**: every skin triangle's centroid and corners are ray-traced against the whole
   head (skin, eyes, teeth, mouth interior) from every capture camera (``MeshScene.visible_from``,
   the view not grazing: cos > 0.25). A triangle whose centroid and corners two or more cameras see
   is *visible skin*; only there are dots placed and the template made.
2. **Dots** by even sampling of the visible skin (``trimesh.sample.sample_surface_even``, fixed seed).
3. **Margins and marks**: the skin's boundary loops that are the mouth and the two eye openings (the
   loops nearest the eyeballs and the one below them between the cheeks) give lip and eyelid margin
   vertices (corners at the loop's extreme x), and three head marks are chosen on the skin: the
   nose bridge (the frontmost midline point at eye height) and one point per ear (the most lateral
   skin seen by two cameras at eye height).
4. **Triangles**: the dual of the geodesic Voronoi diagram of these sites on the skin (Dijkstra over
   the mesh edges, each site seeded from its triangle's corners, cells cut off at 1.6 dot spacings):
   a skin triangle whose three corners fall in three different cells is one template triangle. It
   follows the surface, never spans an opening (cells do not meet across the mouth or the eyes),
   and each triangle is oriented by the skin normal where it was found. Edges used by more than two
   triangles are resolved by dropping the worst-shaped ones; cracks of three or four edges are closed.
5. **Coarse points**: 18 dots chosen by farthest-point sampling among dots three or more cameras
   see, their triangles the dual of their own Voronoi cells.

:func:`template_coverage` is the share of the visible skin's area the template covers (target
≥ 98 %).
"""
from __future__ import annotations

import numpy as np

from .template import REGION_NAMES, Template
from .template_extensions import boundary_loops

MIN_COS = 0.25


def face_normals(V, F):
    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)


def view_counts(points, normals, occluder, cameras, min_cos: float = MIN_COS) -> np.ndarray:
    """(N,) how many cameras see each surface point (ray-traced against ``occluder`` = (V, F), or a
    ``MeshScene`` of it; ``normals`` (N, 3) outward; a view closer than ``acos(min_cos)`` to grazing
    does not count)."""
    from ..geometry.meshscene import MeshScene

    scene = occluder if isinstance(occluder, MeshScene) else MeshScene(*occluder)
    n = np.zeros(len(points), np.int64)
    for cam in cameras:
        v = scene.visible_from(points, cam, tol=5e-4)
        d = cam.centre - points
        d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-30)
        n += v & (np.einsum("ij,ij->i", d, normals) > min_cos)
    return n


def visible_skin(V, F, occluder, cameras, min_views: int = 2):
    """(F,) bool skin triangles whose centroid and corners ``min_views`` cameras see; (Vn,) vertex view counts."""
    from ..geometry.meshscene import MeshScene
    from .subject import vertex_normals

    occluder = occluder if isinstance(occluder, MeshScene) else MeshScene(*occluder)
    N = vertex_normals(V, F)
    vcount = view_counts(V, N, occluder, cameras)
    C = V[F].mean(axis=1)
    fcount = view_counts(C, face_normals(V, F), occluder, cameras)
    ok = (fcount >= min_views) & (vcount[F] >= min_views).all(axis=1)
    return ok, vcount


def _poisson(points, r, tree=None):
    """Greedy Poisson-disk thinning: indices of ``points`` kept in order, each at least ``r`` from
    every earlier kept one."""
    from scipy.spatial import cKDTree

    tree = tree if tree is not None else cKDTree(points)
    alive = np.ones(len(points), bool)
    out = []
    for i in range(len(points)):
        if alive[i]:
            out.append(i)
            alive[tree.query_ball_point(points[i], r)] = False
    return np.array(out, np.int64)


def sample_dots(V, F, mask, n: int, seed: int = 0, avoid=None, avoid_dist: float = 0.0, keep=None):
    """(tri (n,), bary (n, 3)): ``n`` evenly spaced points on the triangles ``mask``, the border of
    that region first (so the template made over them reaches it), none nearer than ``avoid_dist``
    to the points ``avoid`` (the margins), each passing ``keep(points, triangles) -> (N,) bool`` when
    given (seen by enough cameras); fewer is an error."""
    import trimesh

    from .mesh_subject import MeshSubjectError

    ids = np.nonzero(mask)[0]
    if n <= 0:
        return np.zeros(0, np.int32), np.zeros((0, 3))
    if len(ids) == 0:
        raise MeshSubjectError("no skin triangle is seen by two capture cameras: is the head placed in the rig "
                               "(placement 'auto') and facing +Z?")
    m = trimesh.Trimesh(V, F[ids], process=False)
    rng = np.random.default_rng(seed)
    # border candidates: points along the region's boundary edges (inset a little), in loop order
    Fm = F[ids]
    E = np.concatenate([Fm[:, [0, 1]], Fm[:, [1, 2]], Fm[:, [2, 0]]])
    owner = np.tile(np.arange(len(Fm)), 3)
    key = np.sort(E, axis=1)
    _, inv, cnt = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    border = cnt[inv.ravel()] == 1
    cand_t, cand_b = [], []
    which = np.repeat(np.arange(3), len(Fm))
    for t, w in zip(owner[border], which[border]):
        a, b = [(0, 1), (1, 2), (2, 0)][w]
        for s in (0.25, 0.75):
            bb = np.full(3, 0.02)
            bb[a] += (1 - s) * 0.94
            bb[b] += s * 0.94
            cand_t.append(t)
            cand_b.append(bb / bb.sum())
    n_border = len(cand_t)
    k = max(12 * n, 4000)
    pts, fid = trimesh.sample.sample_surface(m, k, seed=seed)
    bary_in = trimesh.triangles.points_to_barycentric(m.triangles[fid], pts)
    tri_all = np.concatenate([np.asarray(cand_t, np.int64), fid]).astype(np.int64)
    bary_all = np.concatenate([np.asarray(cand_b).reshape(-1, 3), np.clip(bary_in, 0, None)])
    bary_all /= bary_all.sum(axis=1, keepdims=True)
    P_all = np.einsum("nk,nkj->nj", bary_all, m.triangles[tri_all])
    order = np.concatenate([np.arange(n_border), n_border + rng.permutation(k)])
    P_all, tri_all, bary_all = P_all[order], tri_all[order], bary_all[order]
    if avoid is not None and len(avoid) and avoid_dist > 0:
        from scipy.spatial import cKDTree

        far = cKDTree(avoid).query(P_all)[0] >= avoid_dist
        P_all, tri_all, bary_all = P_all[far], tri_all[far], bary_all[far]
    if keep is not None:
        ok = keep(P_all, ids[tri_all])
        P_all, tri_all, bary_all = P_all[ok], tri_all[ok], bary_all[ok]
    r_hi = np.sqrt(2 * m.area / (np.sqrt(3) * n)) * 1.3
    r_lo = 0.2 * r_hi
    best = None
    from scipy.spatial import cKDTree

    tree = cKDTree(P_all)
    for _ in range(11):                 # bisect the spacing so that at least n points fit
        r = 0.5 * (r_lo + r_hi)
        sel = _poisson(P_all, r, tree)
        if len(sel) >= n:
            best, r_lo = sel, r
        else:
            r_hi = r
    if best is None:
        raise MeshSubjectError(f"fewer than {n} dots fit on the visible skin ({m.area * 1e4:.0f} cm²); ask for "
                               "fewer dots (--dots)")
    sel = best[:n]                      # the border ones first, then the interior in random order
    return ids[tri_all[sel]].astype(np.int32), bary_all[sel]


def _graph(V, F, n_src, src_links):
    """Sparse directed graph: mesh edges both ways, then ``n_src`` source nodes linked to vertices."""
    from scipy.sparse import coo_matrix

    E = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    E = np.unique(np.sort(E, axis=1), axis=0)
    w = np.linalg.norm(V[E[:, 0]] - V[E[:, 1]], axis=1) + 1e-9
    s_from, s_to, s_w = src_links
    nV = len(V)
    rows = np.concatenate([E[:, 0], E[:, 1], nV + s_from])
    cols = np.concatenate([E[:, 1], E[:, 0], s_to])
    data = np.concatenate([w, w, s_w + 1e-9])
    return coo_matrix((data, (rows, cols)), shape=(nV + n_src, nV + n_src)).tocsr()


def voronoi_cells(V, F, site_tri, site_bary, limit: float):
    """(V,) nearest site of every skin vertex along the surface (−1 beyond ``limit`` metres)."""
    from scipy.sparse.csgraph import dijkstra

    P = np.einsum("nk,nkj->nj", site_bary, V[F[site_tri]])
    corners = F[site_tri]                                           # (n, 3)
    s_from = np.repeat(np.arange(len(P)), 3)
    s_to = corners.ravel()
    s_w = np.linalg.norm(P[s_from] - V[s_to], axis=1)
    G = _graph(V, F, len(P), (s_from, s_to, s_w))
    nV = len(V)
    dist, _, src = dijkstra(G, directed=True, indices=nV + np.arange(len(P)), return_predecessors=True,
                            limit=limit, min_only=True)
    lab = np.where(np.isfinite(dist[:nV]), src[:nV] - nV, -1)
    return lab.astype(np.int64)


def _tri_quality(P, T):
    a = np.linalg.norm(P[T[:, 1]] - P[T[:, 0]], axis=1)
    b = np.linalg.norm(P[T[:, 2]] - P[T[:, 1]], axis=1)
    c = np.linalg.norm(P[T[:, 0]] - P[T[:, 2]], axis=1)
    area = 0.5 * np.linalg.norm(np.cross(P[T[:, 1]] - P[T[:, 0]], P[T[:, 2]] - P[T[:, 0]]), axis=1)
    return 4 * np.sqrt(3) * area / np.maximum(a * a + b * b + c * c, 1e-30)   # 1 = equilateral


def voronoi_dual(V, F, labels, P, normals_at):
    """Template triangles (M, 3) over sites ``P`` from vertex ``labels``; oriented along ``normals_at``
    (the skin normal of each skin triangle), non-manifold edges resolved, 3- and 4-edge cracks closed."""
    L = labels[F]
    ok = (L >= 0).all(axis=1) & (L[:, 0] != L[:, 1]) & (L[:, 1] != L[:, 2]) & (L[:, 0] != L[:, 2])
    T, nrm = L[ok], normals_at[ok]
    u, inv = np.unique(np.sort(T, axis=1), axis=0, return_inverse=True)
    n_acc = np.zeros((len(u), 3))
    np.add.at(n_acc, inv.ravel(), nrm)
    T = u.copy()
    cr = np.cross(P[T[:, 1]] - P[T[:, 0]], P[T[:, 2]] - P[T[:, 0]])
    flip = np.einsum("ij,ij->i", cr, n_acc) < 0
    T[flip] = T[flip][:, [0, 2, 1]]
    T = _resolve_nonmanifold(P, T)
    T = _close_cracks(T)
    return _resolve_nonmanifold(P, T)


def _edges(T):
    return np.concatenate([T[:, [0, 1]], T[:, [1, 2]], T[:, [2, 0]]])


def _resolve_nonmanifold(P, T):
    q = _tri_quality(P, T)
    for _ in range(20):
        E = np.sort(_edges(T), axis=1)
        u, inv, cnt = np.unique(E, axis=0, return_inverse=True, return_counts=True)
        inv = inv.ravel()
        bad_e = cnt[inv] > 2
        if not bad_e.any():
            break
        tri_of = np.tile(np.arange(len(T)), 3)
        drop = set()
        for e in np.unique(inv[bad_e]):
            ts = tri_of[inv == e]
            ts = ts[np.argsort(-q[ts])]
            drop.update(ts[2:].tolist())
        keep = np.ones(len(T), bool)
        keep[list(drop)] = False
        T, q = T[keep], q[keep]
    return T


def _close_cracks(T):
    """Close boundary cycles of three or four edges (cracks the dual leaves where four cells meet),
    found over the boundary half-edges (so a crack touching a hole at one vertex is found too)."""
    E = np.concatenate([T[:, [0, 1]], T[:, [1, 2]], T[:, [2, 0]]]).tolist()
    S = set(map(tuple, E))
    nxt = {}
    for a, b in S:
        if (b, a) not in S:
            nxt.setdefault(a, []).append(b)
    add, done = [], set()
    for a in nxt:
        for b in nxt[a]:
            for c in nxt.get(b, ()):
                if a in nxt.get(c, ()):
                    cyc = (a, b, c)
                    k = frozenset(cyc)
                    if k not in done:
                        done.add(k)
                        add.append([a, c, b])
                    continue
                for d in nxt.get(c, ()):
                    if d != a and a in nxt.get(d, ()) and len({a, b, c, d}) == 4:
                        k = frozenset((a, b, c, d))
                        if k not in done:
                            done.add(k)
                            add += [[a, c, b], [a, d, c]]
    if add:
        T = np.concatenate([T, np.asarray(add, np.int64)])
    return T


def farthest_points(P, k, start):
    chosen = [int(start)]
    d = np.linalg.norm(P - P[chosen[0]], axis=1)
    while len(chosen) < min(k, len(P)):
        j = int(np.argmax(d))
        chosen.append(j)
        d = np.minimum(d, np.linalg.norm(P - P[j], axis=1))
    return np.array(chosen, np.int64)


def template_coverage(V, F, visible, tpl_P, tpl_T, reach: float) -> tuple:
    """(share of the visible skin's area the template covers, (F,) covered): a skin triangle is
    covered when the line along its normal through its centroid meets a template triangle within
    ``reach`` metres (the template's chords cut through curved skin, so nearness alone is no test)."""
    from ..geometry.meshscene import MeshScene

    covered = np.zeros(len(F), bool)
    if len(tpl_T) == 0:
        return 0.0, covered
    C = V[F].mean(axis=1)
    n = face_normals(V, F)
    scene = MeshScene(tpl_P, tpl_T)
    h = scene.trace(C - reach * n, n)
    covered = h.valid & (h.t <= 2 * reach)
    area = 0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1)
    tot = area[visible].sum()
    return (float(area[visible & covered].sum() / tot) if tot > 0 else 0.0), covered


def _areas(V, F):
    return 0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1)


def _vertex_binding(F, v):
    t = int(np.nonzero((F == v).any(axis=1))[0][0])
    b = (F[t] == v).astype(float)
    return t, b


def margin_loops(V, F, vcount, eye_centres: dict) -> dict:
    """{'mouth': loop, 'eye_left': loop, 'eye_right': loop} among the skin's boundary loops on the
    front of the head (a margin vertex touches the eyeball or the lips, so its own view count says
    little: the rotoscoping step picks the views that see each margin); loops not found are left out."""
    zc = np.median(V[:, 2])
    loops = [lp for lp in boundary_loops(F) if V[lp, 2].mean() > zc]
    if not loops:
        return {}
    cen = np.array([V[lp].mean(axis=0) for lp in loops])
    per = np.array([np.linalg.norm(V[lp] - V[np.roll(lp, 1)], axis=1).sum() for lp in loops])
    out, used = {}, set()
    for name, c in eye_centres.items():
        d = np.linalg.norm(cen - c, axis=1)
        j = int(np.argmin(d))
        if d[j] < 0.03 and j not in used:
            out[name] = loops[j]
            used.add(j)
    if eye_centres:
        ec = np.mean(list(eye_centres.values()), axis=0)
        cand = [j for j in range(len(loops)) if j not in used and cen[j, 1] < ec[1] - 0.02
                and abs(cen[j, 0] - ec[0]) < 0.02 and 0.03 < per[j] < 0.3]
    else:
        cand = [j for j in range(len(loops)) if 0.03 < per[j] < 0.3 and abs(cen[j, 0]) < 0.02]
    if cand:
        j = max(cand, key=lambda j: per[j])
        out["mouth"] = loops[j]
    return out


def visible_ring(V, F, loop, seen) -> list:
    """The margin as the cameras see it: for each vertex of the boundary ``loop`` (in order), the
    nearest vertex along the surface that ``seen`` (V,) marks visible (lips and lids of production
    heads roll inwards, so their boundary loop lies out of view); repeated vertices dropped."""
    from scipy.sparse.csgraph import dijkstra

    G = _graph(V, F, 0, (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)))
    lp = np.asarray(loop, np.int64)
    dist, _, src = dijkstra(G, directed=True, indices=lp, return_predecessors=True, min_only=True)
    ok = seen & np.isfinite(dist)
    best = {}
    for v in np.nonzero(ok)[0]:
        s = int(src[v])
        if s not in best or dist[v] < dist[best[s]]:
            best[s] = v
    ring = []
    for v in lp.tolist():
        r = best.get(v)
        if r is not None and (not ring or ring[-1] != r):
            ring.append(int(r))
    if len(ring) > 1 and ring[0] == ring[-1]:
        ring.pop()
    return ring


def _margin_sites(V, loop, spacing):
    """The loop's vertices at about ``spacing`` apart, starting at the min-x corner, upper side first:
    (vertex ids, kinds-suffix 'corner'/'upper'/'lower')."""
    lp = np.asarray(loop, np.int64)
    x = V[lp, 0]
    i0, i1 = int(np.argmin(x)), int(np.argmax(x))
    lp = np.roll(lp, -i0)
    k = (i1 - i0) % len(lp)
    mid = V[lp[1:k], 1].mean() if k > 1 else 0.0
    line = 0.5 * (V[lp[0], 1] + V[lp[k], 1])
    if k > 1 and mid < line:                           # the first half runs below: reverse
        lp = np.concatenate([[lp[0]], lp[1:][::-1]])
        k = len(lp) - k
    seg = np.linalg.norm(V[lp] - V[np.roll(lp, -1)], axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)[:-1]])

    def pick(a, b):
        if b - a <= 1:
            return []
        length = s[b] - s[a] if b < len(lp) else s[-1] + seg[-1] - s[a]
        m = max(1, int(round(length / spacing)))
        targets = s[a] + length * np.arange(1, m) / m
        idx = [a + 1 + int(np.argmin(np.abs(s[a + 1:b] - t))) for t in targets] if b > a + 1 else []
        return sorted(set(idx))

    up = pick(0, k)
    lo = pick(k, len(lp))
    ids = [lp[0]] + [lp[i] for i in up] + [lp[k]] + [lp[i] for i in lo]
    kinds = ["corner"] + ["upper"] * len(up) + ["corner"] + ["lower"] * len(lo)
    return ids, kinds


def head_marks(V, vcount, eye_centres: dict, nose_tip):
    """{'nose_bridge': v, 'ear_L': v, 'ear_R': v} skin vertex ids (those found)."""
    out = {}
    if eye_centres:
        ec = np.mean(list(eye_centres.values()), axis=0)
    else:
        ec = np.asarray(nose_tip) + np.array([0.0, 0.035, -0.04])
    band = np.abs(V[:, 1] - ec[1]) < 0.006
    mid = band & (np.abs(V[:, 0] - ec[0]) < 0.004) & (vcount >= 2)
    if mid.any():
        ids = np.nonzero(mid)[0]
        out["nose_bridge"] = int(ids[np.argmax(V[ids, 2])])
    for name, sgn in (("ear_L", 1.0), ("ear_R", -1.0)):
        ear = (V[:, 1] < ec[1] + 0.005) & (V[:, 1] > ec[1] - 0.03) & (vcount >= 2) & (sgn * (V[:, 0] - ec[0]) > 0.05)
        if ear.any():
            ids = np.nonzero(ear)[0]
            out[name] = int(ids[np.argmax(sgn * V[ids, 0])])
    return out


def _seen_in_every_pose(V, F, scenes, cameras, min_views):
    """``keep(points, triangles) -> (N,) bool`` for :func:`sample_dots`: the points (on the neutral skin
    ``V``) that ``min_views`` cameras see in the neutral and, carried by their triangle's barycentric
    coordinates, in every further pose of ``scenes`` [(V_k, MeshScene of its occluder)]."""
    fn0 = face_normals(V, F)

    def keep(P, t):
        ok = view_counts(P, fn0[t], scenes[0][1], cameras) >= min_views
        if len(scenes) > 1 and ok.any():
            import trimesh

            b = trimesh.triangles.points_to_barycentric(V[F[t]], P)
            for Vk, sc in scenes[1:]:
                Pk = np.einsum("nk,nkj->nj", b, Vk[F[t]])
                ok &= view_counts(Pk, face_normals(Vk, F)[t], sc, cameras) >= min_views
        return ok
    return keep


def min_view_counts(F, tri, bary, scenes, cameras) -> np.ndarray:
    """(n,) the fewest cameras that see each point (triangle ``tri``, ``bary``) over the poses ``scenes``."""
    out = None
    for Vk, sc in scenes:
        P = np.einsum("nk,nkj->nj", bary, Vk[F[tri]])
        c = view_counts(P, face_normals(Vk, F)[tri], sc, cameras)
        out = c if out is None else np.minimum(out, c)
    return out


def coarse_choice(P, motions, candidates, k: int = 18, motion_weight: float = 2.0) -> np.ndarray:
    """``k`` coarse points among ``candidates`` (ids into ``P``): farthest-point sampling in the space of
    the neutral position and ``motion_weight`` times the point's displacement in each expression
    (``motions`` (K, n, 3)), so the coarse mesh, which predicts every expression's dots, has points where
    the skin moves (lips, chin, jaw) and not only at the extremes of the head."""
    X = P[candidates]
    if len(motions):
        X = np.concatenate([X] + [motion_weight * m[candidates] for m in motions], axis=1)
    centre = np.argmin(np.linalg.norm(P[candidates] - P[candidates].mean(axis=0), axis=1))
    return candidates[farthest_points(X, k, centre)]


def protrudes(V, mark, min_mm: float = 8.0) -> bool:
    """Whether the skin at an ear mark is an ear: at the mark's height, the skin 25-40 mm in front of it
    and behind it (where there is skin) reaches on average at least ``min_mm`` less far sideways (a head
    without ears, or with its ears cut off, has its widest point there and keeps its dots there)."""
    side = np.sign(mark[0] - V[:, 0].mean()) or 1.0
    band = (np.abs(V[:, 1] - mark[1]) < 0.005) & (side * (V[:, 0] - mark[0]) > -0.1)
    lat = side * (V[:, 0] - V[:, 0].mean())
    reach = []
    for lo, hi in ((0.025, 0.040), (-0.040, -0.025)):
        sel = band & (V[:, 2] - mark[2] >= lo) & (V[:, 2] - mark[2] <= hi)
        if sel.any():
            reach.append(float(lat[sel].max()))
    m = float(side * (mark[0] - V[:, 0].mean()))
    return bool(reach) and m - float(np.mean(reach)) >= min_mm * 1e-3


def ear_zones(V, F, ear_marks) -> np.ndarray:
    """(F,) bool the skin triangles of the ears: within the extensions' ``EAR_RADIUS`` of an ear mark and
    beyond it sideways as the extensions' ear rule counts (:func:`.template_extensions.extension_mesh`)."""
    from .template_extensions import EAR_RADIUS

    C = V[F].mean(axis=1)
    c = V.mean(axis=0)
    out = np.zeros(len(F), bool)
    for p in ear_marks:
        out |= (np.linalg.norm(C - p, axis=1) < EAR_RADIUS) & (np.abs(C[:, 0] - c[0]) > abs(p[0] - c[0]) - 0.012)
    return out


def build_mesh_template(V, F, occluder, cameras, n_dots: int, seed: int = 0, eye_centres=None,
                        min_views: int = 2, poses=None, ear_extensions: bool = True):
    """The template of a skin surface ``V`` (V, 3), ``F`` (F, 3) seen by ``cameras``.

    ``poses``: the skin's vertices ``V_k`` and occluder ``(V, F)`` of every further expression the
    capture photographs [(V_k, occluder_k), ...]: dots only where ``min_views`` cameras see them in
    the neutral *and in each of these* (an open jaw hides its underside from the upper cameras), and
    the coarse points spread over the skin's motion in them as well as over its shape.
    ``ear_extensions``: where an ear mark is on an ear that sticks out (:func:`protrudes`), no dot on
    that ear (:func:`ear_zones`) and no template triangle reaching the mark (on the ear's rim: chords
    from the cheek's dots to it cover the ear and hide it from the extensions, which mesh the ear on
    the skin, rigid with the head).

    Returns ``(template, info)``; ``info``: ``visible`` (F,) bool, ``covered`` (F,) bool,
    ``coverage`` (share of the visible skin's area), ``dot_tri``, ``dot_bary``, ``dot_views`` (cameras
    seeing each dot in the neutral), ``dot_views_min`` (... the fewest over the poses), ``margins`` found,
    ``marks`` found, ``spacing`` (m), ``region`` (F,) bool (the skin ``min_views`` cameras see in every pose),
    ``region_area`` (m²), ``region_coverage`` (the share of it the template covers), ``ears_to_extensions``
    (how many ears were left to the extensions)."""
    from ..geometry.meshscene import MeshScene
    from .mesh_subject import MeshSubjectError

    eye_centres = eye_centres or {}
    scenes = [(V, MeshScene(*occluder))] + [(np.asarray(Vk, np.float64), MeshScene(*occ)) for Vk, occ in poses or []]
    visible, vcount = visible_skin(V, F, scenes[0][1], cameras, min_views)
    region = visible.copy()
    for Vk, sc in scenes[1:]:
        region &= visible_skin(Vk, F, sc, cameras, min_views)[0]
    fn = face_normals(V, F)
    area = 0.5 * np.linalg.norm(np.cross(V[F[visible, 1]] - V[F[visible, 0]], V[F[visible, 2]] - V[F[visible, 0]]),
                                axis=1).sum()
    spacing = float(np.sqrt(2 * area / (np.sqrt(3) * max(n_dots, 1))))
    loops = margin_loops(V, F, vcount, eye_centres)
    loops = {k: r for k, r in ((k, visible_ring(V, F, lp, vcount >= min_views)) for k, lp in loops.items())
             if len(r) >= 6}
    margin_pts = V[np.concatenate([np.asarray(lp) for lp in loops.values()])] if loops else np.zeros((0, 3))
    nose_tip = V[int(np.argmax(V[:, 2]))]
    marks = head_marks(V, vcount, eye_centres, nose_tip)
    ears = [V[v] for k, v in marks.items() if k.startswith("ear") and ear_extensions and protrudes(V, V[v])]
    if ears:
        region &= ~ear_zones(V, F, ears)
    dot_tri, dot_bary = sample_dots(V, F, region, n_dots, seed, avoid=margin_pts, avoid_dist=0.4 * spacing,
                                    keep=_seen_in_every_pose(V, F, scenes, cameras, min_views))
    dots = np.einsum("nk,nkj->nj", dot_bary, V[F[dot_tri]])
    dot_views = view_counts(dots, fn[dot_tri], scenes[0][1], cameras)
    dot_views_min = min_view_counts(F, dot_tri, dot_bary, scenes, cameras)
    if (dot_views_min < min_views).any():
        raise MeshSubjectError(f"{int((dot_views_min < min_views).sum())} of {n_dots} dots are seen by fewer than "
                               f"{min_views} cameras" + (" in some expression" if len(scenes) > 1 else ""))

    kinds = ["dot"] * n_dots
    names = [""] * n_dots
    tri = list(dot_tri.astype(int))
    bary = [b for b in dot_bary]
    holes = {}
    for hole, loop in loops.items():
        ids, sub = _margin_sites(V, loop, min(0.45 * spacing, 0.004))
        base = "lip" if hole == "mouth" else "lid"
        start = len(kinds)
        for j, (v, s) in enumerate(zip(ids, sub)):
            t, b = _vertex_binding(F, v)
            kinds.append(f"{base}_{s}")
            if s == "corner":
                side = "R" if j == 0 else "L"
                names.append(f"mouth_corner_{side}" if hole == "mouth" else f"{hole}_corner")
            else:
                names.append("")
            tri.append(t)
            bary.append(b)
        holes[hole] = list(range(start, len(kinds)))
    for name, v in marks.items():
        t, b = _vertex_binding(F, v)
        kinds.append("ear" if name.startswith("ear") else "nose_bridge")
        names.append(name)
        tri.append(t)
        bary.append(b)
    tri = np.asarray(tri, np.int64)
    bary = np.asarray(bary, np.float64)
    P = np.einsum("nk,nkj->nj", bary, V[F[tri]])

    limit = 1.6 * spacing
    labels = voronoi_cells(V, F, tri, bary, limit)
    T = voronoi_dual(V, F, labels, P, fn)
    for loop in holes.values():            # cells meet beyond an opening's corners: keep the opening open
        T = T[~np.isin(T, loop).all(axis=1)]
    if ears:                               # the ear marks lie on the ears' rims: triangles from the cheek's dots to
        ids = [i for i, nm in enumerate(names) if nm in ("ear_L", "ear_R") and any(np.allclose(P[i], e) for e in ears)]
        T = T[~np.isin(T, ids).any(axis=1)]     # them are chords over the ear that hide it from the extensions
    # coarse points: farthest-point sampling over well-seen dots (in shape and motion), their own dual
    good = np.nonzero(dot_views_min >= 3)[0]
    if len(good) < 18:
        good = np.nonzero(dot_views >= 3)[0]
    if len(good) < 18:
        good = np.arange(n_dots)
    motions = [np.einsum("nk,nkj->nj", dot_bary, Vk[F[dot_tri]]) - dots for Vk, _ in scenes[1:]]
    coarse = coarse_choice(dots, motions, good)
    clab = voronoi_cells(V, F, tri[coarse], bary[coarse], np.inf)
    clab[labels < 0] = -1
    Tc = voronoi_dual(V, F, clab, P[coarse], fn)
    cnames = [f"coarse_{i:02d}" for i in range(len(coarse))]
    for i, j in enumerate(coarse):
        names[j] = cnames[i]
    coverage, covered = template_coverage(V, F, visible, P, T, reach=0.5 * spacing)
    tot = _areas(V, F)
    region_coverage = float(tot[region & covered].sum() / max(tot[region].sum(), 1e-30))
    regions = bbox_regions(P, V[np.unique(F[visible])])
    tpl = Template(kinds, names, P.copy(), T, coarse, cnames, Tc, regions, holes, {}, {},
                   ["skin"] * len(kinds), tri, bary, "mesh", extra={"skin_faces": F})
    info = {"visible": visible, "covered": covered, "coverage": coverage, "dot_tri": dot_tri,
            "dot_bary": dot_bary, "dot_views": dot_views, "dot_views_min": dot_views_min, "margins": sorted(loops),
            "marks": sorted(marks), "spacing": spacing, "visible_area": float(area), "n_poses": len(scenes) - 1,
            "region": region, "region_area": float(tot[region].sum()), "region_coverage": region_coverage,
            "ears_to_extensions": len(ears)}
    return tpl, info


def bbox_regions(P, V):
    """§5.1 culling regions from positions in the visible skin's bounding box (a partition of ``P``)."""
    lo, hi = V.min(axis=0), V.max(axis=0)
    u = (P - lo) / np.maximum(hi - lo, 1e-12)
    x, y = u[:, 0] - 0.5, u[:, 1]
    out = {k: [] for k in REGION_NAMES}
    for i in range(len(P)):
        if y[i] > 0.75:
            r = "forehead"
        elif y[i] > 0.55:
            r = "nose" if abs(x[i]) < 0.08 else ("eye_left" if x[i] > 0 else "eye_right")
        elif y[i] > 0.40:
            r = "nose" if abs(x[i]) < 0.08 else ("cheek_left" if x[i] > 0 else "cheek_right")
        elif y[i] > 0.22:
            r = "mouth" if abs(x[i]) < 0.18 else ("cheek_left" if x[i] > 0 else "cheek_right")
        elif y[i] > 0.10:
            r = "chin" if abs(x[i]) < 0.2 else ("cheek_left" if x[i] > 0 else "cheek_right")
        else:
            r = "throat" if abs(x[i]) < 0.2 else "neck"
        out[r].append(i)
    return {k: np.array(v, int) for k, v in out.items()}
