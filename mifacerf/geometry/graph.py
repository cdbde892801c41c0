"""The edge graph of a triangle mesh: which vertices share an edge.

One builder for every stage that walks a mesh's connectivity (harmonic interpolation, the dot graph of
the registration's snap, margin rings and propagation, the blend's neighbourhoods). Conventions: vertex
ids index ``(V,)``; a triangle ``(a, b, c)`` joins a–b, b–c, c–a; an edge shared by two triangles counts
once; no vertex is its own neighbour. scipy is loaded when a graph is built, not at import.
"""
from __future__ import annotations

import numpy as np


def edge_graph(triangles, n_vertices: int | None = None):
    """Symmetric ``(V, V)`` adjacency (``scipy.sparse`` CSR, bool) of the ``triangles``' (F, 3) edges;
    ``n_vertices`` default: the largest id + 1. Raises ``ValueError`` naming the shape or the id out of range."""
    import scipy.sparse as sp

    F = np.asarray(triangles)
    if F.size == 0:
        F = F.reshape(0, 3)
    if F.ndim != 2 or F.shape[1] != 3:
        raise ValueError(f"triangles must have shape (F, 3); got {F.shape}")
    F = F.astype(np.int64)
    if F.size and F.min() < 0:
        raise ValueError("triangles contain negative vertex indices")
    V = int(n_vertices) if n_vertices is not None else (int(F.max()) + 1 if F.size else 0)
    if F.size and F.max() >= V:
        raise ValueError(f"triangles reference vertex {int(F.max())} but there are only {V} vertices")
    i = np.concatenate([F[:, 0], F[:, 1], F[:, 2]])
    j = np.concatenate([F[:, 1], F[:, 2], F[:, 0]])
    A = sp.coo_matrix((np.ones(i.size, dtype=bool), (i, j)), shape=(V, V)).tocsr()
    A = (A + A.T).astype(bool)
    A.setdiag(False)
    A.eliminate_zeros()
    return A.tocsr()
