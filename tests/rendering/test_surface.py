"""The surface a model's renders trace is the model's own (``Model.surface``, carried from its registration:
the surface the extension outlines were fitted against); ``Renderer(curved=...)`` overrides it."""
import copy

import pytest


def test_renderer_traces_the_models_surface_unless_told(toy_model):
    from mifacerf.geometry.meshscene import CurvedMeshScene
    from mifacerf.rendering.renderer import Renderer

    assert toy_model.surface == {"method": "flat", "curved": 1}      # its registration records none: flat
    assert Renderer(toy_model).curved == 1
    phong = copy.copy(toy_model)
    phong.meta = dict(toy_model.meta, surface={"method": "phong", "curved": 2})
    r = Renderer(phong)
    assert r.curved == 2 and isinstance(r._scene, CurvedMeshScene) and r._scene.tessellation.level == 2
    assert Renderer(phong, curved=1).curved == 1
    for bad in (0, 1.5, True):
        with pytest.raises(ValueError, match="curved must be a whole number"):
            Renderer(toy_model, curved=bad)
