"""Fixtures of the registration tests: a toy capture (independent of the synthetic head), registered once."""
import pytest

from helpers.toy import make_toy


@pytest.fixture(scope="session")
def toy_capture(tmp_path_factory):
    """(capture path, {expression: (T, 3) true template positions}) of a 3-expression toy capture."""
    root = tmp_path_factory.mktemp("toy")
    toy = make_toy(root, names=("neutral", "stretch", "bulge"), size=96)
    return toy.capture, toy.truth


@pytest.fixture(scope="session")
def toy_registered(toy_capture):
    from mifacerf.registration import register_capture

    cap, truth = toy_capture
    out = register_capture(cap, progress=False)
    return cap, truth, out
