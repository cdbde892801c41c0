"""Tracked frames place the template's extensions as the registration does (issue 16): rigid with the
frame's head pose (scalp, ears), driven by the nearest tracked dots (neck)."""
from types import SimpleNamespace

import numpy as np

from mifacerf.geometry.schaefer2006 import mls_affine
from mifacerf.tracking.track import place_extensions_per_frame


def _grid_template(extensions):
    n = 6
    xx, yy = np.meshgrid(np.arange(n) * 0.02, np.arange(n) * 0.02)
    V = np.stack([xx.ravel(), yy.ravel(), 0.01 * np.sin(7 * xx.ravel())], 1)
    F = []
    for i in range(n - 1):
        for j in range(n - 1):
            a = i * n + j
            F += [[a, a + 1, a + n], [a + 1, a + n + 1, a + n]]
    dots = np.arange(3 * n)                    # the lower three rows carry fiducials, the rest is extension
    raw = {"vertices": [{}] * len(V), "extensions": extensions}
    tpl = SimpleNamespace(raw=raw, n_vertices=len(V), triangles=np.array(F), dot_ids=dots)
    return tpl, V


def _turn(deg):
    a = np.radians(deg)
    T = np.eye(4)
    T[:3, :3] = [[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]]
    T[:3, 3] = (0.01, -0.02, 0.005)
    return T


def test_rigid_extensions_follow_the_head_pose_exactly():
    tpl, V_ref = _grid_template({"scalp": {"vertices": list(range(18, 36)), "mode": "rigid"}})
    H = np.stack([np.eye(4), _turn(25)])
    rng = np.random.default_rng(0)
    V = np.stack([V_ref @ h[:3, :3].T + h[:3, 3] for h in H])
    V[:, :18] += rng.normal(0, 0.002, (2, 18, 3))          # the dots move off the rigid motion (expression)
    dots = V[:, :18].copy()
    status = np.zeros((2, 36), np.int8)
    status[:, :18] = 1
    mls = mls_affine(V_ref[:18], dots[1], V_ref[18:], k=16)   # what tracking did before: the dots' map
    rep = place_extensions_per_frame(tpl, V_ref, V, status, H)
    assert rep["frames"] == 2 and rep["fallbacks"] == []
    want = V_ref[18:] @ H[1, :3, :3].T + H[1, :3, 3]
    np.testing.assert_allclose(V[1, 18:], want, atol=1e-12)
    assert np.abs(mls - want).max() > 1e-3                  # the dots' map is mm off the head's motion
    assert (status[:, 18:] == 1).all() and (V[:, :18] == dots).all()


def test_driven_extension_follows_the_dots_near_them_and_frames_without_a_pose_keep_theirs():
    tpl, V_ref = _grid_template({"neck": {"vertices": list(range(18, 36)), "mode": "driven", "falloff": 0.05}})
    H = np.stack([_turn(10), np.full((4, 4), np.nan)])
    V = np.stack([V_ref @ H[0, :3, :3].T + H[0, :3, 3], V_ref.copy()])
    V[0, :18] += (0.0, 0.0, 0.003)                          # the dots pushed forward: the skin near them follows
    status = np.ones((2, 36), np.int8)
    before = V[1].copy()
    rep = place_extensions_per_frame(tpl, V_ref, V, status, H)
    assert rep["frames"] == 1
    rigid = V_ref[18:] @ H[0, :3, :3].T + H[0, :3, 3]
    lift = V[0, 18:, 2] - rigid[:, 2]
    assert lift[:6].mean() > 0.0015 and abs(lift[-6:].mean()) < lift[:6].mean()   # full near the dots, less far
    assert (V[1] == before).all()
