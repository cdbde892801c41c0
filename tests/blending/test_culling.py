"""Coherent expression culling (paper §5.1): similarity graph, minimum-degree greedy MIS, regions."""
import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mifacerf.blending import load_regions, save_regions
from mifacerf.blending.culling import (
    CullingResult, allowed_sources, cull_region, cull_regions, min_degree_greedy_mis, similarity_graph,
)


def is_maximal_independent(A, S):
    S = set(S.tolist())
    indep = all(not A[i, j] for i in S for j in S if i != j)
    maximal = all(any(A[v, s] for s in S) for v in range(len(A)) if v not in S)
    return indep and maximal


def graph(n, edges):
    A = np.zeros((n, n), bool)
    for i, j in edges:
        A[i, j] = A[j, i] = True
    return A


def test_min_degree_greedy_on_a_star_takes_the_leaves():
    A = graph(5, [(0, 1), (0, 2), (0, 3), (0, 4)])
    assert min_degree_greedy_mis(A).tolist() == [1, 2, 3, 4]
    # forcing the hub (the "neutral") first leaves nothing else
    assert min_degree_greedy_mis(A, first=0).tolist() == [0]


def test_min_degree_greedy_recomputes_degrees():
    # path 0-1-2-3-4: min degree picks 0 (ties → smallest), removes 1; then 2's degree is 1 → picks 2...
    A = graph(5, [(0, 1), (1, 2), (2, 3), (3, 4)])
    assert min_degree_greedy_mis(A).tolist() == [0, 2, 4]


@pytest.mark.parametrize("seed", range(10))
def test_result_is_a_maximal_independent_set(seed):
    rng = np.random.default_rng(seed)
    n = 15
    A = np.triu(rng.random((n, n)) < 0.3, 1)
    A = A | A.T
    for first in (None, 3):
        S = min_degree_greedy_mis(A, first=first)
        assert is_maximal_independent(A, S)
        if first is not None:
            assert first in S


def test_rejects_asymmetric():
    with pytest.raises(ValueError):
        min_degree_greedy_mis(np.array([[0, 1], [0, 0]], bool))


def crafted_sources():
    """Neutral sheet + expressions whose region deformations are known exactly.

    Region A = vertices 0..4, region B = vertices 5..9.  Expressions (ids):
      0 neutral; 1 bends A (5 mm); 2 = 1 plus 0.05 mm (similar to 1); 3 bends A the other way;
      4 bends B only; 5 = pure rigid motion of the neutral (similar to 0 everywhere);
      6 bends A and B a little (0.1 mm: similar to neutral)
    """
    rng = np.random.default_rng(0)
    X = np.c_[rng.random((10, 2)) * 0.05, np.zeros(10)]
    bump = np.zeros((10, 3))
    bump[:5, 2] = [0.0, 1.0, 2.0, 1.0, 0.0]
    bumpB = np.zeros((10, 3))
    bumpB[5:, 2] = [0.0, 1.0, 2.0, 1.0, 0.0]
    R = Rotation.from_rotvec([0.1, -0.2, 0.05]).as_matrix()
    S = np.stack([X, X + 5e-3 * bump, X + 5.05e-3 * bump, X - 5e-3 * bump, X + 5e-3 * bumpB,
                  X @ R.T + [0.01, 0.02, 0.0], X + 1e-4 * (bump + bumpB)])
    return S, {"A": np.arange(5), "B": np.arange(5, 10)}


def test_culling_keeps_the_right_expressions():
    S, regions = crafted_sources()
    res = cull_regions(S, 0, regions, similarity_threshold=5e-4)
    # region A: {0, 5, 4, 6} look neutral → only 0; {1, 2} similar → one of them; 3 distinct
    assert res.kept["A"].tolist() == [0, 1, 3] or res.kept["A"].tolist() == [0, 2, 3]
    # region B: only expression 4 deforms B
    assert res.kept["B"].tolist() == [0, 4]
    # a tiny threshold keeps everything but the expressions that are exactly neutral in A (4, 5)
    assert cull_region(S, 0, regions["A"], 1e-9).tolist() == [0, 1, 2, 3, 6]


def test_region_deformation_is_rigid_invariant():
    S, regions = crafted_sources()
    R = Rotation.from_rotvec([0.3, 0.1, -0.2]).as_matrix()
    S2 = S.copy()
    S2[3] = S[3] @ R.T + 0.1
    a = cull_regions(S, 0, regions, 5e-4).kept
    b = cull_regions(S2, 0, regions, 5e-4).kept
    assert {k: v.tolist() for k, v in a.items()} == {k: v.tolist() for k, v in b.items()}


def test_similarity_graph_threshold_is_rms():
    D = np.zeros((2, 4, 3))
    D[1, :, 0] = 1e-3                       # every vertex 1 mm apart → RMS distance 1 mm
    assert not similarity_graph(D, 1e-3)[0, 1]
    assert similarity_graph(D, 1.0001e-3)[0, 1]


def test_allowed_sources_union_rule():
    membership = np.array([[1, 0], [1, 1], [0, 0], [0, 1]], bool)
    res = CullingResult(kept={"a": np.array([0, 2]), "b": np.array([0, 3])}, membership=membership,
                        names=("a", "b"))
    got = allowed_sources(res, 5, np.arange(4))
    assert [g.tolist() for g in got] == [[0, 2], [0, 2, 3], [0, 1, 2, 3, 4], [0, 3]]
    assert [g.tolist() for g in allowed_sources(None, 3, [0, 1])] == [[0, 1, 2], [0, 1, 2]]


def test_region_file_roundtrip(tmp_path):
    regions = {"forehead": np.array([3, 1, 2]), "mouth": np.array([7])}
    p = tmp_path / "regions.json"
    save_regions(p, regions)
    data = json.loads(p.read_text())
    assert data == {"regions": {"forehead": [3, 1, 2], "mouth": [7]}}
    back = load_regions(p)
    assert back.keys() == regions.keys() and all(np.array_equal(back[k], regions[k]) for k in regions)
    # a registration template file (mifacerf.template/1) has the same "regions" member
    p.write_text(json.dumps({"schema": "mifacerf.template/1", "vertices": [], "regions": {"chin": [4, 5]}}))
    assert load_regions(p)["chin"].tolist() == [4, 5]
    p.write_text('{"nope": 1}')
    with pytest.raises(ValueError):
        load_regions(p)


def test_bad_regions():
    S, _ = crafted_sources()
    with pytest.raises(ValueError):
        cull_regions(S, 0, {"a": [0, 99]}, 1e-3)
    with pytest.raises(ValueError):
        cull_regions(S, 0, {"a": []}, 1e-3)
