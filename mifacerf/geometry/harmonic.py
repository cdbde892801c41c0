"""Harmonic and biharmonic interpolation of values over a triangle mesh's edge graph.

Given values at some vertices (the *known* ones), the other vertices get the values of least energy,
with ``L`` the uniform graph Laplacian (degree minus adjacency):

* ``order=1``, membrane: ``L x = 0`` at every free vertex — each holds the mean of its edge neighbours;
* ``order=2``, thin plate: ``|L x|²`` summed over *all* vertices is least (``Lᵀ L x = 0`` at the free
  ones) — linear trends continue past the known vertices instead of flattening between them.

These are the linear variational deformations of Botsch & Sorkine, "On linear variational surface
deformation methods", IEEE TVCG 14(1), 2008 (§3), on the mesh's connectivity only: values travel
along the surface, so they do not jump across a hole of the mesh (an open mouth, an eye) as a
nearest-neighbour or distance-weighted rule in 3-D does.

Registration uses it to carry the registered fiducials' displacement (measured − predicted) to the
fiducials the first pass left, before searching for them again (:mod:`mifacerf.registration.register`).

Conventions: ``values`` (K, D) any unit, rows matching ``known_ids`` (K,); result (N, D) float64.
A free vertex in a connected component with no known vertex (or a vertex in no triangle) gets
``fill`` (default 0: no displacement); the result is always finite for finite input.
"""
from __future__ import annotations

import numpy as np

from .graph import edge_graph


def harmonic_interpolation(n_vertices: int, faces, known_ids, values, order: int = 1,
                           fill: float = 0.0) -> np.ndarray:
    """(N, D) values: ``values`` at ``known_ids``, of least membrane (``order=1``) or thin-plate
    (``order=2``) energy elsewhere (module docstring).

    ``faces`` (F, 3) vertex ids; ``known_ids`` (K,) distinct ids; ``values`` (K, D) or (K,).
    """
    if order not in (1, 2):
        raise ValueError(f"harmonic_interpolation: order must be 1 or 2, got {order!r}")
    from scipy.sparse import diags
    from scipy.sparse.csgraph import connected_components
    from scipy.sparse.linalg import spsolve

    F = np.asarray(faces, np.int64).reshape(-1, 3)
    kid = np.asarray(known_ids, np.int64).reshape(-1)
    vals = np.asarray(values, np.float64)
    squeeze = vals.ndim == 1
    if vals.ndim not in (1, 2) or len(vals) != len(kid):
        raise ValueError(f"harmonic_interpolation: values of shape {vals.shape} for {len(kid)} known ids "
                         "(expected (K,) or (K, D))")
    vals = vals.reshape(len(kid), -1)
    if len(np.unique(kid)) != len(kid):
        raise ValueError("harmonic_interpolation: known_ids repeat")
    if not np.isfinite(vals).all():
        raise ValueError("harmonic_interpolation: values must be finite")
    n = int(n_vertices)
    out = np.full((n, vals.shape[1]), float(fill))
    out[kid] = vals
    known = np.zeros(n, bool)
    known[kid] = True
    A = edge_graph(F, n).astype(np.float64)
    # free vertices whose component holds a known vertex; the rest keep ``fill``
    _, comp = connected_components(A, directed=False)
    anchored = np.zeros(comp.max() + 1 if n else 0, bool)
    anchored[comp[known]] = True
    free = ~known & anchored[comp]
    if not free.any():
        return out[:, 0] if squeeze else out
    deg = np.asarray(A.sum(1)).ravel()
    L = (diags(deg) - A).tocsr()
    Q = L if order == 1 else (L.T @ L).tocsr()
    Qff = Q[free][:, free].tocsc()
    rhs = -(Q[free][:, known] @ out[known])             # the known values in the mask's (sorted) order
    sol = spsolve(Qff, rhs)
    out[free] = np.asarray(sol).reshape(int(free.sum()), -1)
    return out[:, 0] if squeeze else out
