"""File helpers shared by every on-disk format: atomic writes, JSON documents, checksums, folder locks.

Atomic write: the data goes to a temporary file in the destination's folder
(``.<name>.<random>.tmp``, unique per call, so two processes never share one), is
flushed and fsynced, then renamed over the destination and the folder fsynced, so a
crash never leaves a half-written file under the final name. Files are created with
the process's umask (``0o666 & ~umask``), as ``open()`` would create them.

Integrity: a folder's manifest lists ``{"<relative path>": {"size": bytes, "sha256": hex}}``
per file (:func:`file_entry`, :func:`check_entry`); the formats decide when each
check runs (docs/reliability.md).

Locks (:class:`FolderLock`): one writer per folder, serialised by an advisory
``flock`` on a lock file beside the folder (``.<folder name>.lock``) holding the
holder's PID, host and start time. The kernel drops the lock when its process dies,
so a lock left by a killed process is recovered by the next writer without a word;
a live holder is reported as ``locked by PID … on HOST since …`` (and waited for,
or refused). An *ephemeral* lock (beside a user's own files: a render's output, the demo's folder)
deletes its file on release.

Files replaced together (:func:`replacing`, over :func:`replace_together`): temporary files renamed
over their destinations through a journal that the next writer finishes (``mifacerf render -o``'s EXR
+ PNG).
"""
from __future__ import annotations

import errno
import fcntl
import hashlib
import json
import os
import socket
import tempfile
import threading
import time
import weakref
from contextlib import contextmanager
from pathlib import Path

from ..errors import refused


# ---------------------------------------------------------------- atomic writes
_umask_lock = threading.Lock()


def process_umask() -> int:
    """The process's current umask (read from /proc where available, without changing it)."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    with _umask_lock:
        mask = os.umask(0o022)
        os.umask(mask)
    return mask


def _mkstemp_for(path: Path, suffix: str = ".tmp") -> tuple[int, str]:
    """A unique temporary file next to ``path``, created with the process's umask (not 0600)."""
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix, dir=path.parent)
    try:
        os.fchmod(fd, 0o666 & ~process_umask())
    except BaseException:
        os.close(fd)
        os.unlink(tmp)
        raise
    return fd, tmp


def fsync_dir(path: str | os.PathLike) -> None:
    """fsync a folder so that renames inside it are durable (no-op where folders cannot be opened)."""
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


@contextmanager
def atomic_open(path: str | os.PathLike):
    """``with atomic_open(path) as f: f.write(...)``: a binary file that appears at ``path`` complete
    (fsync, rename, folder fsync) when the block ends, and not at all when it raises."""
    path = Path(path)
    fd, tmp = _mkstemp_for(path)
    try:
        with os.fdopen(fd, "wb") as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    fsync_dir(path.parent)


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to ``path`` via a temporary file in the same folder, fsync and rename."""
    with atomic_open(path) as f:
        f.write(data)


def atomic_target(path: Path) -> Path:
    """A temporary path next to ``path`` for writers that need a file name (rename it over ``path``)."""
    fd, tmp = _mkstemp_for(path, ".tmp" + path.suffix)
    os.close(fd)
    return Path(tmp)


def save_npz_atomic(path: str | os.PathLike, compressed: bool = True, **arrays) -> None:
    """``np.savez[_compressed]`` to ``path`` atomically (the folder is created if needed)."""
    import numpy as np

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_open(path) as f:
        (np.savez_compressed if compressed else np.savez)(f, **arrays)


def save_npy_atomic(path: str | os.PathLike, array) -> None:
    """``np.save`` to ``path`` atomically (the folder is created if needed)."""
    import numpy as np

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_open(path) as f:
        np.save(f, array)


# ---------------------------------------------------------------- JSON
def read_json(path: Path, error: type[Exception], missing: str) -> dict:
    """The JSON document at ``path``; otherwise ``error`` naming the file: ``"<path>: <missing>"`` when
    absent, ``"<path>: not valid JSON (...)"``."""
    if not path.exists():
        raise error(f"{path}: {missing}")
    try:
        return json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise error(f"{path}: not valid JSON ({exc})") from exc


def read_json_manifest(path: Path, fmt: str, version: int | tuple, error: type[Exception], missing: str,
                       what: str) -> dict:
    """The JSON manifest at ``path``, checked to be ``format`` ``fmt`` at ``version`` (or one of several);
    otherwise ``error`` naming the file: ``"<path>: <missing>"`` when absent, invalid JSON, or
    ``"not a version-N <what>"``."""
    meta = read_json(path, error, missing)
    versions = version if isinstance(version, tuple) else (version,)
    if not isinstance(meta, dict) or meta.get("format") != fmt or meta.get("version") not in versions:
        raise error(f"{path}: not a version-{versions[-1]} {what}")
    return meta


def require_keys(mapping, keys, where: str, error: type[Exception]) -> None:
    """``error("<where>: lacks 'key'")`` for the first of ``keys`` missing from ``mapping``."""
    if not isinstance(mapping, dict):
        raise error(f"{where}: expected a JSON object, got {type(mapping).__name__}")
    for k in keys:
        if k not in mapping:
            raise error(f"{where}: lacks '{k}'")


def write_json_atomic(path: str | os.PathLike, data: dict) -> None:
    atomic_write_bytes(path, (json.dumps(data, indent=1) + "\n").encode())


# ---------------------------------------------------------------- checksums
def sha256_file(path: str | os.PathLike) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def file_entry(path: str | os.PathLike) -> dict:
    """``{"size": bytes, "sha256": hex}`` of a file (its manifest entry)."""
    return {"size": os.path.getsize(path), "sha256": sha256_file(path)}


def user_cache_dir() -> Path:
    """The user's mifacerf cache: ``$MIFACERF_CACHE``, else ``~/.cache/mifacerf`` (not created here)."""
    root = os.environ.get("MIFACERF_CACHE", "").strip()
    return Path(root) if root else Path.home() / ".cache" / "mifacerf"


def switched_off(variable: str) -> bool:
    """Whether environment ``variable`` turns a default-on cache off (``0``, ``off``, ``no`` or ``false``)."""
    return os.environ.get(variable, "1").strip().lower() in ("0", "off", "no", "false")


#: a file changed less than this many seconds ago gets no stamp: file times advance in coarse ticks, so a
#: rewrite of the same size within one tick could keep a just-stamped file's times ("racy clean")
STAMP_MIN_AGE_S = 2.0


def _stamp(st: os.stat_result, sha256: str) -> Path | None:
    """The stamp of a file whose checksum was found equal to ``sha256`` while its ``stat`` was ``st``
    (None when stamps are off: ``MIFACERF_CHECKSUM_STAMPS=0``). A stamp is an empty file in
    ``<cache>/verified/`` named by the hash of (device, inode, size, mtime, ctime, sha256): any write to
    the file, a ``touch``, a copy or a replacement changes its ctime (which no user call can set back),
    so the stamp no longer applies and the file is checksummed again."""
    if switched_off("MIFACERF_CHECKSUM_STAMPS"):
        return None
    key = f"{st.st_dev}:{st.st_ino}:{st.st_size}:{st.st_mtime_ns}:{st.st_ctime_ns}:{sha256}"
    return user_cache_dir() / "verified" / hashlib.sha1(key.encode()).hexdigest()


def check_entry(path: Path, entry: dict, error: type[Exception], checksum: bool = True,
                stamps: bool = True) -> None:
    """``error`` naming ``path`` when it is missing, has another size than ``entry`` or (``checksum``)
    another sha256.

    A file whose checksum has matched once is stamped (:func:`_stamp`) and, with ``stamps``, not read
    again while its device, inode, size, mtime and ctime are unchanged — as git trusts its index's stat
    data. This is what lets a second process open a 4 GB model without hashing its fields again (a
    fresh 30-frame ``mifacerf drive`` spent 3.5 s there). ``stamps=False`` (``mifacerf verify``) reads
    every byte; so does every check with ``MIFACERF_CHECKSUM_STAMPS=0``. A cache folder that cannot be
    written only costs the re-reading."""
    try:
        st = path.stat()
    except FileNotFoundError:
        raise error(f"{path}: missing (listed in the folder's manifest)") from None
    if st.st_size != entry["size"]:
        raise error(f"{path}: {st.st_size} bytes, the manifest says {entry['size']} (the file changed or is "
                    "truncated)")
    if not checksum:
        return
    stamp = _stamp(st, entry["sha256"])
    if stamps and stamp is not None and stamp.exists():
        return
    if sha256_file(path) != entry["sha256"]:
        raise error(f"{path}: checksum mismatch (the file changed or is corrupt)")
    if stamp is not None and time.time() - st.st_ctime >= STAMP_MIN_AGE_S:
        try:
            stamp.parent.mkdir(parents=True, exist_ok=True)
            stamp.touch()
        except OSError:
            pass


def verify_entries(root: Path, files: dict, error: type[Exception]) -> list[str]:
    """Every problem (one line each, naming the file) found by checking each ``files`` entry under ``root``."""
    problems = []
    for rel, entry in sorted(files.items()):
        try:
            check_entry(Path(root) / rel, entry, error, stamps=False)
        except error as exc:
            problems.append(str(exc))
    return problems


# ---------------------------------------------------------------- locks
_held: dict[tuple, list] = {}         # (lock path, thread) -> [fd, count]: re-entrant within one thread
_held_lock = threading.Lock()


def lock_path(folder: str | os.PathLike) -> Path:
    """The lock file of ``folder``: ``.<name>.lock`` beside it (it survives the folder being replaced)."""
    folder = Path(os.path.abspath(folder))
    return folder.parent / f".{folder.name}.lock"


def _try_flock(fd: int) -> bool:
    """Take the exclusive lock on ``fd`` if it is free (True), else False."""
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        return True
    except OSError as exc:
        if exc.errno not in (errno.EAGAIN, errno.EACCES, errno.EWOULDBLOCK):
            raise
        return False


def _holder(fd: int) -> str:
    try:
        os.lseek(fd, 0, os.SEEK_SET)
        d = json.loads(os.read(fd, 4096).decode() or "{}")
        return f"PID {d.get('pid', '?')} on {d.get('host', '?')} since {d.get('since', '?')}"
    except (OSError, ValueError):
        return "another process"


def _same_file(fd: int, path: Path) -> bool:
    try:
        a, b = os.fstat(fd), os.stat(path)
    except OSError:
        return False
    return (a.st_dev, a.st_ino) == (b.st_dev, b.st_ino)


class FolderLock:
    """Exclusive writer's lock on ``folder`` (a context manager; re-entrant within a thread).

    ``wait``: True waits for a live holder (``log`` hears once who holds it), a number waits that many
    seconds at most, False refuses at once; a refusal raises ``error`` ("<folder>: locked by PID … on
    HOST since …"), made a :class:`mifacerf.errors.RefusedError` too (:func:`mifacerf.errors.refused`:
    the command line exits 3). A holder that died left nothing to clean up: the kernel released its lock.
    """

    def __init__(self, folder: str | os.PathLike, error: type[Exception] = OSError, wait: bool | float = True,
                 log=None, what: str = "write", ephemeral: bool = False):
        self.folder = Path(folder)
        self.path = lock_path(folder)
        self.error, self.wait, self.log, self.what = error, wait, log, what
        # ephemeral: the lock file is deleted on release (for a lock beside a user's own files, e.g. one
        # render's output, where a lasting dot-file would be litter); a holder that finds it has locked
        # a file another holder deleted meanwhile opens the new one and locks again
        self.ephemeral = ephemeral
        self._fd = None

    def acquire(self) -> "FolderLock":
        # re-entrant in the thread that holds it; another thread opens its own descriptor, which flock
        # treats as another holder (it waits or is refused, as another process would be)
        key = self._key = (str(self.path), threading.get_ident())
        with _held_lock:
            if key in _held:
                _held[key][1] += 1
                self._fd = _held[key][0]
                return self
        self.path.parent.mkdir(parents=True, exist_ok=True)
        while True:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o666)
            try:
                self._lock(fd)
            except BaseException:
                os.close(fd)
                raise
            if not self.ephemeral or _same_file(fd, self.path):
                break
            os.close(fd)                 # locked a file its holder deleted on release: lock the new one
        try:
            os.ftruncate(fd, 0)
            os.lseek(fd, 0, os.SEEK_SET)
            os.write(fd, json.dumps({"pid": os.getpid(), "host": socket.gethostname(),
                                     "since": time.strftime("%Y-%m-%d %H:%M:%S"), "what": self.what}).encode())
        except BaseException:
            os.close(fd)
            raise
        with _held_lock:
            _held[key] = [fd, 1]
        self._fd = fd
        return self

    def _lock(self, fd: int) -> None:
        if _try_flock(fd):
            return
        who = _holder(fd)
        if self.wait is False:
            raise refused(self.error, f"{self.folder}: locked by {who} (another {self.what} is running; "
                          "wait for it to finish)")
        if self.log is not None:
            self.log(f"{self.folder}: locked by {who}; waiting for it to finish")
        deadline = None if self.wait is True else time.monotonic() + float(self.wait)
        while not _try_flock(fd):
            if deadline is not None and time.monotonic() > deadline:
                raise refused(self.error, f"{self.folder}: locked by {_holder(fd)} (still, after {self.wait} s)")
            time.sleep(0.05)

    def release(self) -> None:
        if self._fd is None:
            return
        key = self._key                  # (the thread that acquired it: a finalizer may run elsewhere)
        with _held_lock:
            entry = _held.get(key)
            if entry is not None:
                entry[1] -= 1
                if entry[1] > 0:
                    self._fd = None
                    return
                del _held[key]
        fd, self._fd = self._fd, None
        try:
            os.ftruncate(fd, 0)
        except OSError:
            pass
        if self.ephemeral:
            try:
                self.path.unlink()       # still held: a waiter that locks it next sees it is gone (above)
            except OSError:
                pass
        fcntl.flock(fd, fcntl.LOCK_UN)
        os.close(fd)

    def __enter__(self) -> "FolderLock":
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()


# ---------------------------------------------------------------- files replaced together
def replace_together(pairs, journal: str | os.PathLike) -> None:
    """Rename complete temporary files over their destinations as one roll-forward transaction.

    ``pairs``: ``[(temporary, destination), ...]``, all in one folder (``mifacerf render -o``: the EXR
    and its PNG). The journal (a small JSON file, written atomically) names the pairs before the first
    rename and is deleted after the last, so a process killed between two renames leaves the journal:
    :func:`finish_replacing` — run by the next writer of the same destinations, under their lock —
    completes the renames left, and the destinations are the new set again (never the old one of one
    file beside the new one of the other, past that point). Call it with the destinations' lock held.
    """
    journal = Path(journal)
    write_json_atomic(journal, {"replace": [[Path(t).name, Path(d).name] for t, d in pairs]})
    finish_replacing(journal)


def finish_replacing(journal: str | os.PathLike, error: type[Exception] = OSError) -> bool:
    """Finish an interrupted :func:`replace_together` (True), or do nothing when ``journal`` is absent."""
    journal = Path(journal)
    try:
        entries = json.loads(journal.read_text())["replace"]
    except FileNotFoundError:
        return False
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise error(f"{journal}: unreadable replacement journal ({exc}); its temporary files beside it hold "
                    "the newer render: rename them by hand or delete the journal") from exc
    for tmp, dst in entries:
        src = journal.parent / tmp
        if src.exists():                 # absent: renamed before the interruption
            os.replace(src, journal.parent / dst)
    fsync_dir(journal.parent)
    journal.unlink()
    fsync_dir(journal.parent)
    return True


@contextmanager
def replacing(target: str | os.PathLike, companions=(), error: type[Exception] = OSError, what: str = "write"):
    """``with replacing(path, (".png",)) as tmp:`` write ``tmp`` (and ``tmp.with_suffix(s)`` for each
    companion suffix); when the block ends they replace ``path`` and its companions as one transaction.

    ``path``'s ephemeral lock (:class:`FolderLock`; a second writer is refused, ``error`` made a
    :class:`mifacerf.errors.RefusedError`) is held throughout. First a replacement interrupted by a kill
    is finished (:func:`finish_replacing`) and temporaries of a writer killed before its renames are
    deleted; then the block writes; then :func:`replace_together` renames through the journal
    ``.<name>.replacing``. A block that raises leaves the previous files and no temporary.
    """
    target = Path(os.path.abspath(target))
    folder, stem = target.parent, f".{target.name}."
    journal = folder / f"{stem}replacing"
    with FolderLock(target, error, wait=False, what=what, ephemeral=True):
        finish_replacing(journal, error)
        for name in os.listdir(folder):
            for start in (stem, f".{journal.name}."):     # (and of the journal's own atomic write)
                if name.startswith(start) and ".tmp" in name[len(start):]:
                    (folder / name).unlink(missing_ok=True)
        tmp = folder / f"{stem}{os.getpid()}-{os.urandom(4).hex()}.tmp{target.suffix}"
        pairs = [(tmp.with_suffix(s), target.with_suffix(s)) for s in companions
                 if tmp.with_suffix(s) != tmp] + [(tmp, target)]
        try:
            yield tmp
            replace_together(pairs, journal)
        finally:
            if journal.exists():             # failed between two renames: roll forward now if the disk
                try:                         # lets us (else the next writer does)
                    finish_replacing(journal, error)
                except (OSError, error):
                    pass
            if not journal.exists():
                for t, _ in pairs:
                    t.unlink(missing_ok=True)


# ---------------------------------------------------------------- whole-folder transactions
#: sibling folders of a folder transaction: ``.<name>.building-*`` (being written), ``.<name>.ready-*``
#: (complete, about to be swapped in), ``.<name>.old-*`` (the replaced folder, being deleted)
_STAGES = ("building", "ready", "old")


def new_building_dir(target: str | os.PathLike) -> Path:
    """A fresh ``.<name>.building-*`` folder beside ``target`` (created with the process's umask)."""
    target = Path(os.path.abspath(target))
    target.parent.mkdir(parents=True, exist_ok=True)
    path = Path(tempfile.mkdtemp(prefix=f".{target.name}.building-{os.getpid()}-", dir=target.parent))
    os.chmod(path, 0o777 & ~process_umask())
    return path


def _siblings(target: Path, stage: str) -> list[Path]:
    prefix = f".{target.name}.{stage}-"
    try:
        names = os.listdir(target.parent)
    except OSError:
        return []
    return sorted((target.parent / n for n in names if n.startswith(prefix)), key=lambda p: p.name)


def _remove_tree(path: Path, marker: str) -> None:
    import shutil

    try:
        (path / marker).unlink()        # first: a half-deleted folder never looks complete
    except FileNotFoundError:
        pass
    shutil.rmtree(path, ignore_errors=True)


def swap_in(target: str | os.PathLike, building: Path, marker: str) -> None:
    """Replace ``target`` by the complete folder ``building`` (the caller holds ``target``'s lock).

    Renames ``building`` to ``.<name>.ready-*`` (the commit point), ``target`` (if any) aside to
    ``.<name>.old-*``, the ready folder to ``target``, then deletes the old one (its ``marker`` file
    first). Killed at any moment, :func:`repair_swap` finishes the swap: ``target`` is either the old
    complete folder or the new one.
    """
    target = Path(os.path.abspath(target))
    ready = target.parent / building.name.replace(".building-", ".ready-", 1)
    os.rename(building, ready)
    fsync_dir(target.parent)
    _finish_swap(target, ready, marker)


def _finish_swap(target: Path, ready: Path, marker: str) -> None:
    old = None
    if target.exists():
        old = target.parent / ready.name.replace(".ready-", ".old-", 1)
        os.rename(target, old)
    os.rename(ready, target)
    fsync_dir(target.parent)
    if old is not None:
        _remove_tree(old, marker)


def pending_swap(target: str | os.PathLike) -> bool:
    """Whether folders of an unfinished transaction lie beside ``target``."""
    target = Path(os.path.abspath(target))
    return any(_siblings(target, s) for s in _STAGES)


def repair_swap(target: str | os.PathLike, marker: str) -> None:
    """Finish or undo an interrupted :func:`swap_in` (the caller holds ``target``'s lock, so no writer is
    running): a ready folder is swapped in; without one, a missing ``target`` gets its old folder back
    (when complete: ``marker`` present); every other leftover (unfinished builds) is deleted."""
    target = Path(os.path.abspath(target))
    ready = _siblings(target, "ready")
    if ready:
        _finish_swap(target, ready[-1], marker)
    elif not target.exists():
        olds = [p for p in _siblings(target, "old") if (p / marker).exists()]
        if olds:
            os.rename(olds[-1], target)
            fsync_dir(target.parent)
    for stage in _STAGES:
        for p in _siblings(target, stage):
            _remove_tree(p, marker)


def repair_if_needed(target: str | os.PathLike, marker: str, error: type[Exception], settle_s: float = 10.0) -> None:
    """Readers' half of the folder transaction: when an interrupted swap lies beside ``target``, repair
    it if no writer holds the lock; when one does, wait (up to ``settle_s``) for ``target`` to exist."""
    target = Path(os.path.abspath(target))
    if not pending_swap(target):
        return
    try:
        with FolderLock(target, error, wait=False):
            repair_swap(target, marker)
        return
    except error:
        pass                       # a writer is at work: it finishes its own swap
    except OSError:
        return                     # cannot lock here (read-only medium): read what is there
    deadline = time.monotonic() + settle_s
    while not (target / marker).exists() and time.monotonic() < deadline:
        time.sleep(0.05)


def link_tree(src: str | os.PathLike, dst: str | os.PathLike) -> None:
    """``dst`` (absent, or an empty folder) gets ``src`` (a file or a folder tree) as hard links, copies
    where links fail; the two then share every file's inode, so writing a file of ``dst`` by rename (the
    atomic writer) leaves ``src``'s untouched."""
    import shutil

    src, dst = Path(src), Path(dst)
    if src.is_file():
        dst.parent.mkdir(parents=True, exist_ok=True)
        try:
            os.link(src, dst)
        except OSError:
            shutil.copy2(src, dst)
        return
    dst.mkdir(parents=True, exist_ok=True)
    for p in sorted(src.iterdir()):
        link_tree(p, dst / p.name)


def _discard(root: Path, lock: "FolderLock") -> None:
    import shutil

    shutil.rmtree(root, ignore_errors=True)
    lock.release()


class OutputFolder:
    """A command's output folder written as one transaction (``mifacerf drive``, ``mifacerf track``).

    Construction takes the folder's lock (``wait``: see :class:`FolderLock`; False refuses at once,
    exit 3), finishes or undoes an interrupted swap (:func:`repair_swap`), refuses a folder that holds
    files but no ``marker`` (it is not this command's output: never replaced; ``legacy(name)`` accepts
    the entries of an earlier version's output, which had no marker), and makes :attr:`root`,
    a ``.<name>.building-*`` folder beside ``target`` that the command writes into. :meth:`finish`
    (once ``marker`` is written) hard-links into it the entries of the previous folder that ``carry(name)``
    keeps (another command's output inside this one) and swaps it in (:func:`swap_in`): killed, failed or
    out of space at any moment, ``target`` is the previous complete folder or the new one. :meth:`abort`
    — or a failure inside ``with OutputFolder(...)``, or the object being dropped unfinished — deletes
    the new folder and releases the lock.
    """

    def __init__(self, target: str | os.PathLike, marker: str, error: type[Exception] = OSError,
                 what: str = "run", wait: bool | float = False, carry=None, log=None, legacy=None):
        self.target = Path(os.path.abspath(target))
        self.marker, self.error, self.what, self.carry = marker, error, what, carry
        lock = FolderLock(self.target, error, wait=wait, log=log, what=what).acquire()
        try:
            repair_swap(self.target, marker)
            if self.target.exists() and not self.target.is_dir():
                raise error(f"{self.target}: not a folder")
            if self.target.is_dir() and not (self.target / marker).exists() and \
                    any(not n.startswith(".") and not (legacy and legacy(n)) for n in os.listdir(self.target)):
                raise error(f"{self.target}: holds files but no {marker}, so it is not a {what} folder; refusing "
                            "to replace it (choose a new or empty folder)")
            self.root = new_building_dir(self.target)
        except BaseException:
            lock.release()
            raise
        self._lock = lock
        self._finalizer = weakref.finalize(self, _discard, self.root, lock)

    def finish(self) -> Path:
        """Swap the new folder in (the lock is released); returns ``target``."""
        if not self._finalizer.alive:
            raise self.error(f"{self.target}: this {self.what} was already finished or aborted")
        try:
            if not (self.root / self.marker).exists():
                raise self.error(f"{self.root / self.marker}: not written; the new {self.what} folder is "
                                 "incomplete and is not swapped in")
            if self.carry is not None and self.target.is_dir():
                for name in sorted(os.listdir(self.target)):
                    if not name.startswith(".") and self.carry(name) and not (self.root / name).exists():
                        link_tree(self.target / name, self.root / name)
            swap_in(self.target, self.root, self.marker)
        except BaseException:
            self.abort()
            raise
        self._finalizer.detach()
        self._lock.release()
        return self.target

    def abort(self) -> None:
        """Delete the new folder (the previous one stays) and release the lock."""
        self._finalizer()

    def __enter__(self) -> "OutputFolder":
        return self

    def __exit__(self, exc_type, *exc) -> None:
        if exc_type is not None:
            self.abort()
