"""Shared test fixtures. Tests use tiny rigs and images so the suite stays fast on 2 cores."""
import os

import numpy as np
import pytest

# Generated data (environments, the synthetic subject's atlas) is cached per test session.
os.environ.setdefault("MIFACERF_CACHE", os.path.join(os.path.dirname(__file__), "..", ".cache-tests"))


@pytest.fixture(scope="session")
def mi():
    from mifacerf.variant import ensure_variant

    return ensure_variant()


@pytest.fixture
def rng():
    return np.random.default_rng(1234)
