"""The captured self-visibility of each source expression, so the material can divide it out.

A captured reflectance field already holds the face's self-shadowing: texel x of source ``s`` lit
by light ``l`` is dark where the subject's own nose or brow stood between x and the light. Under
Mitsuba's integrators the material's shadow rays shadow the target face again (double shadowing).
Where the capture's visibility is *known* — ray-traced against the registered geometry of source
``s`` — the material divides it out, so the shadow rays alone supply the visibility of the target
geometry (and other objects in the scene shadow the face as they should).

``visibility(model)`` returns ``V`` (S, T, L) in [0, 1]: for every source expression, template
vertex and light-stage light, whether a ray from the vertex (offset along its normal by ``eps`` of
the face's size) towards the light escapes the source mesh. Per hit the material interpolates
``V`` at the triangle's barycentrics for the light it uses (``v``) and divides the field by it.

Fill where a light is (mostly) shadowed, ``v < MIN_VISIBILITY``: there the field holds little or no
information about the unshadowed response, so nothing is divided (the captured, dark value is kept,
divisor 1); division therefore only brightens the penumbra band ``MIN_VISIBILITY ≤ v < 1`` (by at most
``1 / MIN_VISIBILITY``) and never amplifies a fully shadowed texel's noise. Consequence: a captured
shadow that the target geometry would not cast (another expression's nose) stays dark — the material
shows the union of the captured shadow and the target's own, without the penumbra darkened twice.

Computed at load, once per model (in memory, keyed by the model folder and its manifest's
modification time; nothing is written to the model folder).
"""
from __future__ import annotations

import threading
from pathlib import Path

import numpy as np

MIN_VISIBILITY = 0.5
EPS = 1e-3

_CACHE: dict = {}
_LOCK = threading.Lock()


def _key(model):
    root = Path(model.root).resolve()
    marker = [p for p in (root / "model.json",) if p.exists()]
    return str(root), (marker[0].stat().st_mtime_ns if marker else 0)


def trace(vertices: np.ndarray, triangles: np.ndarray, directions: np.ndarray, eps: float = EPS) -> np.ndarray:
    """(T, L) float32: 1 where a ray from each vertex (offset along its normal by ``eps`` × the mesh's
    bounding-box diagonal) towards each direction meets no triangle of the mesh, else 0."""
    from ..geometry.visibility import vertex_normals
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
    scene = mi.load_dict({"type": "scene", "mesh": mesh})
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


def visibility(model) -> np.ndarray:
    """(S, T, L) float32 self-visibility of every source expression of ``model`` (see module docstring)."""
    key = _key(model)
    with _LOCK:
        if key not in _CACHE:
            _CACHE[key] = np.stack([trace(model.vertices[s], model.triangles, model.light_directions)
                                    for s in range(len(model.expressions))])
        return _CACHE[key]
