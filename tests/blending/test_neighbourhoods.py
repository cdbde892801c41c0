"""Graph neighbourhoods (paper §5: shortest path <= 2)."""
from collections import deque

import numpy as np
import pytest

from mifacerf.blending import Neighbourhoods, neighbourhoods
from mifacerf.blending.toy import grid_mesh


def bfs(F, V, v, rings):
    adj = [set() for _ in range(V)]
    for a, b, c in F:
        for x, y in ((a, b), (b, c), (c, a)):
            adj[x].add(y)
            adj[y].add(x)
    dist = {v: 0}
    q = deque([v])
    while q:
        u = q.popleft()
        if dist[u] == rings:
            continue
        for w in adj[u]:
            if w not in dist:
                dist[w] = dist[u] + 1
                q.append(w)
    return set(dist)


def test_grid_interior_two_ring_has_19_vertices():
    V, F = grid_mesh(7, 7)
    nb = neighbourhoods(F, len(V))
    centre = 3 * 7 + 3
    assert nb.count[centre] == 19          # 1 + 6 + 12 on a regular valence-6 grid
    assert nb.index[centre, 0] == centre
    assert nb.count.min() >= 4 and np.all(nb.mask.sum(1) == nb.count)


@pytest.mark.parametrize("rings", [0, 1, 2, 3])
def test_matches_breadth_first_search(rings):
    rng = np.random.default_rng(rings)
    V, F = grid_mesh(6, 5)
    F = F[rng.permutation(len(F))[: len(F) - 5]]        # a ragged mesh with holes
    nb = neighbourhoods(F, len(V) + 2, rings=rings)      # two isolated vertices
    for v in range(len(V) + 2):
        got = nb.index[v, : nb.count[v]]
        assert got[0] == v
        assert set(got.tolist()) == bfs(F, len(V) + 2, v, rings)
        assert np.all(nb.index[v, nb.count[v]:] == v)     # padding repeats the centre


def test_lists_roundtrip_and_errors():
    nb = Neighbourhoods.from_lists([[0, 1], [1], [2, 0, 1]])
    assert nb.index.shape == (3, 3) and list(nb.count) == [2, 1, 3]
    assert [a.tolist() for a in nb.as_lists()] == [[0, 1], [1], [2, 0, 1]]
    with pytest.raises(ValueError):
        neighbourhoods(np.zeros((3, 2), dtype=int))
    with pytest.raises(ValueError):
        neighbourhoods(np.array([[0, 1, 5]]), n_vertices=3)
