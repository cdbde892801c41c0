"""The procedural head: geometry, UV atlas, expression rig, rigid parts, presets."""
import numpy as np
import pytest
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from mifacerf.synthetic import CONTROLS, default_subject
from mifacerf.synthetic import head as H
from mifacerf.synthetic.expressions import fold_report, interior_edges
from mifacerf.synthetic.presets import CATEGORIES
from mifacerf.synthetic.textures import rasterize


@pytest.fixture(scope="module")
def subj():
    return default_subject()


@pytest.fixture(scope="module")
def neutral(subj):
    return subj.neutral


def _edges(F):
    e = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    return e


def test_skin_is_a_head_not_a_sphere(subj, neutral):
    V, F = neutral.skin_vertices, subj.skin_faces
    assert len(V) >= 5000
    assert F.min() >= 0 and F.max() < len(V)
    head = V[V[:, 1] > -0.115]
    width = np.ptp(head[:, 0])
    mid = V[(np.abs(V[:, 0]) < 0.004) & (V[:, 1] > -0.15)]
    chin = mid[mid[:, 2] > 0.045, 1].min()    # lowest point of the chin on the midline
    crown = V[:, 1].max()
    assert 0.14 < width < 0.17                       # a real head's width (ears included)
    assert 0.21 < crown - chin < 0.25                # chin to crown
    centre = 0.5 * (head.max(0) + head.min(0))
    assert np.linalg.norm(centre) < 0.04            # head centre near the origin
    # the face looks along +Z: the nose tip is the front-most point, on the midline
    tip = V[np.argmax(V[:, 2])]
    assert abs(tip[0]) < 0.003 and tip[2] > 0.10 and -0.05 < tip[1] < -0.01
    # not a sphere: the radius about the centre varies a lot
    r = np.linalg.norm(head - centre, axis=1)
    assert r.std() / r.mean() > 0.08


def test_skin_is_closed_except_the_slits(subj):
    F = subj.skin_faces
    e = np.sort(_edges(F), axis=1)
    u, c = np.unique(e, axis=0, return_counts=True)
    assert c.max() == 2
    boundary = {tuple(x) for x in u[c == 1]}
    slit_edges = set()
    for s in subj.grid.slits.values():
        for side in (s.upper, s.lower):
            chain = [s.corners[0], *side, s.corners[1]]
            slit_edges |= {tuple(sorted((int(a), int(b)))) for a, b in zip(chain[:-1], chain[1:])}
    assert boundary == slit_edges
    # consistent orientation: every directed edge once
    d = _edges(F)
    assert len(np.unique(d, axis=0)) == len(d)
    # outward: positive volume
    V = subj.skin_rest
    vol = np.einsum("ij,ij->i", V[F[:, 0]], np.cross(V[F[:, 1]], V[F[:, 2]])).sum() / 6
    assert vol > 0.002


def test_uv_atlas(subj):
    uv, UF, UV_of = subj.skin_uv, subj.skin_uv_faces, subj.skin_uv_vertex
    assert uv.min() >= 0.0 and uv.max() <= 1.0
    assert UF.shape == subj.skin_faces.shape
    np.testing.assert_array_equal(UV_of[UF], subj.skin_faces)   # same faces, seams split
    assert len(uv) > len(subj.skin_rest)                       # xatlas cut seams
    # charts: connected components of uv faces; no texel is covered by two charts
    n = len(uv)
    rows = np.concatenate([UF[:, 0], UF[:, 1]])
    cols = np.concatenate([UF[:, 1], UF[:, 2]])
    ncomp, label = connected_components(coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n)), directed=False)
    assert ncomp > 10
    chart = label[UF[:, 0]]
    # every (texel, face) pair with the texel centre strictly inside the face
    res = 512
    T = uv[UF] * res - 0.5
    lo = np.clip(np.floor(T.min(1)).astype(int), 0, res - 1)
    hi = np.clip(np.ceil(T.max(1)).astype(int), 0, res - 1)
    w, h = hi[:, 0] - lo[:, 0] + 1, hi[:, 1] - lo[:, 1] + 1
    cnt = w * h
    fid = np.repeat(np.arange(len(UF)), cnt)
    k = np.arange(cnt.sum()) - np.repeat(np.concatenate([[0], np.cumsum(cnt)[:-1]]), cnt)
    c = lo[fid, 0] + k % w[fid]
    r = lo[fid, 1] + k // w[fid]
    a, b, cc = T[fid, 0], T[fid, 1], T[fid, 2]
    v0, v1, v2 = b - a, cc - a, np.stack([c, r], 1) - a
    den = v0[:, 0] * v1[:, 1] - v1[:, 0] * v0[:, 1]
    with np.errstate(invalid="ignore", divide="ignore"):   # zero-area sliver triangles own no texel
        l1 = (v2[:, 0] * v1[:, 1] - v1[:, 0] * v2[:, 1]) / den
        l2 = (v0[:, 0] * v2[:, 1] - v2[:, 0] * v0[:, 1]) / den
    ok = np.minimum(np.minimum(l1, l2), 1 - l1 - l2) > 0.02
    texel = (r * res + c)[ok]
    ch = chart[fid[ok]]
    pairs = np.unique(np.stack([texel, ch], 1), axis=0)
    _, per_texel = np.unique(pairs[:, 0], return_counts=True)
    assert per_texel.max() == 1          # no texel belongs to two charts
    assert len(per_texel) > 0.4 * res * res


def test_texel_map_points_into_charts(subj):
    tri, bary, inside = rasterize(subj.skin_uv, subj.skin_uv_faces, 128)
    assert inside.mean() > 0.4
    assert np.all(bary[tri >= 0] >= -1e-6)
    np.testing.assert_allclose(bary[tri >= 0].sum(1), 1.0, atol=1e-5)


def test_controls_documented(subj):
    names = [c.name for c in subj.controls]
    assert len(set(names)) == len(names) >= 25
    for c in subj.controls:
        assert c.lo <= c.default <= c.hi and c.lo < c.hi and len(c.description) > 10
    for want in ("brow_raise_L", "frown", "smile_R", "pucker", "funnel", "lower_lip_tuck", "jaw_open",
                 "jaw_sideways", "blink_L", "eyes_wide", "gaze_yaw", "head_yaw", "head_pitch", "head_roll"):
        assert want in names
    p = subj.params(smile_L=0.5, head_yaw=0.1)
    assert p[names.index("smile_L")] == 0.5 and p[names.index("head_yaw")] == 0.1
    assert p[names.index("frown")] == 0.0
    with pytest.raises(KeyError):
        subj.params(no_such_control=1)
    with pytest.raises(ValueError):
        subj.pose(np.full(len(names), np.nan))


def test_neutral_reproduces_itself(subj, neutral):
    again = subj.pose(subj.params(), textures=False)
    np.testing.assert_array_equal(again.skin_vertices, neutral.skin_vertices)
    np.testing.assert_allclose(neutral.skin_vertices, subj.neutral_skin, atol=0)
    # the eyes are open in the neutral face, shut at rest
    es = subj.grid.slits["eye_left"]
    gap = np.linalg.norm(neutral.skin_vertices[es.upper] - neutral.skin_vertices[es.lower], axis=1)
    assert gap.max() > 0.007
    np.testing.assert_allclose(subj.skin_rest[es.upper], subj.skin_rest[es.lower])


def test_random_parameter_vectors_are_fold_free(subj, neutral):
    F = subj.skin_faces
    pairs = interior_edges(F)
    lo = np.array([c.lo for c in CONTROLS])
    hi = np.array([c.hi for c in CONTROLS])
    rng = np.random.default_rng(7)
    for i in range(10):
        p = lo + (hi - lo) * rng.random(len(lo))
        if i % 2:
            p = np.where(rng.random(len(lo)) < 0.5, [c.default for c in CONTROLS], p)
        V = subj.pose(p, textures=False).skin_vertices
        assert np.all(np.isfinite(V))
        ratio, folded = fold_report(neutral.skin_vertices, V, F, pairs)
        assert folded == 0, (i, folded)
        assert ratio > 0.08, (i, ratio)
    # every control alone at both ends of its range
    for c in CONTROLS:
        for v in (c.lo, c.hi):
            V = subj.pose(subj.params(**{c.name: v}), textures=False).skin_vertices
            ratio, folded = fold_report(neutral.skin_vertices, V, F, pairs)
            assert folded == 0 and ratio > 0.1, (c.name, v, ratio, folded)


def test_fold_report_detects_a_fold(subj, neutral):
    V = neutral.skin_vertices.copy()
    F = subj.skin_faces
    # drag one cheek vertex along the surface past its neighbours: its triangles flip over
    i = int(np.argmin(np.linalg.norm(V - [0.045, -0.02, 0.08], axis=1)))
    ring = np.unique(F[(F == i).any(1)])
    j = ring[ring != i][0]
    V[i] = V[i] + 2.5 * (V[j] - V[i])
    ratio, folded = fold_report(neutral.skin_vertices, V, F)
    assert folded > 0
    ratio, folded = fold_report(neutral.skin_vertices, neutral.skin_vertices, F)
    assert folded == 0 and abs(ratio - 1) < 1e-12


def test_expressions_move_the_right_places(subj, neutral):
    V0 = neutral.skin_vertices
    ms = subj.grid.slits["mouth"]
    # jaw open: lips apart, chin down; upper face still
    V = subj.pose(subj.params(jaw_open=0.3), textures=False).skin_vertices
    gap = np.linalg.norm(V[ms.upper] - V[ms.lower], axis=1)
    assert gap.max() > 0.02
    chin = np.argmin(np.abs(V0 - [0, -0.10, 0.085]).sum(1))
    assert V[chin, 1] < V0[chin, 1] - 0.01
    brow = V0[:, 1] > 0.03
    assert np.abs(V[brow] - V0[brow]).max() < 1e-9
    # smile: the mouth corners go up and out
    V = subj.pose(subj.params(smile_L=1, smile_R=1), textures=False).skin_vertices
    for c, s in zip(ms.corners, (-1, 1)):
        assert V[c, 1] > V0[c, 1] + 0.004 and s * (V[c, 0] - V0[c, 0]) > 0.003
    # brow raise: the left brow goes up, the right stays
    V = subj.pose(subj.params(brow_raise_L=1), textures=False).skin_vertices
    bl = np.argmin(np.abs(V0 - [0.03, 0.024, 0.085]).sum(1))
    br = np.argmin(np.abs(V0 - [-0.03, 0.024, 0.085]).sum(1))
    assert V[bl, 1] - V0[bl, 1] > 0.004 and abs(V[br, 1] - V0[br, 1]) < 1e-3
    # blink shuts the slit
    V = subj.pose(subj.params(blink_L=1), textures=False).skin_vertices
    es = subj.grid.slits["eye_left"]
    assert np.linalg.norm(V[es.upper] - V[es.lower], axis=1).max() < 1e-6
    # head yaw: the nose turns towards +X; the neck base stays
    V = subj.pose(subj.params(head_yaw=0.4), textures=False).skin_vertices
    tip = np.argmax(V0[:, 2])
    assert V[tip, 0] > 0.03
    base = V0[:, 1] < H.NECK_BASE_Y + 1e-6
    np.testing.assert_allclose(V[base], V0[base], atol=1e-12)


def test_rigid_parts_stay_rigid(subj):
    p = subj.params(jaw_open=0.25, jaw_sideways=0.05, gaze_yaw=0.3, gaze_pitch=-0.2, head_yaw=0.3,
                    head_pitch=0.2, head_roll=-0.1)
    pose = subj.pose(p, textures=False)
    for name in ("eye_left", "eye_right", "teeth_upper", "teeth_lower"):
        part = pose.parts[name]
        T = part.transform
        R = T[:3, :3]
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        assert abs(np.linalg.det(R) - 1) < 1e-12
        rest = subj.part_rest[name]
        np.testing.assert_allclose(part.vertices, rest @ R.T + T[:3, 3], atol=1e-12)
        i = np.random.default_rng(0).integers(0, len(rest), (200, 2))
        d0 = np.linalg.norm(rest[i[:, 0]] - rest[i[:, 1]], axis=1)
        d1 = np.linalg.norm(part.vertices[i[:, 0]] - part.vertices[i[:, 1]], axis=1)
        np.testing.assert_allclose(d0, d1, atol=1e-12)
    # upper teeth follow the head only; the lower ones the jaw as well
    np.testing.assert_allclose(pose.parts["teeth_upper"].transform, pose.transforms["head"])
    assert not np.allclose(pose.parts["teeth_lower"].transform, pose.transforms["head"])
    # the eyes turn about their own centres
    c = subj.eye_centres["eye_left"]
    Th = pose.transforms["head"]
    np.testing.assert_allclose(pose.parts["eye_left"].transform[:3, :3] @ c + pose.parts["eye_left"].transform[:3, 3],
                               Th[:3, :3] @ c + Th[:3, 3], atol=1e-12)


def test_presets(subj):
    tiny, draft, paper = subj.presets("tiny"), subj.presets("draft"), subj.presets("paper")
    assert [len(tiny), len(draft), len(paper)] == [6, 24, 60]
    assert [e.name for e in subj.presets(24)] == [e.name for e in draft]
    assert [e.name for e in paper[:24]] == [e.name for e in draft] and [e.name for e in draft[:6]] == [e.name for e in tiny]
    assert draft[0].name == "neutral" and draft[0].category == "neutral"
    assert len({e.name for e in paper}) == 60
    assert {e.category for e in paper} == set(CATEGORIES)
    names = [c.name for c in subj.controls]
    idx = {n: i for i, n in enumerate(names)}
    cats = {e.category for e in tiny}
    assert {"emotion", "viseme", "head_pose", "coverage"} <= cats
    assert any(e.category == "viseme" and e.params[idx["jaw_open"]] > 0.15 for e in tiny)
    assert any(e.params[idx["blink_L"]] == 1 and e.params[idx["blink_R"]] == 1 for e in tiny)
    for e in paper:
        assert e.params.shape == (len(names),)
        for c, v in zip(subj.controls, e.params):
            assert c.lo - 1e-12 <= v <= c.hi + 1e-12, (e.name, c.name, v)
    with pytest.raises(ValueError):
        subj.presets(7)


def test_pose_is_fast(subj):
    import time

    p = subj.params(smile_L=1, brow_raise_R=0.5, jaw_open=0.2, head_yaw=0.2)
    subj.pose(p)
    t = time.perf_counter()
    subj.pose(p)
    assert time.perf_counter() - t < 0.6
