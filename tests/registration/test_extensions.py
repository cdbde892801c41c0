"""Template extensions placed from what is registered (toy geometry, analytic expectations)."""
import numpy as np
import pytest

from mifacerf.geometry.rigid import apply, homogeneous
from mifacerf.registration.extensions import Extension, falloff_weight, place_extensions


def _toy():
    """A strip: face vertices 0-5 on x in [0, 0.05] (fiducials 0..5), extension vertices 6-9 beyond
    x = 0.05 .. 0.2 along the same strip, stitched to the face at vertex 5 (two rows, y = 0 / 0.01)."""
    xs = np.array([0.0, 0.025, 0.05, 0.1, 0.15, 0.2])
    top = np.stack([xs, np.zeros(6), np.zeros(6)], 1)
    bot = top + [0, 0.01, 0.002]
    X = np.concatenate([top, bot])                 # 0-5 top, 6-11 bottom
    faces = [[i, i + 1, i + 6] for i in range(5)] + [[i + 1, i + 7, i + 6] for i in range(5)]
    fid = np.array([0, 1, 2, 6, 7, 8])             # the face part: x <= 0.05
    ext = np.array([3, 4, 5, 9, 10, 11])
    return X, np.array(faces), fid, ext


def _rot(deg):
    a = np.radians(deg)
    return homogeneous(np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]]),
                       np.array([0.01, -0.02, 0.005]))


def test_rigid_extension_follows_the_head_pose_exactly():
    X, F, fid, ext = _toy()
    T = _rot(12)
    out, rep = place_extensions(X, F, fid, apply(T, X[fid]), [Extension("scalp", ext, "rigid")])
    assert np.allclose(out[ext], apply(T, X[ext]), atol=1e-9)
    assert np.array_equal(out[fid], X[fid])        # the face is not touched
    assert rep["extensions"]["scalp"] == {"mode": "rigid", "anchor": "head", "vertices": 6} and rep["fallbacks"] == []


def test_driven_extension_follows_the_fiducials_near_and_the_head_far():
    X, F, fid, ext = _toy()
    R = X[fid].copy()
    R[:, 2] += 0.004 * (X[fid, 0] / 0.05)           # the face's border lifts 4 mm; no rigid motion at the far end
    out, rep = place_extensions(X, F, fid, R, [Extension("neck", ext, "driven", falloff=0.12)],
                                head=np.eye(4))
    lift = out[ext, 2] - X[ext, 2]
    near, far = ext[X[ext, 0] == 0.1], ext[X[ext, 0] == 0.2]
    assert lift[np.isin(ext, near)].min() > 0.001   # next to the fiducials it follows their lift
    assert np.allclose(out[far], X[far], atol=1e-12)  # beyond the falloff: rigid with the head (identity)
    assert rep["extensions"]["neck"]["mode"] == "driven"


def test_falloff_weight_is_smooth_one_at_the_fiducial_zero_beyond():
    w = falloff_weight(np.array([0.0, 0.015, 0.03, 0.05]), 0.03)
    assert w[0] == 1.0 and w[1] == pytest.approx(0.5) and w[2] == 0.0 and w[3] == 0.0


def test_detached_extension_is_an_error_naming_the_gap():
    X, F, fid, ext = _toy()
    X2 = np.concatenate([X, X[ext] + [0.0, 0.0, 0.03]])      # a floating copy of the extension
    n = len(X)
    F2 = np.concatenate([F[:4], [[n, n + 1, n + 3]]])        # only the face triangles + one floating triangle
    with pytest.raises(ValueError, match=r"'cap' is not attached to the face.*gap \d+\.\d mm"):
        place_extensions(X2, F2, fid, X2[fid], [Extension("cap", np.array([n, n + 1, n + 3]))])


def test_driven_region_with_no_fiducial_near_falls_back_to_rigid_and_says_so():
    X, F, fid, ext = _toy()
    far = ext[X[ext, 0] >= 0.15]
    T = _rot(5)
    out, rep = place_extensions(X, F, fid, apply(T, X[fid]), [Extension("temple", far, "driven", falloff=0.02)])
    assert rep["extensions"]["temple"]["mode"] == "rigid"
    assert "no registered fiducial within 20 mm" in rep["fallbacks"][0] and "rigid with the head" in rep["fallbacks"][0]
    assert np.allclose(out[far], apply(T, X[far]))


def test_bad_declarations_refused():
    X, F, fid, ext = _toy()
    with pytest.raises(ValueError, match="unknown mode 'wobbly'; choose one of rigid, driven"):
        Extension("x", ext, "wobbly")
    with pytest.raises(ValueError, match="holds fiducials"):
        place_extensions(X, F, fid, X[fid], [Extension("x", np.array([0, 3]))])
