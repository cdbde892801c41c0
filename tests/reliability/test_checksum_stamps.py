"""Checksum stamps (formats/files.py): a file whose sha256 matched once is not read again while its stat data
(device, inode, size, mtime, ctime) are unchanged; any change to it is still found."""
import os
import time

import pytest

from mifacerf.formats import files


class ModelError(Exception):
    pass


@pytest.fixture
def counted(tmp_path, monkeypatch):
    """A file with its manifest entry, the cache in tmp_path, and a counter of full reads."""
    monkeypatch.setenv("MIFACERF_CACHE", str(tmp_path / "cache"))
    monkeypatch.delenv("MIFACERF_CHECKSUM_STAMPS", raising=False)
    path = tmp_path / "field.rf.npy"
    path.write_bytes(os.urandom(100_000))
    entry = files.file_entry(path)
    reads = []
    real = files.sha256_file
    monkeypatch.setattr(files, "sha256_file", lambda p: reads.append(p) or real(p))
    return path, entry, reads


@pytest.fixture
def stamped(counted, monkeypatch):
    """``counted`` with the age rule off and the file checked (and stamped) once."""
    path, entry, reads = counted
    monkeypatch.setattr(files, "STAMP_MIN_AGE_S", 0.0)
    files.check_entry(path, entry, ModelError)
    assert len(reads) == 1
    return counted


def test_a_checked_file_is_not_read_again_until_it_changes(stamped):
    path, entry, reads = stamped
    files.check_entry(path, entry, ModelError)
    assert len(reads) == 1                                    # the second check trusted the stamp
    assert files.verify_entries(path.parent, {path.name: entry}, ModelError) == []
    assert len(reads) == 2                                    # 'mifacerf verify' reads every byte
    time.sleep(0.05)                                          # past the file clock's tick
    data = bytearray(path.read_bytes())
    data[5000] ^= 0x01
    path.write_bytes(bytes(data))                             # same size, one bit changed
    with pytest.raises(ModelError, match="field.rf.npy: checksum mismatch"):
        files.check_entry(path, entry, ModelError)
    assert len(reads) == 3


def test_touch_and_replacement_void_the_stamp(stamped):
    path, entry, reads = stamped
    time.sleep(0.05)
    st = path.stat()
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))      # mtime put back: the ctime still moves
    files.check_entry(path, entry, ModelError)
    assert len(reads) == 2
    copy = path.with_name("copy")
    copy.write_bytes(path.read_bytes())
    os.replace(copy, path)                                    # same bytes, another inode
    files.check_entry(path, entry, ModelError)
    assert len(reads) == 3


def test_a_file_changed_just_now_gets_no_stamp(counted):
    """The racy case: a file written within STAMP_MIN_AGE_S is checksummed on every check."""
    path, entry, reads = counted
    files.check_entry(path, entry, ModelError)
    files.check_entry(path, entry, ModelError)
    assert len(reads) == 2
    assert not (files.user_cache_dir() / "verified").exists()


def test_stamps_off_and_an_unwritable_cache(counted, monkeypatch, tmp_path):
    path, entry, reads = counted
    monkeypatch.setattr(files, "STAMP_MIN_AGE_S", 0.0)
    monkeypatch.setenv("MIFACERF_CHECKSUM_STAMPS", "0")
    for _ in range(2):
        files.check_entry(path, entry, ModelError)
    assert len(reads) == 2
    monkeypatch.delenv("MIFACERF_CHECKSUM_STAMPS")
    blocker = tmp_path / "not-a-folder"
    blocker.write_text("x")
    monkeypatch.setenv("MIFACERF_CACHE", str(blocker))        # the cache cannot be made: checks still run
    for _ in range(2):
        files.check_entry(path, entry, ModelError)
    assert len(reads) == 4


def test_a_stamp_is_for_one_checksum(stamped):
    """A manifest that expects other content is checked in full, even for a stamped file."""
    path, entry, reads = stamped
    with pytest.raises(ModelError, match="checksum mismatch"):
        files.check_entry(path, {**entry, "sha256": "0" * 64}, ModelError)
    assert len(reads) == 2
