"""Shared fixtures of the blending tests: small toy subjects and fitted models (module-scoped)."""
import pytest

from mifacerf.blending import BlendModel
from mifacerf.blending.toy import random_sources, toy_subject


@pytest.fixture(scope="session")
def toy():
    sub = toy_subject(nx=10, ny=8, n_shapes=5, seed=2)
    S, params = random_sources(sub, 18, seed=4)
    return sub, S, params


@pytest.fixture(scope="session")
def model(toy):
    sub, S, _ = toy
    return BlendModel.fit(S, 0, sub.triangles, residual_threshold=1e-5)


@pytest.fixture(scope="session")
def culled_model(toy):
    sub, S, _ = toy
    return BlendModel.fit(S, 0, sub.triangles, regions=sub.regions, residual_threshold=1e-5,
                          similarity_threshold=4e-4)

