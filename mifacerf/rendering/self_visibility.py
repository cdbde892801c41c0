"""The captured self-visibility of each source expression, so the material can divide it out.

A captured reflectance field already holds the face's self-shadowing: texel x of source ``s`` lit
by light ``l`` is dark where the subject's own nose or brow stood between x and the light. Under
Mitsuba's integrators the material's shadow rays shadow the target face again (double shadowing).
Where the capture's visibility is *known* — ray-traced against the registered geometry of source
``s`` — the material divides it out, so the shadow rays alone supply the visibility of the target
geometry (and other objects in the scene shadow the face as they should).

``visibility(model)`` returns ``V`` (S, T, L) in [0, 1]: for every source expression, template
vertex and light-stage light, the share of the light's spherical-Voronoi cell (``CELL_SAMPLES``
directions over the sphere, each given to its nearest light) whose rays from the vertex (offset along
its normal by ``eps`` of the face's size) escape the source mesh (:func:`cell_visibility`). The
material answers every direction of a cell with that light's field, and the integrator's shadow rays
pass a share ``V`` of them on average, so per hit the material interpolates ``V`` at the triangle's
barycentrics for the light it uses (``v``) and divides the field by it: in expectation the shadow rays
then give back the captured value (until 2026-12-02 ``V`` was the single ray towards the light itself,
0 or 1: on the tiny preset's face the material was 4.3 % darker than the exact path in ``direct``,
3.2 % with the cell shares and fill 0.5, 2.6 % with fill 0.1 — docs/rendering.md).

Fill where a light is (almost) wholly shadowed, ``v < MIN_VISIBILITY``: there the field holds little or
no information about the unshadowed response, so nothing is divided (the captured, dark value is kept,
divisor 1); division brightens ``MIN_VISIBILITY ≤ v < 1`` by at most ``1 / MIN_VISIBILITY`` and never
amplifies a fully shadowed texel's noise. Consequences: a captured shadow that the target geometry would
not cast (another expression's nose) stays dark — the material shows the union of the captured shadow
and the target's own; and where a cell is wholly shadowed in the source *and* the target, the shadow
rays block every direction the field answers, so the light the capture saw there (interreflection
and subsurface light inside the shadow) is lost — a limit of shadow-ray integrators with fields that
already hold their shadows (0.8 % of the tiny preset face's mean under the interior environment).

Inside the triangles (``triangle_visibility``, what the material uses since 2026-12-02): the same shares at
a barycentric grid of points on every triangle (:data:`GRID_ORDER` 3: 10 points), traced from the
triangle's surface with its geometric normal as Mitsuba spawns its shadow rays, interpolated linearly
at the hit. On the coarse template the per-vertex values miss what happens inside a triangle (a crease's
vertices are shadowed where its interior is not; a facet tilted away from the light blocks it where its
vertices, with their averaged normals, see it): on the draft model the per-vertex rule scored 29.4 dB
against the exact path, the grid 33.2 dB (docs/rendering.md). Computed per source expression when a
material first uses it (about 10 s per source of the draft model on the shared cores).

Computed at load, once per model (in memory, keyed by the model folder and its manifest's
modification time; nothing is written to the model folder). The per-triangle grids are also kept on disk,
in the user's cache (``$MIFACERF_CACHE/visibility/``, default ``~/.cache/mifacerf``), named by a hash of
everything they are computed from — the source's vertices, the triangles, the light directions, rule, order,
``near``, :data:`CELL_SAMPLES` and :data:`CACHE_VERSION` —, so a second process (every ``mifacerf render`` of a
scene with ``facerf_bsdf``) reads them instead of tracing 3.7 s a source again. A cached file of another
shape, with values outside [0, 1] or unreadable is recomputed, with a warning naming it; one that cannot be
written only costs the tracing (``MIFACERF_VISIBILITY_CACHE=0``: memory only). F × 16 × L float32 a source:
19 MB for the demo model's 1,527 triangles and 192 lights. The folder is kept under
``$MIFACERF_VISIBILITY_CACHE_MB`` (default 2048 MB) by deleting the least recently used grids
(:func:`trim_cache`).
"""
from __future__ import annotations

import os
import threading
from pathlib import Path

import numpy as np

MIN_VISIBILITY = 0.1
EPS = 1e-3
CELL_SAMPLES = 4096

_CACHE: dict = {}
_LOCK = threading.Lock()
#: bump when anything that changes :func:`triangle_visibility`'s values changes (the disk cache's key)
CACHE_VERSION = 1


def _key(model):
    root = Path(model.root).resolve()
    marker = [p for p in (root / "model.json",) if p.exists()]
    return str(root), (marker[0].stat().st_mtime_ns if marker else 0)


def _mesh_scene(vertices, triangles):
    """(mitsuba module, a Mitsuba scene of the one mesh, vertices (T, 3) float64, triangles (F, 3) int64)."""
    from ..jitarrays import to_jit
    from ..variant import ensure_variant

    mi = ensure_variant()
    V = np.asarray(vertices, np.float64)
    F = np.asarray(triangles, np.int64).reshape(-1, 3)
    mesh = mi.Mesh("self", len(V), len(F))
    params = mi.traverse(mesh)
    params["vertex_positions"] = to_jit(mi.Float, V.reshape(-1).astype(np.float32))
    params["faces"] = to_jit(mi.UInt32, F.reshape(-1).astype(np.uint32))
    params.update()
    return mi, mi.load_dict({"type": "scene", "mesh": mesh}, parallel=False), V, F   # not nested (meshscene.py)


def trace(vertices: np.ndarray, triangles: np.ndarray, directions: np.ndarray, eps: float = EPS) -> np.ndarray:
    """(T, L) float32: 1 where a ray from each vertex (offset along its normal by ``eps`` × the mesh's
    bounding-box diagonal) towards each direction meets no triangle of the mesh, else 0."""
    from ..geometry.visibility import vertex_normals

    mi, scene, V, F = _mesh_scene(vertices, triangles)
    n = vertex_normals(V, F)
    scale = float(np.linalg.norm(V.max(0) - V.min(0))) or 1.0
    o = V + n * eps * scale
    D = np.asarray(directions, np.float64)
    T, L = len(V), len(D)
    oo = np.repeat(o, L, axis=0).astype(np.float32)
    dd = np.tile(D, (T, 1)).astype(np.float32)
    ray = mi.Ray3f(mi.Point3f(oo.T), mi.Vector3f(dd.T))
    hit = scene.ray_test(ray)
    blocked = np.asarray(hit, bool).reshape(T, L)
    return (~blocked).astype(np.float32)


def cell_directions(directions: np.ndarray, n: int = CELL_SAMPLES) -> tuple[np.ndarray, np.ndarray]:
    """``n`` directions spread evenly over the sphere (a Fibonacci lattice) and, for each, its nearest light
    (its spherical-Voronoi cell among ``directions`` (L, 3)): (samples (n, 3), cell (n,))."""
    k = np.arange(n) + 0.5
    z = 1 - 2 * k / n
    phi = np.pi * (1 + 5 ** 0.5) * k
    r = np.sqrt(1 - z * z)
    samples = np.stack([r * np.cos(phi), r * np.sin(phi), z], 1)
    return samples, np.argmax(samples @ np.asarray(directions, np.float64).T, axis=1)


def cell_visibility(vertices, triangles, directions, n: int = CELL_SAMPLES) -> np.ndarray:
    """(T, L) float32: per vertex, the fraction of each light's Voronoi cell (``n`` directions over the
    sphere) that is not blocked by the mesh — what the material's shadow rays let through, on average, of
    the light-stage light it answers with (a cell with no sample falls back to its light's own direction)."""
    samples, cell = cell_directions(directions, n)
    L = len(directions)
    free = trace(vertices, triangles, samples)                      # (T, n)
    count = np.bincount(cell, minlength=L).astype(np.float64)
    out = np.zeros((len(free), L))
    np.add.at(out.T, cell, free.T)
    empty = count == 0
    out[:, ~empty] /= count[~empty]
    if empty.any():
        out[:, empty] = trace(vertices, triangles, np.asarray(directions)[empty])
    return out.astype(np.float32)


#: how the captured self-visibility of a light is measured: ``cell`` — the unblocked share of the light's
#: Voronoi cell (the material then agrees with the exact path under environments, which spread each light
#: over its cell); ``ray`` — the one ray towards the light (agrees with a directional or point light along
#: a stage light, which lights along that very ray)
VISIBILITY_RULES = ("cell", "ray")


def visibility(model, rule: str = "cell") -> np.ndarray:
    """(S, T, L) float32 self-visibility of every source expression of ``model`` by ``rule``
    (:data:`VISIBILITY_RULES`; see the module docstring)."""
    if rule not in VISIBILITY_RULES:
        raise ValueError(f"self-visibility rule {rule!r} is not one of {', '.join(VISIBILITY_RULES)}")
    key = (_key(model), rule)
    with _LOCK:
        if key not in _CACHE:
            how = cell_visibility if rule == "cell" else trace
            _CACHE[key] = np.stack([how(model.vertices[s], model.triangles, model.light_directions)
                                    for s in range(len(model.expressions))])
        return _CACHE[key]


# ---------------------------------------------------------------- inside the triangles
#: order ``k`` of the per-triangle grid of :func:`triangle_visibility`: points at barycentrics (i/k, j/k, 1 − (i+j)/k)
GRID_ORDER = 3
#: the grid points are pulled this share of the way towards the triangle's centroid (rays from a point on an edge
#: would graze the neighbouring triangle)
GRID_INSET = 0.05


def grid_barycentrics(order: int = GRID_ORDER) -> np.ndarray:
    """((order+1)², 3) barycentrics of the grid points in square storage (row ``i * (order+1) + j`` is grid point
    (i, j), i + j ≤ order; the other rows, i + j > order, are never read and hold the centroid), inset by
    :data:`GRID_INSET` towards the centroid."""
    k = int(order)
    ij = np.array([(i, j) for i in range(k + 1) for j in range(k + 1)], np.float64)
    b = np.stack([ij[:, 0] / k, ij[:, 1] / k, 1 - ij.sum(1) / k], 1)
    b[ij.sum(1) > k] = 1 / 3
    return (1 - GRID_INSET) * b + GRID_INSET / 3


def _free_from(vertices, triangles, origins, normals, directions, chunk_rays: int = 1 << 21,
               near: float = 0.0) -> np.ndarray:
    """(N, D) bool: a ray from each point towards each direction escapes the mesh. The origin is offset along
    the point's (geometric) normal to the side the ray leaves by, as Mitsuba spawns its shadow rays, so a
    direction below the triangle's plane is blocked by the surface itself (as under Mitsuba's integrators).
    ``near`` > 0: the mesh's own surface closer than ``near`` (metres, straight-line distance from the origin)
    does not block — the rule of ``facerf_direct``'s shadow rays (:func:`near_free`)."""
    mi, scene, V, F = _mesh_scene(vertices, triangles)
    scale = float(np.linalg.norm(V.max(0) - V.min(0))) or 1.0
    eps = 1e-4 * scale
    O, N, D = (np.asarray(x, np.float64) for x in (origins, normals, directions))
    step = max(1, chunk_rays // len(D))
    if near <= 0 and len(O) and len(D):
        return _free_from_device(mi, scene, O, N, D, eps, step)
    out = np.zeros((len(O), len(D)), bool)
    for a in range(0, len(O), step):
        o, n = O[a:a + step], N[a:a + step]
        side = np.sign(n @ D.T)                                            # (n, D): +1 above the plane
        side[side == 0] = 1
        oo = (o[:, None, :] + side[..., None] * n[:, None, :] * eps).reshape(-1, 3).astype(np.float32)
        dd = np.broadcast_to(D[None], (len(o), len(D), 3)).reshape(-1, 3).astype(np.float32)
        if near > 0:
            out[a:a + step] = near_free(mi, scene, oo, dd, near).reshape(len(o), len(D))
            continue
        hit = scene.ray_test(mi.Ray3f(mi.Point3f(oo.T), mi.Vector3f(dd.T)))
        out[a:a + step] = ~np.asarray(hit, bool).reshape(len(o), len(D))
    return out


def _free_from_device(mi, scene, O, N, D, eps: float, step: int) -> np.ndarray:
    """:func:`_free_from`'s rays made on the device (float64, as the NumPy form made them, then float32): the
    origin of ray (point i, direction j) is ``O_i + s_ij N_i eps`` with ``s_ij`` the sign of ``N_i · D_j``
    (+1 at 0). Only the points and directions travel, not one origin and direction per ray (the NumPy form
    built 12 floats a ray, ~2 s of a source's 62 M rays)."""
    import drjit as dr

    from ..jitarrays import to_jit

    F64 = mi.Float64
    UInt32 = mi.UInt32
    nd = len(D)
    Dd = [to_jit(F64, D[:, k]) for k in range(3)]
    out = np.zeros((len(O), nd), bool)
    for a in range(0, len(O), step):
        o, n = O[a:a + step], N[a:a + step]
        m = len(o) * nd
        Od, Nd = [to_jit(F64, o[:, k]) for k in range(3)], [to_jit(F64, n[:, k]) for k in range(3)]
        r = dr.arange(UInt32, m)
        i = r // nd
        j = r - i * nd
        d = [dr.gather(F64, Dd[k], j) for k in range(3)]
        nn = [dr.gather(F64, Nd[k], i) for k in range(3)]
        cos = nn[0] * d[0] + nn[1] * d[1] + nn[2] * d[2]
        side = dr.select(cos < 0, -1.0, 1.0)
        org = [dr.gather(F64, Od[k], i) + (side * nn[k]) * eps for k in range(3)]
        ray = mi.Ray3f(mi.Point3f(*[mi.Float(x) for x in org]), mi.Vector3f(*[mi.Float(x) for x in d]))
        hit = scene.ray_test(ray)
        out[a:a + step] = ~np.asarray(hit, bool).reshape(len(o), nd)
    return out


#: the most surfaces a near-rule ray passes through (:func:`near_free`; ``facerf_direct`` uses the same bound)
NEAR_PASSES = 6


def near_free(mi, scene, origins, directions, near: float) -> np.ndarray:
    """(N,) bool: rays (float32 (N, 3) origins and unit directions) that meet no surface of ``scene`` farther
    than ``near`` from their origin — the surfaces within ``near`` are passed through (at most
    :data:`NEAR_PASSES` of them; a ray still inside that band after as many counts as blocked)."""
    start = np.asarray(origins, np.float64)
    D = np.asarray(directions, np.float64)
    cur = start.copy()
    free = np.zeros(len(start), bool)
    todo = np.ones(len(start), bool)
    for _ in range(NEAR_PASSES):
        idx = np.nonzero(todo)[0]
        if not len(idx):
            break
        hit = scene.ray_intersect(mi.Ray3f(mi.Point3f(cur[idx].T.astype(np.float32)),
                                           mi.Vector3f(D[idx].T.astype(np.float32))))
        valid, t = np.asarray(hit.is_valid(), bool), np.asarray(hit.t, np.float64)
        at = cur[idx] + D[idx] * np.where(valid, t, 0.0)[:, None]
        inside = valid & (np.linalg.norm(at - start[idx], axis=1) <= near)
        free[idx[~valid]] = True
        todo[idx[~inside]] = False
        cur[idx[inside]] = at[inside] + D[idx[inside]] * NEAR_STEP
    return free


#: metres a near-rule ray moves past a surface it passes through before it is traced on
NEAR_STEP = 1e-5


def triangle_visibility(vertices, triangles, directions, rule: str = "cell", order: int = GRID_ORDER,
                        n: int = CELL_SAMPLES, near: float = 0.0, curved: int = 1,
                        weights: np.ndarray | None = None) -> np.ndarray:
    """(F, (order+1)², L) float32: the self-visibility of each light (``rule`` as :func:`visibility`) at the
    grid points of every triangle (:func:`grid_barycentrics`), traced from the point on the triangle with its
    geometric normal — what the integrator's shadow rays from a hit there let through (``near`` > 0: rays that
    pass through the mesh's surface within ``near`` metres, as ``facerf_direct``'s do, :func:`_free_from`).

    The per-vertex values (:func:`cell_visibility`) interpolated across a triangle of a coarse template miss
    what happens inside it: in a crease (under the lower lip) the vertices sit in the fold, their cells
    mostly blocked (v ≈ 0.2), while the triangle's interior sees the frontal lights freely — the material's
    division by the interpolated v made those pixels 3–4× too bright (draft model, docs/rendering.md).

    ``curved`` > 1: the surface is the Phong surface of that level (:mod:`~mifacerf.geometry.boubekeur2008`,
    the skin a ``facerf_face`` shape puts in the scene for a model of that ``surface``): a grid point lies on
    the flat sub-face holding its barycentrics, the ray leaves it with that sub-face's normal, and the rays
    meet the Phong surface — what the shadow rays from a hit there meet. Flat (1), the template's triangles:
    on the demo model's Phong scene these disagreed with the shadow rays on the tilted facets beside the nose
    (docs/rendering.md, "The visibility on the surface the scene traces").

    ``weights`` (n,) ≥ 0, rule ``cell`` only: the share of a cell is weighted by these per-sample weights (the
    radiance of the scene's environment along each of :func:`cell_directions`' samples,
    :func:`emitter_weights`) — the visible share *of the cell's light*, which is what the shadow rays pass
    of it under that environment; a cell whose samples all weigh 0 keeps the unweighted share."""
    if rule not in VISIBILITY_RULES:
        raise ValueError(f"self-visibility rule {rule!r} is not one of {', '.join(VISIBILITY_RULES)}")
    w = check_sample_weights(weights, n, rule)
    V = np.asarray(vertices, np.float64)
    F = np.asarray(triangles, np.int64).reshape(-1, 3)
    Ld = np.asarray(directions, np.float64)
    B = grid_barycentrics(order)
    k = int(order)
    ij = np.array([(i, j) for i in range(k + 1) for j in range(k + 1)])
    valid = ij.sum(1) <= k
    if int(curved) > 1:
        V, F, P, Nn = _on_phong_surface(V, F, B[valid], int(curved))
    else:
        P = np.einsum("gk,fkd->fgd", B[valid], V[F])                   # (F, Pv, 3)
        nrm = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
        nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-30)
        Nn = np.repeat(nrm[:, None], valid.sum(), 1)
    n_faces = len(np.asarray(triangles).reshape(-1, 3))
    if rule == "ray":
        vis = _free_from(V, F, P.reshape(-1, 3), Nn.reshape(-1, 3), Ld, near=near).astype(np.float32)
    else:
        samples, cell = cell_directions(Ld, n)
        free = _free_from(V, F, P.reshape(-1, 3), Nn.reshape(-1, 3), samples, near=near).astype(np.float32)
        count = np.bincount(cell, minlength=len(Ld)).astype(np.float64)
        onehot = np.zeros((len(samples), len(Ld)), np.float32)
        onehot[np.arange(len(samples)), cell] = 1
        vis = free @ onehot
        empty = count == 0
        vis[:, ~empty] /= count[~empty]
        if w is not None:   # the share of each cell's light: Σ w free / Σ w over its samples, where it has light
            wsum = w @ onehot.astype(np.float64)
            lit = wsum > 0
            if lit.any():
                wv = free @ (onehot[:, lit] * w[:, None].astype(np.float32))
                vis[:, lit] = np.clip(wv / wsum[lit].astype(np.float32), 0.0, 1.0)
        if empty.any():
            vis[:, empty] = _free_from(V, F, P.reshape(-1, 3), Nn.reshape(-1, 3), Ld[empty],
                                       near=near).astype(np.float32)
    out = np.ones((n_faces, len(B), len(Ld)), np.float32)
    out[:, valid] = vis.reshape(n_faces, valid.sum(), len(Ld))
    return out


def check_sample_weights(weights, n: int = CELL_SAMPLES, rule: str = "cell") -> np.ndarray | None:
    """``weights`` as float64 (n,), checked (finite, ≥ 0, not all 0, rule ``cell``); None stays None."""
    if weights is None:
        return None
    w = np.asarray(weights, np.float64)
    if rule != "cell":
        raise ValueError(f"self-visibility weights need the 'cell' rule (got rule {rule!r})")
    if w.shape != (n,):
        raise ValueError(f"self-visibility weights must have shape ({n},), one per cell sample; got {w.shape}")
    if not (np.isfinite(w).all() and (w >= 0).all() and w.sum() > 0):
        raise ValueError(f"self-visibility weights {w.shape} must be finite, >= 0 and not all 0")
    return w


def emitter_weights(emitter, rotation=None, n: int = CELL_SAMPLES) -> np.ndarray:
    """(n,) float64: the luminance (Rec. 709) of a Mitsuba infinite emitter (``envmap``, ``constant``) along
    :func:`cell_directions`' samples, which are in the model's frame; ``rotation`` (3, 3) takes them into the
    world (the face shape's ``to_world``; default the identity). The ``weights`` of :func:`triangle_visibility`."""
    from ..environment import evaluate_emitter
    from ..imageio import LUMINANCE

    samples, _ = cell_directions(np.eye(3), n)
    R = np.eye(3) if rotation is None else np.asarray(rotation, np.float64)
    if R.shape != (3, 3):
        raise ValueError(f"rotation must be (3, 3); got {R.shape}")
    d = samples @ R.T
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    rgb = evaluate_emitter(emitter, d).astype(np.float64)
    return np.maximum(rgb @ LUMINANCE, 0.0)


def _weights_tag(weights) -> str:
    """A short hash of the sample weights ('' for none): part of the caches' keys."""
    if weights is None:
        return ""
    import hashlib

    return hashlib.sha256(np.ascontiguousarray(np.asarray(weights, np.float64)).tobytes()).hexdigest()[:16]


def _on_phong_surface(V, F, bary, level: int):
    """The Phong surface of level ``level`` over vertices ``V`` (T, 3) and triangles ``F`` (F, 3), and the points
    of barycentrics ``bary`` (G, 3) of every triangle on it: (sub-vertices (T', 3), sub-faces (F', 3), points
    (F, G, 3) on the flat sub-face holding each, that sub-face's unit normal (F, G, 3)). The sub-face is the one
    whose corners' barycentrics (``PhongTessellation.corner_bary``) hold the point with all weights >= 0 — the
    inverse of the scene's map from a sub-face hit to the template triangle."""
    from ..geometry.boubekeur2008 import PhongTessellation

    t = PhongTessellation(F, len(V), level)
    Vs = t.positions(V)
    per = level * level                                    # every face is curved: its sub-faces are contiguous
    C = t.corner_bary.reshape(len(F), per, 3, 3)           # (F, per, corner k, coarse barycentric)
    Minv = np.linalg.inv(np.transpose(C[0], (0, 2, 1)))    # the same lattice in every face: (per, 3, 3)
    w = np.einsum("skc,gc->gsk", Minv, np.asarray(bary, np.float64))   # (G, per, 3) weights on each sub-face
    sub = np.argmax(w.min(-1), axis=1)                     # (G,) the sub-face holding each grid point
    wg = w[np.arange(len(bary)), sub]                      # (G, 3)
    faces = t.faces.reshape(len(F), per, 3)[:, sub]        # (F, G, 3)
    corners = Vs[faces]                                    # (F, G, 3, 3)
    P = np.einsum("gk,fgkd->fgd", wg, corners)
    nrm = np.cross(corners[:, :, 1] - corners[:, :, 0], corners[:, :, 2] - corners[:, :, 0])
    nrm /= np.maximum(np.linalg.norm(nrm, axis=-1, keepdims=True), 1e-30)
    return Vs, t.faces, P, nrm


def source_triangle_visibility(model, source: int, rule: str = "cell", order: int = GRID_ORDER,
                               near: float = 0.0, curved: int = 1, weights=None) -> np.ndarray:
    """:func:`triangle_visibility` of source expression ``source`` of ``model`` against its registered mesh
    (cached in memory per model folder, source, rule, order, ``near`` and ``weights``, and on disk by what it is
    computed from: :func:`cached_triangle_visibility`; computed when a material first uses it)."""
    key = (_key(model), "grid", int(source), rule, int(order), float(near), int(curved), _weights_tag(weights))
    with _LOCK:
        if key not in _CACHE:
            _CACHE[key] = cached_triangle_visibility(model.vertices[source], model.triangles,
                                                     model.light_directions, rule, order, near=near,
                                                     curved=curved, weights=weights)
        return _CACHE[key]


def _disk_path(vertices, triangles, directions, rule, order, near, curved: int = 1, weights=None) -> Path | None:
    import hashlib

    from ..formats.files import switched_off, user_cache_dir

    if switched_off("MIFACERF_VISIBILITY_CACHE"):
        return None
    what = (CACHE_VERSION, rule, int(order), float(near), CELL_SAMPLES) + ((int(curved),) if int(curved) > 1 else ())
    if weights is not None:
        what += (_weights_tag(weights),)
    h = hashlib.sha256(repr(what).encode())
    for a in (np.asarray(vertices, np.float64), np.asarray(triangles, np.int64), np.asarray(directions, np.float64)):
        h.update(repr(a.shape).encode())
        h.update(np.ascontiguousarray(a).tobytes())
    return user_cache_dir() / "visibility" / f"grid-{h.hexdigest()[:32]}.npy"


def cached_triangle_visibility(vertices, triangles, directions, rule: str = "cell", order: int = GRID_ORDER,
                               near: float = 0.0, curved: int = 1, weights=None) -> np.ndarray:
    """:func:`triangle_visibility`, read from the user's cache when an earlier process computed it from the
    same inputs (module doc), else computed and written there (atomically)."""
    import warnings

    from ..formats.files import save_npy_atomic

    path = _disk_path(vertices, triangles, directions, rule, order, near, curved, weights)
    want = (len(np.asarray(triangles).reshape(-1, 3)), len(grid_barycentrics(order)), len(directions))
    if path is not None and path.exists():
        try:
            got = np.load(path, allow_pickle=False)
            if got.shape == want and got.dtype == np.float32 and np.all((got >= 0) & (got <= 1)):
                try:
                    os.utime(path)                      # used now: the last to go when the cache is trimmed
                except OSError:
                    pass
                return got
            problem = f"shape {got.shape} {got.dtype}, want {want} float32 in [0, 1]"
        except (OSError, ValueError, EOFError) as exc:
            problem = str(exc) or type(exc).__name__
        warnings.warn(f"{path}: a damaged self-visibility cache file ({problem}); recomputed", stacklevel=2)
    out = triangle_visibility(vertices, triangles, directions, rule, order, near=near, curved=curved, weights=weights)
    if path is not None:
        try:
            save_npy_atomic(path, out)
            trim_cache(path.parent)
        except OSError:
            pass
    return out


#: the disk cache's bound in MB (``MIFACERF_VISIBILITY_CACHE_MB``): beyond it the least recently used grids go
CACHE_MB = 2048


def trim_cache(folder: Path, limit_mb: float | None = None) -> list[Path]:
    """Delete the least recently used grids (by modification time, which a read renews) of ``folder`` until
    the rest hold at most ``limit_mb`` (default ``$MIFACERF_VISIBILITY_CACHE_MB``, else :data:`CACHE_MB`);
    the newest is always kept. Returns the files deleted."""
    if limit_mb is None:
        raw = os.environ.get("MIFACERF_VISIBILITY_CACHE_MB", "").strip()
        try:
            limit_mb = float(raw) if raw else CACHE_MB
            if not limit_mb >= 0:
                raise ValueError
        except ValueError:
            import warnings

            warnings.warn(f"MIFACERF_VISIBILITY_CACHE_MB={raw!r} is not a size in MB >= 0; {CACHE_MB} used",
                          stacklevel=2)
            limit_mb = CACHE_MB
    entries = []
    for p in folder.glob("grid-*.npy"):
        try:
            st = p.stat()
        except OSError:
            continue
        entries.append((st.st_mtime_ns, st.st_size, p))
    entries.sort(reverse=True)                           # newest first
    total, gone = 0, []
    for i, (_, size, p) in enumerate(entries):
        total += size
        if i and total > limit_mb * 1e6:
            try:
                p.unlink()
                gone.append(p)
            except OSError:
                pass
    return gone
