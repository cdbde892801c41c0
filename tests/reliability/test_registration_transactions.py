"""The registration folder as a transaction: --force replaces only what it re-made, concurrent runs both
land, a kill or a full disk leaves the previous state or the new one, bit rot is named."""
import errno
import json
import os
import random
import time

import numpy as np
import pytest

from mifacerf.formats.registration import INTENT, MARKER, Registration, RegistrationError

from .faults import ENOSPC, killed, run_child, siblings, snapshot, start_child

# the registered toy capture takes ~20 s to make
pytestmark = pytest.mark.slow


def register(capture, **kw):
    from mifacerf.registration import register_capture

    return register_capture(capture, progress=False, **kw)


def meta(reg_dir):
    return json.loads((reg_dir / MARKER).read_text())


def files_of(snap, name):
    return {k for k in snap if k == f"expressions/{name}.npz" or k.startswith(f"dotfree/{name}/")}


def assert_old_or_new(reg_dir, old: dict, redone: set):
    """Every file of ``old`` is byte-identical, or belongs to an expression in ``redone`` that is now a
    complete newer registration; no expression is lost; the folder verifies."""
    r = Registration(reg_dir)                 # (finishes an interrupted commit)
    now = snapshot(reg_dir)
    assert r.verify() == [], r.verify()
    assert set(json.loads(old[MARKER])["expressions"]) <= set(r.meta["expressions"])
    for rel, data in old.items():
        if rel in (MARKER,) or now.get(rel) == data:
            continue
        owner = rel.split("/")[1].removesuffix(".npz") if "/" in rel else None
        assert owner in redone, rel
    assert not (reg_dir / INTENT).exists() and not [p for p in reg_dir.iterdir() if p.name.startswith(".staging")]
    assert siblings(reg_dir) == []
    return now == old


def test_force_on_one_expression_keeps_the_others(toy_reg, capture_copy):
    """Defect 1: 'register --force --expressions X' dropped every other expression from registration.json."""
    cap = capture_copy(toy_reg)
    out = cap / "registration"
    old = snapshot(out)
    register(cap, expressions=["stretch"], force=True)
    assert sorted(meta(out)["expressions"]) == ["bulge", "neutral", "stretch"]
    now = snapshot(out)
    for rel in files_of(old, "neutral") | files_of(old, "bulge") | {"template.json"}:
        assert now[rel] == old[rel], rel                  # untouched
    assert now["expressions/stretch.npz"] != old["expressions/stretch.npz"]   # re-made
    assert Registration(out).verify() == []


def test_a_failure_during_force_leaves_the_previous_state(toy_reg, capture_copy, monkeypatch):
    from mifacerf.registration.register import Registrar

    cap = capture_copy(toy_reg)
    out = cap / "registration"
    old = snapshot(out)
    real = Registrar.register

    def failing(self, name):
        if name == "stretch":
            self.writer.write_dotfree("stretch", "cam0", np.zeros((1, 2)), np.zeros((self.cap.n_lights, 1, 3)))
            raise RuntimeError("injected failure")
        return real(self, name)

    monkeypatch.setattr(Registrar, "register", failing)
    with pytest.raises(RuntimeError, match="injected"):
        register(cap, expressions=["stretch"], force=True)
    assert snapshot(out) == old
    assert assert_old_or_new(out, old, set())
    with pytest.raises(RuntimeError, match="injected"):       # a full re-registration: the old folder stays
        register(cap, force=True)
    assert snapshot(out) == old and siblings(out) == []


@pytest.mark.parametrize("nth", [1, 3, 4])
def test_a_full_disk_during_a_commit_leaves_the_previous_state(toy_reg, capture_copy, monkeypatch, nth):
    """The n-th file write of 'register --force --expressions bulge' (dot-free patches, the geometry, the
    commit's intent) fails with ENOSPC."""
    cap = capture_copy(toy_reg)
    out = cap / "registration"
    old = snapshot(out)
    monkeypatch.setattr(os, "fsync", ENOSPC(nth))
    with pytest.raises(OSError) as exc:
        register(cap, expressions=["bulge"], force=True)
    assert exc.value.errno == errno.ENOSPC
    assert snapshot(out) == old
    assert assert_old_or_new(out, old, set())


def test_two_registers_at_once_both_land(toy_plain, capture_copy):
    """Defect 2: two runs on different expressions lost one of them (last writer wins)."""
    cap = capture_copy(toy_plain)
    procs = [start_child("register", {"capture": str(cap), "expressions": [n]}) for n in ("stretch", "bulge")]
    outs = [p.communicate(timeout=600) for p in procs]
    assert [p.returncode for p in procs] == [0, 0], [o[1][-2000:] for o in outs]
    assert any("locked by PID" in err and "waiting" in err for _, err in outs)
    out = cap / "registration"
    assert sorted(meta(out)["expressions"]) == ["bulge", "neutral", "stretch"]
    assert Registration(out).verify() == []


def test_sigkill_during_commits(toy_reg, capture_copy):
    """Killed just before each move of a commit and at random moments: the previous state or the new one."""
    cap = capture_copy(toy_reg)
    out = cap / "registration"
    old = snapshot(out)
    args = {"capture": str(cap), "expressions": ["stretch"], "force": True}
    # a staged write, the intent's own rename, the first and the second move of the commit
    for kill in ("call:replace:2:.staging-", "call:replace:1:.commit.json", "call:replace:1:.staging-!.tmp",
                 "call:replace:2:.staging-!.tmp"):
        p = run_child("register", args, kill)
        assert killed(p), p.stderr[-2000:]
        if not assert_old_or_new(out, old, {"stretch"}):
            old = snapshot(out)
    rnd = random.Random(15)
    for _ in range(2):
        p = start_child("register", args, f"time:{rnd.uniform(0.5, 8.0):.2f}")
        p.communicate(timeout=600)
        if not assert_old_or_new(out, old, {"stretch"}):
            old = snapshot(out)


def test_sigkill_during_a_full_reregistration(toy_reg, capture_copy):
    cap = capture_copy(toy_reg)
    out = cap / "registration"
    old = snapshot(out)
    # killed just before the staged write of the last expression: neutral and stretch are done, nothing is
    # committed (a fixed delay was a race: registration got faster and CI finished it before 6 s)
    p = run_child("register", {"capture": str(cap), "force": True}, "call:replace:1:bulge", timeout=600)
    assert killed(p), p.stderr[-2000:]
    assert assert_old_or_new(out, old, {"neutral", "stretch", "bulge"})
    assert snapshot(out) == old                       # the fresh folder was never swapped in


def test_an_interrupted_commit_is_finished_by_the_next_reader(toy_reg, capture_copy):
    cap = capture_copy(toy_reg)
    out = cap / "registration"
    old = snapshot(out)
    p = run_child("register", {"capture": str(cap), "expressions": ["stretch"], "force": True},
                  "call:replace:2:.staging-!.tmp")      # after the intent and the first move
    assert killed(p)
    assert (out / INTENT).exists()
    assert not assert_old_or_new(out, old, {"stretch"})       # rolled forward: the new stretch
    assert meta(out)["expressions"]["stretch"] != json.loads(old[MARKER])["expressions"]["stretch"]


def test_bit_rot_is_named(toy_reg, capture_copy):
    from mifacerf.formats.cli import verify_folder

    cap = capture_copy(toy_reg)
    out = cap / "registration"
    npz = out / "expressions" / "bulge.npz"
    data = bytearray(npz.read_bytes())
    data[len(data) // 2] ^= 1
    npz.write_bytes(bytes(data))
    r = Registration(out)
    with pytest.raises(RegistrationError, match=r"bulge\.npz: checksum mismatch"):
        r.expression("bulge")
    kind, problems = verify_folder(out)
    assert kind == "registration" and len(problems) == 1 and "bulge.npz" in problems[0]
    with pytest.raises(RegistrationError, match=r"bulge\.npz: checksum mismatch"):
        register(cap)                                   # a damaged reference is not used silently


@pytest.mark.parametrize("key", ["capture", "expressions", "files"])
def test_a_missing_manifest_key_is_an_error_naming_it(toy_reg, capture_copy, key):
    cap = capture_copy(toy_reg)
    m = meta(cap / "registration")
    del m[key]
    (cap / "registration" / MARKER).write_text(json.dumps(m))
    with pytest.raises(RegistrationError, match=f"lacks '{key}'"):
        Registration(cap / "registration")


def test_a_rerun_with_nothing_to_do_writes_nothing(toy_reg, capture_copy):
    cap = capture_copy(toy_reg)
    out = cap / "registration"
    before = {p: p.stat().st_mtime_ns for p in out.rglob("*") if p.is_file()}
    time.sleep(0.01)
    register(cap)
    assert {p: p.stat().st_mtime_ns for p in out.rglob("*") if p.is_file()} == before


def test_a_version_1_folder_is_read_and_upgraded(toy_reg, capture_copy):
    cap = capture_copy(toy_reg)
    out = cap / "registration"
    m = meta(out)
    m["version"] = 1
    del m["files"]
    (out / MARKER).write_text(json.dumps(m))
    r = Registration(out)
    assert r.files is None and r.expression_names == ["neutral", "stretch", "bulge"]
    assert "version-1" in r.verify()[0]
    register(cap)                                       # nothing to register: upgraded all the same
    assert meta(out)["version"] == 2 and Registration(out).verify() == []
