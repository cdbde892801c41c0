"""Fixtures shared by the rendering tests."""
import pytest

from helpers.toy import make_toy


@pytest.fixture(scope="session")
def toy_model(tmp_path_factory, mi):
    """A small built toy model (neutral and stretch, 32² cameras, a 6 × 5 light arm), opened."""
    from mifacerf.rendering.build import build_model
    from mifacerf.rendering.model import Model

    root = tmp_path_factory.mktemp("toy_model")
    cap = make_toy(root, names=("neutral", "stretch"), size=32, n_pos=6, n_str=5, truth_registration=True).capture
    build_model(cap, root / "model")
    return Model(root / "model")
