"""The refit pass: fiducials whose prediction is off by more than the search radius are found again
from the registered ones' displacement, carried over the template mesh (Registrar.refit_pass).

On a toy capture (its truth known) at 160 px, where the dots are 8 px apart and the extra passes run:
a patch of the bulge's predictions is pushed 8 mm off (twice the 4 mm search radius, below the
dots' 11.5 mm spacing), so that the first round cannot find them; the refit's starts come
from the registered neutral and the displacement of the registered fiducials round the patch, not
from the bad prediction.
"""
import numpy as np
import pytest

from mifacerf.formats.capture import Capture

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def toy160(tmp_path_factory):
    from helpers.toy import make_toy

    toy = make_toy(tmp_path_factory.mktemp("toy160"), names=("neutral", "bulge"), size=160)
    return toy.capture, toy.truth


def test_refit_finds_fiducials_a_bad_prediction_hid(toy160, tmp_path):
    from mifacerf.registration.register import Options, Registrar

    cap, truth = toy160
    r = Registrar(Capture(cap), tmp_path / "reg", options=Options(refit=False), fresh=True)
    r.register("neutral")
    e = r.load("bulge", need_fields=False)
    r.ensure_filter(e)
    views = r.views(e)
    known, _ = r.coarse_points("bulge", e.flags)
    N = r.registered["neutral"].vertices
    dots = r.dots
    T = truth["bulge"]
    # the prediction: the neutral, with a patch of fiducials (not coarse points) pushed 8 mm sideways
    centre = N[dots][np.argmin(np.linalg.norm(N[dots] - N[dots].mean(0), axis=1))]
    patch = dots[(np.linalg.norm(N[dots] - centre, axis=1) < 0.015)]
    patch = np.setdiff1d(patch, np.array(sorted(known), np.int64))
    assert len(patch) >= 4
    pred = N.copy()
    pred[patch] += [0.008, 0.0, 0.0]
    X, snapped, _ = r._snap_round(e, views, pred, known, r.opt.radius_px, {})
    lost = patch[~snapped[patch]]
    assert len(lost) >= 3, "the first round found the pushed fiducials: the test proves nothing"
    X0, s0 = X.copy(), snapped.copy()
    new = r.refit_pass(e, views, pred, N, known, r.opt.radius_px, X, snapped)
    assert set(new.tolist()) <= set(np.flatnonzero(~s0).tolist())
    found = np.intersect1d(new, lost)
    assert len(found) >= 0.6 * len(lost), (len(found), len(lost))
    fp = r.fp
    err = np.linalg.norm(X[found] - T[found], axis=1) / fp
    assert np.median(err) < 0.5 and err.max() < 1.5, err           # on their own dots, not a neighbour's
    np.testing.assert_array_equal(X[s0], X0[s0])                     # the registered ones stay as they were
    rep = e.report["refit"]
    assert rep["tried"] >= len(lost) and sorted(rep["registered"]) == sorted(new.tolist())
    # the same state refitted from the bad prediction itself (base = pred) does not find them: the
    # starts must come from the neutral plus the carried displacement
    X1, s1 = X0.copy(), s0.copy()
    again = r.refit_pass(e, views, pred, pred, known, r.opt.radius_px, X1, s1)
    assert len(np.intersect1d(again, lost)) < len(found)
