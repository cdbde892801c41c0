"""Fixtures of the reliability tests: small toy captures (tests/helpers/toy.py), a truth registration for
the model tests and a real registration for the registration tests, built once per session."""
import shutil

import pytest

from helpers.toy import make_toy


@pytest.fixture(scope="session")
def toy_truth(tmp_path_factory):
    """A 3-expression 48 px toy capture with CAPTURE/registration written from the truth (~7 s)."""
    root = tmp_path_factory.mktemp("rel_truth")
    return make_toy(root, names=("neutral", "stretch", "bulge"), size=48, n_pos=6, n_str=4,
                    truth_registration=True).capture


@pytest.fixture(scope="session")
def toy_plain(tmp_path_factory):
    """A 3-expression 64 px toy capture (hand inputs, no registration yet)."""
    root = tmp_path_factory.mktemp("rel_plain")
    return make_toy(root, names=("neutral", "stretch", "bulge"), size=64, n_pos=6, n_str=4).capture


@pytest.fixture(scope="session")
def toy_reg(toy_plain, tmp_path_factory):
    """``toy_plain`` registered (every expression; ~12 s)."""
    from mifacerf.registration import register_capture

    dst = tmp_path_factory.mktemp("rel_reg") / "capture"
    shutil.copytree(toy_plain, dst)
    register_capture(dst, progress=False)
    return dst


@pytest.fixture
def capture_copy(tmp_path):
    """``capture_copy(src)``: a private copy of a capture folder (with its registration and cache)."""
    def copy(src):
        dst = tmp_path / "capture"
        shutil.copytree(src, dst)
        return dst
    return copy
