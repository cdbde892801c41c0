"""Shared test fixtures. Tests use tiny rigs and images so the suite stays fast on 2 cores."""
import os

import numpy as np
import pytest

# Generated data (environments, the synthetic subject's atlas) is cached per test session.
os.environ.setdefault("MIFACERF_CACHE", os.path.join(os.path.dirname(__file__), "..", ".cache-tests"))
# Commands run in the test process (no local cluster per CLI test); tests/test_execution.py and the
# *_distributed tests start their own 2-worker clusters.
os.environ.setdefault("MIFACERF_WORKERS", "1")


# Fixtures that take more than ~20 s to build on the 2-core CI machine. Every test that needs one (directly
# or through another fixture) must be marked slow, so that `pytest -m "not slow"` stays quick.
SLOW_FIXTURES = {"tiny", "built_root", "toy_capture", "world"}


def pytest_collection_modifyitems(config, items):
    unmarked = [item.nodeid for item in items if SLOW_FIXTURES & set(getattr(item, "fixturenames", ()))
                and item.get_closest_marker("slow") is None]
    if unmarked:
        raise pytest.UsageError("these tests need a slow fixture (%s) but are not marked @pytest.mark.slow: %s"
                                % (", ".join(sorted(SLOW_FIXTURES)), ", ".join(unmarked)))


@pytest.fixture(scope="session")
def mi():
    from mifacerf.variant import ensure_variant

    return ensure_variant()


@pytest.fixture
def rng():
    return np.random.default_rng(1234)
