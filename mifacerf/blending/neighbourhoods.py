"""Graph neighbourhoods of template vertices (paper §5: "vertices V with shortest path from v ≤ 2").

The graph is the edge graph of the template's triangles.  A neighbourhood always
contains its centre vertex.  Neighbourhoods have different sizes; they are stored
padded in a :class:`Neighbourhoods` (index array padded with the centre, a
boolean mask marking the real entries), which is what every vectorised
consumer (Horn on all neighbourhoods at once, the Dr.Jit evaluator) wants.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from ..geometry.graph import edge_graph

__all__ = ["Neighbourhoods", "neighbourhoods", "edge_graph"]


@dataclass(frozen=True)
class Neighbourhoods:
    """Padded neighbourhoods.

    Attributes
    ----------
    index : ndarray, shape ``(V, K)``, int32
        ``index[v, :count[v]]`` are the vertices of ``v``'s neighbourhood, centre first, then
        ascending; the rest is padding equal to ``v``.
    count : ndarray, shape ``(V,)``, int32
        Number of real entries per row (>= 1).
    """

    index: np.ndarray
    count: np.ndarray

    @property
    def mask(self) -> np.ndarray:
        """``(V, K)`` bool: True on real entries, False on padding."""
        return np.arange(self.index.shape[1])[None, :] < self.count[:, None]

    @property
    def n_vertices(self) -> int:
        return int(self.index.shape[0])

    def subset(self, rows) -> "Neighbourhoods":
        """The neighbourhoods of the vertices ``rows`` (indices keep referring to the full template)."""
        rows = np.asarray(rows)
        return Neighbourhoods(self.index[rows], self.count[rows])

    def as_lists(self) -> list[np.ndarray]:
        return [self.index[v, : self.count[v]].copy() for v in range(self.n_vertices)]

    @classmethod
    def from_lists(cls, lists) -> "Neighbourhoods":
        """From a sequence of index arrays (one per vertex; the first entry should be the centre)."""
        lists = [np.asarray(a, dtype=np.int64).ravel() for a in lists]
        if any(a.size == 0 for a in lists):
            raise ValueError("Neighbourhoods.from_lists: every neighbourhood needs at least one vertex")
        K = max(a.size for a in lists)
        index = np.empty((len(lists), K), dtype=np.int32)
        for v, a in enumerate(lists):
            index[v, : a.size] = a
            index[v, a.size:] = a[0]
        return cls(index, np.array([a.size for a in lists], dtype=np.int32))


def neighbourhoods(triangles, n_vertices: int | None = None, rings: int = 2) -> Neighbourhoods:
    """Vertices within ``rings`` edges of each vertex (default 2, as in the paper).

    Parameters
    ----------
    triangles : array_like, shape ``(F, 3)``
        Template triangles (vertex indices).
    n_vertices : int, optional
        Number of template vertices (default: ``max(triangles) + 1``).  Vertices in no triangle get
        the neighbourhood ``{v}``.
    rings : int
        Graph radius (>= 0).
    """
    if rings < 0:
        raise ValueError(f"rings must be >= 0; got {rings}")
    A = edge_graph(triangles, n_vertices)
    V = A.shape[0]
    I = sp.identity(V, dtype=np.int64, format="csr")
    step = (A.astype(np.int64) + I).tocsr()
    reach = I
    for _ in range(rings):
        reach = (reach @ step).tocsr()
        reach.data[:] = 1
    reach.sort_indices()
    counts = np.diff(reach.indptr).astype(np.int32)
    K = int(counts.max()) if V else 1
    index = np.repeat(np.arange(V, dtype=np.int32)[:, None], K, axis=1)
    rows = np.repeat(np.arange(V), counts)
    # centre first: give it key -1, others their own index; stable order otherwise ascending
    cols = reach.indices.astype(np.int64)
    key = np.where(cols == rows, -1, cols)
    order = np.lexsort((key, rows))
    cols = cols[order]
    pos = np.arange(cols.size) - np.repeat(reach.indptr[:-1], counts)
    index[rows, pos] = cols
    return Neighbourhoods(index, counts)
