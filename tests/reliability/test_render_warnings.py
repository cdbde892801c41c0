"""Issue 15 defect 8: renders that cannot be right say so. A camera behind or beside the head (far from
every capture camera), a collapsed target (drawn as nothing), parts seen with no skin around them:
each a message in RenderStats.warnings and a RenderWarning (the CLI prints it as one line)."""
import numpy as np
import pytest


@pytest.fixture(scope="module")
def face(toy_truth, tmp_path_factory, mi):
    from mifacerf.rendering.api import load_model
    from mifacerf.rendering.build import build_model

    out = tmp_path_factory.mktemp("warn_model") / "model"
    build_model(toy_truth, out, progress=False)
    return load_model(out)


def _render(face, **kw):
    from mifacerf.rendering.renderer import RenderStats, RenderWarning

    st = RenderStats()
    with pytest.warns(RenderWarning) if kw.pop("expect", False) else _no_render_warning():
        img = face.render(stats=st, spp=1, size=24, **kw)
    return img, st


class _no_render_warning:
    def __enter__(self):
        import warnings
        self._w = warnings.catch_warnings(record=True)
        self.got = self._w.__enter__()
        warnings.simplefilter("always")

    def __exit__(self, *exc):
        from mifacerf.rendering.renderer import RenderWarning
        self._w.__exit__(*exc)
        assert not [w for w in self.got if issubclass(w.category, RenderWarning)], [str(w.message) for w in self.got]


def test_a_capture_camera_renders_without_warnings(face):
    img, st = _render(face, expression="neutral")
    assert st.warnings == [] and img[..., 3].max() > 0


@pytest.mark.parametrize("yaw", [180.0, 100.0])
def test_a_view_behind_or_beside_the_head_is_warned(face, yaw):
    img, st = _render(face, expression="neutral", camera=(yaw, 0.0), expect=True)
    assert len(st.warnings) >= 1 and "from the nearest capture camera" in st.warnings[0]


def test_a_collapsed_target_draws_nothing_and_says_so(face):
    target, _ = face.target("neutral")
    img, st = _render(face, mesh=np.zeros_like(target), expect=True)
    assert "degenerate target mesh" in st.warnings[0]
    assert img.shape == (24, 24, 4) and not img.any()
