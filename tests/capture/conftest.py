"""Fixtures of the capture tests (their helpers are in tests/helpers/capture.py)."""
import pytest

from helpers.capture import new_session, tiny_rig


@pytest.fixture
def rig():
    return tiny_rig()


@pytest.fixture
def session_factory(tmp_path, rig):
    def make(n_expressions=2, root=None, **config):
        return new_session(root or tmp_path / "cap", rig, n_expressions, **config)
    return make


