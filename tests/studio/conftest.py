"""Fixtures of the studio tests: one tiny synthetic capture (two expressions) per session, its truth moved
out of reach (the studio must never read it), and a fresh copy of the capture folder per test that edits."""
import shutil

import pytest
from helpers.capture import tiny_capture_without_truth

EXPRESSIONS = ["neutral", "smile"]


@pytest.fixture(scope="session")
def studio_capture(tmp_path_factory):
    """(pristine capture folder, hidden truth folder)."""
    return tiny_capture_without_truth(tmp_path_factory.mktemp("studio"), EXPRESSIONS)


@pytest.fixture
def capture(studio_capture, tmp_path):
    """A copy of the tiny capture this test may edit (images, hand inputs, proxies cache)."""
    src, _ = studio_capture
    dst = tmp_path / "capture"
    shutil.copytree(src, dst, symlinks=True)
    return dst


@pytest.fixture
def client_for():
    """``client_for(capture) -> (TestClient, token)`` for the studio app on ``capture``."""
    from starlette.testclient import TestClient

    from mifacerf.studio.server import create_app

    def make(cap, token="test-token"):
        return TestClient(create_app(cap, token, {"testserver"})), token
    return make
