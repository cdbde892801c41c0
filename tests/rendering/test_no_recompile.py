"""Animations compile nothing after their first frame (issue 19): checked through Dr.Jit's kernel history.

Dr.Jit keeps compiled kernels in memory and on disk (``~/.drjit``), so a kernel that bakes a per-frame value
into its code (a Python float literal, a sample count used as an offset) is a cache miss only the first
time that value occurs: every frame here uses fresh random weights, poses and sample counts so that a
baked value cannot hide behind an earlier run's disk cache.
"""
import time

import numpy as np
import pytest

from mifacerf import environment as E

from helpers.toy import make_toy


@pytest.fixture(scope="module")
def toy_model(tmp_path_factory, mi):
    import mifacerf
    from mifacerf.rendering.build import build_model

    mifacerf.register_plugins()
    root = tmp_path_factory.mktemp("toy_norecompile")
    cap = make_toy(root, names=("neutral", "stretch"), size=32, n_pos=6, n_str=5, truth_registration=True).capture
    build_model(cap, root / "model")
    return root / "model"


def compiled(history) -> int:
    """Kernels of a kernel history that were compiled (not found in the in-memory or disk cache)."""
    import drjit as dr

    return sum(1 for e in history if e["type"] == dr.KernelType.JIT and not e["cache_hit"])


@pytest.fixture
def kernel_history():
    import drjit as dr

    before = dr.flag(dr.JitFlag.KernelHistory)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    dr.kernel_history()
    yield lambda: dr.kernel_history()
    dr.set_flag(dr.JitFlag.KernelHistory, before)


def fresh(n: int) -> np.ndarray:
    """``n`` values in (0.2, 0.8) never seen before (seeded by the clock: a new sequence every run)."""
    return np.random.default_rng(time.time_ns()).uniform(0.2, 0.8, n)


def test_renderer_sequence_compiles_nothing_after_the_first_frame(toy_model, kernel_history):
    """Blend weights, the target mesh and a small head turn change per frame (the ``mifacerf drive`` loop
    calls the same ``Renderer.render``; its ``render_frame`` is exercised too)."""
    import mifacerf as mf
    from mifacerf.tracking.drive import FrameContext, render_frame

    face = mf.load_model(toy_model)
    env = E.generated("sky", 32)
    ctx = FrameContext(face, env, face.camera((5, 0), size=40), spp=2)
    counts = []
    for k, w in enumerate(fresh(5)):
        target, W = face.target({"neutral": w, "stretch": 1 - w})
        target = target + np.random.default_rng(k).normal(0, 1e-4, target.shape)  # a new mesh each frame
        cam = face.camera((5 + 3 * w, 2 * w - 1), size=40)
        face.renderer.render(target, W, cam, env, spp=2, seed=k)
        render_frame(ctx, (k, target, W, None))
        counts.append(compiled(kernel_history()))
    assert counts[1:] == [0] * 4, counts


def test_traverse_loop_compiles_nothing_after_the_first_frame(toy_model, mi, kernel_history):
    """The README's ``mi.traverse`` animation: face.expression and face.to_world change per frame."""
    from pathlib import Path

    from mifacerf.rendering.scenefile import load_scene_file

    xml = Path(__file__).resolve().parents[2] / "scenes" / "face_envmap.xml"
    scene, _ = load_scene_file(xml, {"model": str(toy_model), "expression": "stretch", "envmap": "gradient",
                                     "width": "32", "height": "32", "spp": "2"})
    params = mi.traverse(scene)
    face = [s for s in scene.shapes() if s.id() == "face"][0]
    counts = []
    for k, w in enumerate(fresh(4)):
        params["face.expression"] = face.weights({"stretch": w, "neutral": 1 - w})
        params["face.to_world"] = face.transform(mi.ScalarTransform4f().rotate([0, 1, 0], 8 * w))
        params.update()
        img = mi.render(scene, seed=k)
        assert np.isfinite(np.asarray(img)).all()
        counts.append(compiled(kernel_history()))
    assert counts[1:] == [0] * 3, counts


def test_a_sequence_loads_each_field_once(toy_model):
    """A sequence driven by meshes (the §5 weights, as ``mifacerf drive`` renders a track) loads each field it
    needs onto the device once for the whole sequence: the frames after the first upload nothing they had
    before, and a field's device form is made once however many frames read it (issue 19 item 3)."""
    import dataclasses

    import mifacerf as mf
    from mifacerf.tracking.drive import FrameContext, render_frame

    face = mf.load_model(toy_model)
    r = face.renderer
    loads = []
    load = r.compression.load

    def counting(model, s, c, rank, lights):
        loads.append((s, c))
        return load(model, s, c, rank, lights)

    r.compression = dataclasses.replace(r.compression, load=counting)
    env = E.generated("sky", 32)
    ctx = FrameContext(face, env, face.camera((5, 0), size=40), spp=2)
    m = face.model
    for k, w in enumerate(fresh(4)):
        mesh = w * m.vertices[0] + (1 - w) * m.vertices[1]
        target, W = face.target(mesh=mesh)
        render_frame(ctx, (k, target, W, None))
    assert loads, "no field was loaded"
    assert len(loads) == len(set(loads)), loads
