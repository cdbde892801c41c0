"""Issue 15 defect 8: renders that cannot be right say so. A camera behind or beside the head (far from
every capture camera), a collapsed target (drawn as nothing), parts seen with no skin around them:
each a message in RenderStats.warnings and a RenderWarning (the CLI prints it as one line)."""
from pathlib import Path

import numpy as np
import pytest


@pytest.fixture(scope="module")
def model_dir(toy_truth, tmp_path_factory, mi):
    from mifacerf.rendering.build import build_model

    out = tmp_path_factory.mktemp("warn_model") / "model"
    build_model(toy_truth, out, progress=False)
    return out


@pytest.fixture(scope="module")
def face(model_dir):
    from mifacerf.rendering.api import load_model

    return load_model(model_dir)


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


SCENE = Path(__file__).resolve().parents[2] / "scenes" / "face_envmap.xml"


def render_cli(model_dir, out, *defines, scene=SCENE):
    from click.testing import CliRunner

    from mifacerf.cli import main

    args = ["render", str(scene), "-D", f"model={model_dir}", "-D", "width=16", "-D", "height=16",
            "-D", "envmap=gradient", "--spp", "1", "-o", str(out)]
    for d in defines:
        args += ["-D", d]
    return CliRunner().invoke(main, args)


def _warnings(result):
    assert "Traceback" not in result.output
    return [ln for ln in result.stderr.splitlines() if ln.startswith("mifacerf render: warning: ")]


def test_the_cli_renders_a_scene_from_the_front_without_warnings(model_dir, tmp_path):
    r = render_cli(model_dir, tmp_path / "front.exr")
    assert r.exit_code == 0, r.output
    assert _warnings(r) == [] and (tmp_path / "front.exr").exists()


def test_the_cli_prints_the_warning_of_a_scene_seen_from_behind(model_dir, tmp_path):
    """Item 6: 'mifacerf render' of a scene whose camera is behind the head says so (the scene path —
    the facerf integrator — was silent: only Renderer.render checked the view)."""
    scene = tmp_path / "behind.xml"
    text = SCENE.read_text()
    assert 'origin="0.3, 0.12, 1.25"' in text
    scene.write_text(text.replace('origin="0.3, 0.12, 1.25"', 'origin="-0.3, 0.12, -1.25"')
                     .replace('value="envmaps/', f'value="{SCENE.parent}/envmaps/'))
    r = render_cli(model_dir, tmp_path / "behind.exr", scene=scene)
    assert r.exit_code == 0, r.output
    w = _warnings(r)
    assert len(w) == 1 and "deg from the nearest capture camera" in w[0], r.stderr
    assert (tmp_path / "behind.exr").exists()


def test_the_cli_prints_the_warning_of_a_collapsed_target(model_dir, face, tmp_path):
    target, _ = face.target("neutral")
    np.save(tmp_path / "collapsed.npy", np.zeros_like(target))
    r = render_cli(model_dir, tmp_path / "collapsed.exr", f"target={tmp_path / 'collapsed.npy'}")
    assert r.exit_code == 0, r.output
    w = _warnings(r)
    assert len(w) == 1 and "degenerate target mesh" in w[0], r.stderr


def test_a_render_that_fails_writing_keeps_the_previous_exr_and_png(model_dir, tmp_path, monkeypatch):
    """Item 1 (render -o): the EXR and the PNG replace the old pair only once both are complete (a full disk
    while writing the PNG, after the EXR, left a new EXR beside the old PNG)."""
    import os

    from .faults import ENOSPC

    out = tmp_path / "r.exr"
    out.write_bytes(b"the previous render")
    out.with_suffix(".png").write_bytes(b"its picture")
    old = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    monkeypatch.setattr(os, "fsync", ENOSPC(2))          # the PNG's write (the EXR's was the first)
    r = render_cli(model_dir, out, "expression=stretch")
    assert r.exit_code == 1 and "No space left on device" in r.stderr and "Traceback" not in r.output
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == old      # no temporary file left either
