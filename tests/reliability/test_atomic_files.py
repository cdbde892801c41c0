"""The file helpers every format writes through: atomic writes (umask, full disk), checksums, folder locks."""
import errno
import json
import os
import signal
import socket
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from mifacerf.formats import files as F

from .faults import ENOSPC


@pytest.mark.parametrize("umask", [0o022, 0o077, 0o002])
def test_atomic_writes_honour_the_umask(tmp_path, umask):
    """Defect 9: files written through the atomic writer were 0600 whatever the umask (mkstemp)."""
    from mifacerf.imageio import write_exr, write_png

    old = os.umask(umask)
    try:
        F.write_json_atomic(tmp_path / "a.json", {"x": 1})
        F.save_npz_atomic(tmp_path / "sub" / "b.npz", x=np.arange(3))
        F.save_npy_atomic(tmp_path / "c.npy", np.arange(3))
        write_exr(tmp_path / "d.exr", np.zeros((4, 4, 3), np.float32))
        write_png(tmp_path / "e.png", np.zeros((4, 4, 3), np.float32))
        assert F.process_umask() == umask
    finally:
        os.umask(old)
    for name in ("a.json", "sub/b.npz", "c.npy", "d.exr", "e.png"):
        assert (tmp_path / name).stat().st_mode & 0o777 == 0o666 & ~umask, name
    assert not [p for p in tmp_path.rglob("*.tmp*")]


def test_a_full_disk_leaves_the_previous_file(tmp_path, monkeypatch):
    path = tmp_path / "doc.json"
    F.write_json_atomic(path, {"version": "old"})
    before = path.read_bytes()
    monkeypatch.setattr(os, "fsync", ENOSPC(1))
    with pytest.raises(OSError) as exc:
        F.write_json_atomic(path, {"version": "new", "pad": "x" * 10000})
    assert exc.value.errno == errno.ENOSPC
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["doc.json"]      # no temporary left behind


def test_temporary_names_are_unique(tmp_path):
    """Two writers of one file never share a temporary name (defect 2's crash in registration/proxies.py)."""
    a, b = F.atomic_target(tmp_path / "x.npz"), F.atomic_target(tmp_path / "x.npz")
    assert a != b and a.name.startswith(".x.npz.") and a.suffix == ".npz"


def test_entries_name_the_file(tmp_path):
    p = tmp_path / "f.bin"
    p.write_bytes(b"abcdef")
    entry = F.file_entry(p)
    F.check_entry(p, entry, ValueError)
    p.write_bytes(b"abcdeg")
    with pytest.raises(ValueError, match=r"f\.bin: checksum mismatch"):
        F.check_entry(p, entry, ValueError)
    F.check_entry(p, entry, ValueError, checksum=False)      # same size: the cheap check passes
    p.write_bytes(b"abc")
    with pytest.raises(ValueError, match=r"f\.bin: 3 bytes, the manifest says 6"):
        F.check_entry(p, entry, ValueError, checksum=False)
    p.unlink()
    with pytest.raises(ValueError, match=r"f\.bin: missing"):
        F.check_entry(p, entry, ValueError, checksum=False)


def test_require_keys_names_the_key():
    with pytest.raises(ValueError, match="m.json: lacks 'b'"):
        F.require_keys({"a": 1}, ("a", "b"), "m.json", ValueError)


HOLDER = textwrap.dedent("""
    import sys, time
    from mifacerf.formats.files import FolderLock
    lock = FolderLock(sys.argv[1]).acquire()
    print("held", flush=True)
    time.sleep(60)
""")


def _holder(folder):
    p = subprocess.Popen([sys.executable, "-c", HOLDER, str(folder)], stdout=subprocess.PIPE, text=True)
    assert p.stdout.readline().strip() == "held"
    return p


def test_lock_refuses_names_the_holder_and_recovers_from_a_killed_one(tmp_path):
    folder = tmp_path / "reg"
    holder = _holder(folder)
    try:
        with pytest.raises(ValueError, match=rf"locked by PID {holder.pid} on {socket.gethostname()} since "
                                             r"\d{4}-\d\d-\d\d \d\d:\d\d:\d\d"):
            F.FolderLock(folder, ValueError, wait=False).acquire()
        with pytest.raises(ValueError, match="still, after 0.2 s"):
            F.FolderLock(folder, ValueError, wait=0.2).acquire()
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait()
    # the killed holder's lock is free at once: nothing to clean up by hand
    with F.FolderLock(folder, ValueError, wait=False):
        held = json.loads(F.lock_path(folder).read_text())
        assert held["pid"] == os.getpid()
        with F.FolderLock(folder, ValueError, wait=False):        # re-entrant within a process
            pass
        assert F.lock_path(folder).read_text()                   # still held by the outer one
    assert F.lock_path(folder).read_text() == ""


def test_waiting_for_a_lock_says_who_holds_it(tmp_path):
    folder = tmp_path / "model"
    holder = _holder(folder)
    heard = []
    try:
        import threading

        threading.Timer(0.5, lambda: holder.send_signal(signal.SIGTERM)).start()
        with F.FolderLock(folder, ValueError, wait=True, log=heard.append):
            pass
    finally:
        holder.wait()
    assert len(heard) == 1 and f"locked by PID {holder.pid}" in heard[0] and "waiting" in heard[0]


def test_an_interrupted_swap_is_finished_or_undone(tmp_path):
    """Every crash point of swap_in: the folder is the old complete one or the new complete one."""
    target = tmp_path / "m"

    def folder(tag):
        d = F.new_building_dir(target)
        (d / "data").write_text(tag)
        (d / "marker").write_text("")
        return d

    target.mkdir()
    (target / "data").write_text("old")
    (target / "marker").write_text("")
    # crash after building -> ready: the repair rolls forward
    b = folder("new1")
    os.rename(b, tmp_path / b.name.replace(".building-", ".ready-"))
    F.repair_swap(target, "marker")
    assert (target / "data").read_text() == "new1" and not F.pending_swap(target)
    # crash after target -> old, before ready -> target: forward again
    b = folder("new2")
    ready = tmp_path / b.name.replace(".building-", ".ready-")
    os.rename(b, ready)
    os.rename(target, tmp_path / ready.name.replace(".ready-", ".old-"))
    F.repair_swap(target, "marker")
    assert (target / "data").read_text() == "new2" and not F.pending_swap(target)
    # an unfinished build (no ready folder): dropped, the target stays
    folder("half")
    F.repair_swap(target, "marker")
    assert (target / "data").read_text() == "new2" and not F.pending_swap(target)
    # target gone, only the old one left (complete): it comes back
    os.rename(target, tmp_path / ".m.old-1-x")
    F.repair_swap(target, "marker")
    assert (target / "data").read_text() == "new2"


def test_another_thread_is_another_holder(tmp_path):
    """The lock is re-entrant in its own thread only: a reader thread of the same process (the studio's
    server beside its registration worker) must not walk into a writer's commit."""
    import threading

    folder = tmp_path / "reg"
    seen = []
    with F.FolderLock(folder, ValueError):
        t = threading.Thread(target=lambda: seen.append(
            pytest.raises(ValueError, F.FolderLock(folder, ValueError, wait=False).acquire).value))
        t.start()
        t.join()
    assert len(seen) == 1 and f"locked by PID {os.getpid()}" in str(seen[0])
    with F.FolderLock(folder, ValueError, wait=False):       # free again once released
        pass
