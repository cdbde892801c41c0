"""Fixtures of the registration tests: a toy capture (independent of the synthetic head), registered once."""
import numpy as np
import pytest

from . import toy


@pytest.fixture(scope="session")
def toy_capture(tmp_path_factory):
    """(capture path, {expression: (T, 3) true template positions}) of a 3-expression toy capture."""
    root = tmp_path_factory.mktemp("toy")
    cap, truth = toy.make_toy(root, names=("neutral", "stretch", "bulge"), size=96)
    return cap, truth


@pytest.fixture(scope="session")
def toy_registered(toy_capture):
    from mifacerf.registration import register_capture

    cap, truth = toy_capture
    out = register_capture(cap, progress=False)
    return cap, truth, out


def errors_px(reg_expr, truth, cams, ids):
    """3-D errors of vertices ``ids`` in pixel footprints (mean over cameras)."""
    fp = np.mean([np.abs(cam.world_to_camera(truth[ids])[:, 2]) / np.sqrt(cam.K[0, 0] * cam.K[1, 1])
                  for cam in cams], axis=0)
    return np.linalg.norm(reg_expr.vertices[ids] - truth[ids], axis=1) / fp
