"""Coherent expression culling (paper §5.1).

For each user-defined region (forehead, mouth, neck, throat, chin, left/right
cheek, left/right eye) every source expression's region is rigidly aligned
(Horn 1987) onto the neutral's; the aligned positions are the region's
deformation vector.  Two expressions are *similar* when the distance between
their deformation vectors is below a threshold; a maximal independent set of
this similarity graph, found by the **minimum-degree greedy** algorithm, is the
set of expressions the region keeps.

Conventions (documented choices beyond the paper):

* **Threshold units.**  ``similarity_threshold`` is an RMS distance per region
  vertex in metres: expressions ``i, j`` are connected when
  ``‖D_i − D_j‖₂ / sqrt(|region|) < similarity_threshold``.  (The paper's plain
  L2 threshold is ``similarity_threshold · sqrt(|region|)``; the RMS form lets
  one value serve regions of different sizes.)
* **The neutral is always kept**: it is put into the set first (with its
  neighbours removed), then the greedy algorithm runs on what remains, so the
  set is still maximal.  The neutral is the expression the ``m = 0`` rule of
  blending falls back to.
* **Greedy rule.**  Repeatedly take the vertex of minimum degree *in the
  remaining graph* (ties: smallest index), add it to the set, delete it and its
  neighbours.
* **Composition with per-vertex weights** (see :func:`allowed_sources`): a
  vertex in one region may use only that region's kept expressions; a vertex in
  several regions may use the **union** of their kept sets (so overlapping
  regions blend smoothly into each other); a vertex in no region is not culled
  (all sources).

Region files for real templates are JSON: ``{"regions": {"forehead": [vertex ids...], ...}}``
(:func:`load_regions`, :func:`save_regions`); a registration template file (``mifacerf.template/1``,
which has the same ``regions`` member) loads directly; the model build takes them from the
registration template.
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass

import numpy as np

from .deformation import region_deformations

__all__ = [
    "REGION_NAMES",
    "similarity_graph",
    "min_degree_greedy_mis",
    "cull_region",
    "cull_regions",
    "CullingResult",
    "allowed_sources",
    "load_regions",
    "save_regions",
    "check_regions",
]

#: the paper's regions (§5.1), named as in the registration template (``mifacerf.template/1``), whose
#: synthetic subject adds a tenth, ``nose``
REGION_NAMES = ("forehead", "mouth", "neck", "throat", "chin", "cheek_left", "cheek_right", "eye_left", "eye_right")


def similarity_graph(D, threshold: float) -> np.ndarray:
    """Adjacency ``(n, n)`` bool of deformation vectors ``D`` ``(n, R, 3)``: RMS distance < threshold.

    The diagonal is False.
    """
    D = np.asarray(D, dtype=np.float64)
    n, R = D.shape[0], D.shape[1]
    X = D.reshape(n, -1)
    d2 = np.sum((X[:, None, :] - X[None, :, :]) ** 2, axis=2) / max(R, 1)
    A = d2 < float(threshold) ** 2
    np.fill_diagonal(A, False)
    return A


def min_degree_greedy_mis(adjacency, first=None) -> np.ndarray:
    """Maximal independent set by the minimum-degree greedy algorithm.

    Parameters
    ----------
    adjacency : array_like, shape ``(n, n)`` bool, symmetric
    first : int, optional
        A vertex forced into the set before the greedy steps (the neutral).

    Returns
    -------
    ndarray of int64: the chosen vertices, ascending.
    """
    A = np.array(adjacency, dtype=bool)
    n = A.shape[0]
    if A.shape != (n, n) or not np.array_equal(A, A.T):
        raise ValueError(f"adjacency must be a symmetric (n, n) matrix; got shape {A.shape}")
    A = A & ~np.eye(n, dtype=bool)
    alive = np.ones(n, dtype=bool)
    chosen = []

    def take(v):
        chosen.append(v)
        alive[v] = False
        alive[A[v]] = False

    if first is not None:
        take(int(first))
    while np.any(alive):
        deg = np.where(alive, (A & alive[None, :]).sum(axis=1), n + 1)
        take(int(np.argmin(deg)))          # argmin: smallest index among ties
    return np.array(sorted(chosen), dtype=np.int64)


def cull_region(sources, neutral_index: int, vertex_ids, similarity_threshold: float) -> np.ndarray:
    """Kept source ids (ascending) of one region; ``sources`` ``(n, V, 3)``."""
    sources = np.asarray(sources, dtype=np.float64)
    D = region_deformations(sources, sources[neutral_index], vertex_ids)
    A = similarity_graph(D, similarity_threshold)
    return min_degree_greedy_mis(A, first=neutral_index)


@dataclass
class CullingResult:
    """Result of :func:`cull_regions`.

    Attributes
    ----------
    kept : dict[str, ndarray]   kept source ids per region (ascending)
    membership : ndarray ``(V, n_regions)`` bool, columns in ``names`` order
    names : tuple[str, ...]
    """

    kept: dict
    membership: np.ndarray
    names: tuple


def check_regions(regions, n_vertices: int) -> dict:
    """Validate ``{name: vertex ids}`` and return it with int64 arrays."""
    out = {}
    for name, ids in dict(regions).items():
        a = np.unique(np.asarray(ids, dtype=np.int64).ravel())
        if a.size == 0:
            raise ValueError(f"region {name!r} is empty")
        if a.min() < 0 or a.max() >= n_vertices:
            raise ValueError(f"region {name!r} has vertex ids outside [0, {n_vertices})")
        out[str(name)] = a
    return out


def cull_regions(sources, neutral_index: int, regions, similarity_threshold: float) -> CullingResult:
    """Cull every region.  ``regions``: ``{name: vertex ids}``; ``sources`` ``(n, V, 3)``."""
    sources = np.asarray(sources, dtype=np.float64)
    V = sources.shape[1]
    regions = check_regions(regions, V)
    names = tuple(regions)
    membership = np.zeros((V, len(names)), dtype=bool)
    kept = {}
    for k, name in enumerate(names):
        membership[regions[name], k] = True
        kept[name] = cull_region(sources, neutral_index, regions[name], similarity_threshold)
    return CullingResult(kept=kept, membership=membership, names=names)


def allowed_sources(culling: CullingResult | None, n_sources: int, vertices) -> list[np.ndarray]:
    """Source ids each vertex may blend (rule in the module docstring); one ascending array per vertex."""
    vertices = np.asarray(vertices, dtype=np.int64)
    everything = np.arange(n_sources, dtype=np.int64)
    if culling is None:
        return [everything for _ in vertices]
    kept_mask = np.zeros((len(culling.names), n_sources), dtype=bool)
    for k, name in enumerate(culling.names):
        kept_mask[k, culling.kept[name]] = True
    out = []
    for v in vertices:
        regs = culling.membership[v]
        if not np.any(regs):
            out.append(everything)
        else:
            out.append(np.nonzero(kept_mask[regs].any(axis=0))[0].astype(np.int64))
    return out


def load_regions(path) -> dict:
    """Read a region file ``{"regions": {"forehead": [ids...], ...}}`` into ``{name: int64 array}``."""
    with open(os.fspath(path), encoding="utf-8") as f:
        data = json.load(f)
    if not isinstance(data, dict) or not isinstance(data.get("regions"), dict):
        raise ValueError(f"{path}: expected a JSON object with a 'regions' object")
    return {str(k): np.asarray(v, dtype=np.int64) for k, v in data["regions"].items()}


def save_regions(path, regions) -> None:
    """Write ``{name: vertex ids}`` as a region file (see :func:`load_regions`)."""
    data = {"regions": {str(k): [int(i) for i in np.asarray(v).ravel()] for k, v in regions.items()}}
    with open(os.fspath(path), "w", encoding="utf-8") as f:
        json.dump(data, f, indent=1)
        f.write("\n")
