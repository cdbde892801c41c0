"""The model folder as a transaction: a failed, killed or disk-full build leaves the previous model; the
manifest catches bit rot and deleted keys; build refuses a registration that does not cover the capture."""
import errno
import json
import os
import random
import shutil

import numpy as np
import pytest
from click.testing import CliRunner

from mifacerf.formats.model import MARKER, ModelError, ModelFolder
from mifacerf.formats.registration import RegistrationError

from .faults import ENOSPC, killed, run_child, siblings, snapshot, start_child


def build(capture, out, **kw):
    from mifacerf.rendering.build import build_model

    return build_model(capture, out, progress=False, **kw)


@pytest.fixture
def built(toy_truth, capture_copy, tmp_path):
    """(capture copy, model folder built from neutral + stretch, snapshot of the model's files)."""
    cap = capture_copy(toy_truth)
    model = tmp_path / "model"
    build(cap, model, expressions=["neutral", "stretch"])
    return cap, model, snapshot(model)


def assert_old_or_new(model, old: dict, new_expressions=None):
    """The folder is byte-identical to ``old``, or a complete model that verifies (the new one); nothing of
    a transaction is left beside it."""
    m = ModelFolder(model)                   # (repairs an interrupted swap first)
    now = snapshot(model)
    if now != old:
        assert m.verify() == [], m.verify()
        assert set(now) >= {"model.json", "geometry.npz", "blend.npz"}
        if new_expressions is not None:
            assert m.expressions == new_expressions
    assert siblings(model) == [], siblings(model)
    return now == old


def test_failed_overwrite_keeps_the_previous_model(built, monkeypatch):
    """Defect 3: a failed 'build --overwrite' deleted model.json before the new model existed."""
    from mifacerf.formats import model as fm

    cap, model, old = built
    calls = [0]
    real = fm.ModelWriter.write_field

    def failing(self, *a, **kw):
        calls[0] += 1
        if calls[0] == 4:
            raise RuntimeError("injected failure in the middle of the build")
        return real(self, *a, **kw)

    monkeypatch.setattr(fm.ModelWriter, "write_field", failing)
    with pytest.raises(RuntimeError, match="injected"):
        build(cap, model, overwrite=True)
    assert snapshot(model) == old and siblings(model) == []
    monkeypatch.setattr(fm.ModelWriter, "write_field", real)
    build(cap, model, overwrite=True)                      # and the lock was released
    assert ModelFolder(model).expressions == ["neutral", "stretch", "bulge"]


@pytest.mark.parametrize("nth", [1, 7, 15])
def test_a_full_disk_during_build_keeps_the_previous_model(built, monkeypatch, nth):
    cap, model, old = built
    monkeypatch.setattr(os, "fsync", ENOSPC(nth))
    with pytest.raises(OSError) as exc:
        build(cap, model, overwrite=True)
    assert exc.value.errno == errno.ENOSPC
    assert snapshot(model) == old and siblings(model) == []


def test_sigkill_at_every_rename_of_the_swap(built):
    """A build killed between any two renames of its swap: the next open finds the old or the new model."""
    cap, model, old = built
    args = {"capture": str(cap), "out": str(model), "overwrite": True}
    outcomes = []
    for n in (1, 2, 3):              # killed before: building -> ready, model -> old, ready -> model
        p = run_child("build", args, f"call:rename:{n}:{model.name}")
        assert killed(p), p.stderr[-2000:]
        outcomes.append(assert_old_or_new(model, old, ["neutral", "stretch", "bulge"]))
        if not outcomes[-1]:         # the new one won: build the old one again for the next point
            shutil.rmtree(model)
            build(cap, model, expressions=["neutral", "stretch"])
            old = snapshot(model)
    assert outcomes == [True, False, False]   # once 'ready' exists, the swap is finished, not undone


def test_sigkill_at_random_moments(built):
    cap, model, old = built
    rnd = random.Random(15)
    args = {"capture": str(cap), "out": str(model), "overwrite": True}
    for _ in range(3):
        delay = rnd.uniform(0.0, 1.5)
        p = start_child("build", args, f"time:{delay:.3f}")
        p.wait(timeout=300)
        p.stdout.read(), p.stderr.read()
        if assert_old_or_new(model, old, ["neutral", "stretch", "bulge"]) is False:
            old = snapshot(model)     # a complete new model is the state to keep from now on


def test_a_flipped_byte_in_a_field_is_found_and_named(built):
    """Defect 4: 20 kB overwritten inside an .rf.npy rendered with exit 0."""
    from mifacerf.formats.cli import verify_cmd

    cap, model, _ = built
    rf = sorted(model.glob("fields/stretch/*.rf.npy"))[0]
    data = bytearray(rf.read_bytes())
    data[len(data) // 2] ^= 0x40
    rf.write_bytes(bytes(data))
    m = ModelFolder(model)                                   # sizes agree: opening stays cheap
    s, c = m.expression_index("stretch"), m.camera_index(rf.name.split(".")[0])
    with pytest.raises(ModelError, match=rf"{rf.name}: checksum mismatch"):
        m.field(s, c)
    res = CliRunner().invoke(verify_cmd, [str(model)])
    assert res.exit_code == 1 and rf.name in res.output and "checksum mismatch" in res.output
    rf.write_bytes(bytes(data[:-100]))                       # truncated: found at open
    with pytest.raises(ModelError, match=rf"{rf.name}: \d+ bytes, the manifest says"):
        ModelFolder(model)


def test_verify_passes_on_a_sound_model_and_after_compress(built):
    from mifacerf.formats.cli import verify_cmd
    from mifacerf.rendering.compression import compress_model
    from mifacerf.rendering.model import Model

    cap, model, _ = built
    compress_model(Model(model), 4, progress=False, method="pca")
    res = CliRunner().invoke(verify_cmd, [str(model)])
    assert res.exit_code == 0, res.output
    m = Model(model)
    m.compressed_field(0, 0, 4, "pca")
    assert "fields/neutral/cam0.pca4.npz" in m.files


KEYS = ["lights", "cameras", "expressions", "neutral", "template", "fields", "files", "references", "part_sources"]


@pytest.mark.parametrize("key", KEYS)
def test_a_missing_manifest_key_is_an_error_naming_it(built, key):
    cap, model, _ = built
    meta = json.loads((model / MARKER).read_text())
    del meta[key]
    (model / MARKER).write_text(json.dumps(meta))
    with pytest.raises(ModelError, match=f"lacks '{key}'"):
        ModelFolder(model)


def test_build_refuses_a_registration_that_does_not_cover_the_capture(toy_truth, capture_copy, tmp_path):
    """Defect 6: build silently made a model of what happened to be registered."""
    from mifacerf.formats.registration import Registration
    from mifacerf.rendering.cli import build_cmd

    cap = capture_copy(toy_truth)
    meta = json.loads((cap / "registration" / "registration.json").read_text())
    del meta["expressions"]["bulge"]                  # as an interrupted register leaves it
    del meta["files"]["expressions/bulge.npz"]
    (cap / "registration" / "registration.json").write_text(json.dumps(meta))
    assert Registration(cap / "registration").expression_names == ["neutral", "stretch"]
    with pytest.raises(RegistrationError, match=r"covers 2 of the capture's 3 expressions \(not registered: "
                                                r"bulge\).*--allow-partial"):
        build(cap, tmp_path / "m1")
    assert not (tmp_path / "m1").exists()
    res = CliRunner().invoke(build_cmd, [str(cap), "-o", str(tmp_path / "m2")])
    assert res.exit_code == 1 and "--allow-partial" in res.output and "Traceback" not in res.output
    res = CliRunner().invoke(build_cmd, [str(cap), "-o", str(tmp_path / "m2"), "--allow-partial"])
    assert res.exit_code == 0, res.output
    assert ModelFolder(tmp_path / "m2").expressions == ["neutral", "stretch"]


def test_build_never_replaces_a_folder_that_is_not_a_model(toy_truth, capture_copy):
    cap = capture_copy(toy_truth)
    old = snapshot(cap)
    with pytest.raises(ModelError, match="not a model folder; refusing to replace it"):
        build(cap, cap, overwrite=True)                  # 'build -o CAPTURE'
    assert snapshot(cap) == old


def test_existing_model_needs_overwrite(built):
    cap, model, old = built
    with pytest.raises(ModelError, match="already holds a model"):
        build(cap, model)
    assert snapshot(model) == old


def _edit_template(reg, edit):
    """Apply ``edit(template)`` to REG/template.json and record its new checksum in the manifest (the folder
    verifies: only build's consistency check can tell)."""
    from mifacerf.formats.files import file_entry

    tpath = reg / "template.json"
    tpl = json.loads(tpath.read_text())
    edit(tpl)
    tpath.write_text(json.dumps(tpl))
    meta = json.loads((reg / "registration.json").read_text())
    meta["files"]["template.json"] = file_entry(tpath)
    (reg / "registration.json").write_text(json.dumps(meta))


def _unlist(reg):
    meta = json.loads((reg / "registration.json").read_text())
    del meta["files"]["template.json"]
    (reg / "registration.json").write_text(json.dumps(meta))


@pytest.mark.parametrize("case, message", [
    ("extra_vertex", r"expressions/neutral.npz: 162 vertices, but the registration's template \S*template.json "
                     r"has 163"),
    ("triangle_out_of_range", r"template.json: triangles of shape \(320, 3\) do not index its 162 vertices"),
    ("no_triangles", r"template.json: not a usable template \(KeyError"),
    ("unlisted", r"template.json: not in the registration's manifest"),
], ids=["extra_vertex", "triangle_out_of_range", "no_triangles", "unlisted"])
def test_build_refuses_a_template_inconsistent_with_the_registration(toy_truth, capture_copy, tmp_path, case,
                                                                   message):
    """Item 4: build checks the registration's template against what was registered on it (vertex count,
    triangles, listed with its checksum); before, a template with another vertex count crashed or built."""
    from mifacerf.cli import main

    cap = capture_copy(toy_truth)
    reg = cap / "registration"
    if case == "extra_vertex":
        _edit_template(reg, lambda t: t.update(kinds=t["kinds"] + ["dot"]))
    elif case == "triangle_out_of_range":
        _edit_template(reg, lambda t: t["triangles"][5].__setitem__(1, 162))
    elif case == "no_triangles":
        _edit_template(reg, lambda t: t.pop("triangles"))
    else:
        _unlist(reg)
    with pytest.raises(RegistrationError, match=message):
        build(cap, tmp_path / "m")
    assert not (tmp_path / "m").exists() and siblings(tmp_path / "m") == []
    res = CliRunner().invoke(main, ["build", str(cap), "-o", str(tmp_path / "m")])
    assert res.exit_code == 1 and "Traceback" not in res.output
    assert len([ln for ln in res.stderr.splitlines() if ln.startswith("mifacerf build: error: ")]) == 1, res.stderr


def _compressed_state(model, old):
    """After a killed compress: the model as it was (byte-identical) or with every new file listed and
    complete (verifies, ranks 4 and 6 recorded); nothing of a transaction beside it."""
    from mifacerf.rendering.model import Model

    m = Model(model)                          # (repairs an interrupted swap first)
    assert siblings(model) == [], siblings(model)
    if snapshot(model) == old:
        return "old"
    assert m.verify() == [], m.verify()
    assert m.meta["compressed"]["pca"] == [4, 6]
    for s in range(len(m.expressions)):
        for c in range(len(m.cameras)):
            if m.has_field(s, c):
                m.compressed_field(s, c, 6, "pca")
    return "new"


@pytest.fixture
def compressed(built):
    """``built`` with rank-4 PCA fields (listed): a second compress rewrites them and adds rank 6."""
    from mifacerf.rendering.compression import compress_model
    from mifacerf.rendering.model import Model

    cap, model, _ = built
    compress_model(Model(model), 4, progress=False, method="pca")
    shutil.copytree(model, model.parent / "rank4", copy_function=shutil.copy2)
    return model, snapshot(model)


def _back_to_rank4(model):
    shutil.rmtree(model)
    shutil.copytree(model.parent / "rank4", model, copy_function=shutil.copy2)


def test_sigkill_during_compress_at_every_rename_of_the_swap(compressed):
    """Item 2: a kill during 'mifacerf compress' left PCA files with a bad checksum or unlisted: compress is
    now one transaction (a hard-linked copy of the model, the new files, model.json, swapped in)."""
    model, old = compressed
    outcomes = []
    for n in (1, 2, 3):
        p = run_child("compress", {"model": str(model), "ranks": [4, 6]}, f"call:rename:{n}:{model.name}")
        assert killed(p), p.stderr[-2000:]
        outcomes.append(_compressed_state(model, old))
        _back_to_rank4(model)
    assert outcomes == ["old", "new", "new"]   # once 'ready' exists, the swap is finished, not undone


def test_sigkill_during_compress_while_writing_and_at_random_moments(compressed):
    model, old = compressed
    p = run_child("compress", {"model": str(model), "ranks": [4, 6]}, "call:replace:3:pca")   # mid-writes
    assert killed(p), p.stderr[-2000:]
    assert _compressed_state(model, old) == "old"
    rnd = random.Random(2)
    for _ in range(2):
        p = start_child("compress", {"model": str(model), "ranks": [4, 6]}, f"time:{rnd.uniform(0, 1.0):.3f}")
        p.wait(timeout=300)
        p.stdout.read(), p.stderr.read()
        if _compressed_state(model, old) == "new":
            _back_to_rank4(model)


@pytest.mark.parametrize("nth", [2, 9])
def test_a_full_disk_during_compress_keeps_the_model(compressed, monkeypatch, nth):
    from mifacerf.rendering.compression import compress_model
    from mifacerf.rendering.model import Model

    model, old = compressed
    monkeypatch.setattr(os, "fsync", ENOSPC(nth))
    with pytest.raises(OSError) as exc:
        compress_model(Model(model), [4, 6], progress=False, method="pca")
    assert exc.value.errno == errno.ENOSPC
    assert snapshot(model) == old and siblings(model) == []
    monkeypatch.undo()
    compress_model(Model(model), [4, 6], progress=False, method="pca")       # the lock was released
    assert _compressed_state(model, old) == "new"
