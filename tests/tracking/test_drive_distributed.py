"""drive on a local cluster of 2 worker processes writes the same files as one process, also when a worker
is killed (SIGKILL) mid-run (issue 20)."""
import json
import os
import signal

import numpy as np
import pytest

from mifacerf.execution import open_executor
from mifacerf.tracking.drive import FrameObserver, drive

FRAMES = (8, 20)
OPTIONS = dict(envs=("sky",), size=48, spp=2, frames=FRAMES, progress=False)


@pytest.fixture(scope="module")
def cluster():
    with open_executor(2) as ex:
        yield ex


@pytest.fixture(scope="module")
def one_process(world, tmp_path_factory):
    return drive(world["track"], world["model"], tmp_path_factory.mktemp("drive1"), **OPTIONS)


def outputs(folder):
    """{relative path: bytes} of every file but drive.json, and drive.json without its timings."""
    files = {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*"))
             if p.is_file() and p.name != "drive.json"}
    meta = json.loads((folder / "drive.json").read_text())
    meta.pop("track"), meta["weights"].pop("seconds_per_frame")
    for e in meta["environments"].values():
        e.pop("render_seconds_per_frame"), e.pop("write_seconds_per_frame")
    return files, meta


def assert_same(a, b):
    fa, ma = outputs(a)
    fb, mb = outputs(b)
    assert sorted(fa) == sorted(fb)
    differ = [k for k in fa if fa[k] != fb[k]]
    assert not differ, f"files differ: {differ}"
    assert ma == mb


@pytest.mark.slow
def test_two_workers_write_the_same_files(world, one_process, cluster, tmp_path):
    out = drive(world["track"], world["model"], tmp_path / "d2", executor=cluster, **OPTIONS)
    n = FRAMES[1] - FRAMES[0]
    assert len(list((out / "sky" / "frames").glob("F*.exr"))) == n
    assert_same(one_process, out)    # bitwise: every PNG, EXR, the weights, the mp4


class KillAWorker(FrameObserver):
    """Kills one worker process (SIGKILL) when the second frame comes back."""

    def __init__(self, client):
        self.client, self.killed = client, None

    def frame(self, f, rgba, plate, picked):
        if f == FRAMES[0] + 1 and self.killed is None:
            pids = self.client.run(os.getpid)
            self.killed = sorted(pids.values())[0]
            os.kill(self.killed, signal.SIGKILL)
        return None


@pytest.mark.slow
def test_a_worker_killed_mid_run(world, one_process, cluster, tmp_path):
    killer = KillAWorker(cluster.client)
    out = drive(world["track"], world["model"], tmp_path / "dk", executor=cluster, observer=killer, **OPTIONS)
    assert killer.killed is not None
    assert_same(one_process, out)    # its frames re-rendered on the other worker; nothing missing or torn
    assert not [p for p in out.rglob("*") if ".tmp" in p.name]
    cluster.client.wait_for_workers(2, timeout=120)
    assert killer.killed not in cluster.client.run(os.getpid).values()
    np.testing.assert_array_equal(np.load(out / "weights.npz")["weights"], np.load(one_process / "weights.npz")["weights"])


@pytest.mark.slow
def test_a_compressed_drive_is_lit_by_its_method_on_the_workers_too(world, one_process, cluster, tmp_path):
    """``drive(method="sh", rank=2)``: the workers light the frames by the same compressed copy (the same files
    as one process, bitwise), not the exact fields (its frames differ from the exact drive's, a little);
    drive.json says which; a rank the model does not hold is one error naming the command that writes it."""
    import shutil

    import imageio.v2 as iio

    from mifacerf.rendering.compression import compress_model
    from mifacerf.rendering.model import Model

    shutil.copytree(world["model"], tmp_path / "model")
    compress_model(Model(tmp_path / "model"), 2, progress=False, method="sh")
    one = drive(world["track"], tmp_path / "model", tmp_path / "s1", method="sh", rank=2, **OPTIONS)
    two = drive(world["track"], tmp_path / "model", tmp_path / "s2", executor=cluster, method="sh", rank=2, **OPTIONS)
    assert_same(one, two)
    assert json.loads((one / "drive.json").read_text())["method"] == {"name": "sh", "rank": 2}
    assert json.loads((one_process / "drive.json").read_text())["method"] == {"name": "exact", "rank": None}
    name = sorted(p.name for p in (one / "sky" / "frames").glob("*.png"))[3]
    a = iio.imread(one / "sky" / "frames" / name).astype(float)
    b = iio.imread(one_process / "sky" / "frames" / name).astype(float)
    mse = ((a - b) ** 2).mean()
    assert 0 < mse and 10 * np.log10(255 ** 2 / mse) > 25
    with pytest.raises(ValueError, match=r"mifacerf compress .* --method sh --rank 3"):
        drive(world["track"], tmp_path / "model", tmp_path / "s3", method="sh", rank=3, **OPTIONS)
    assert not (tmp_path / "s3").exists()
    with pytest.raises(ValueError, match="unknown compression method"):
        drive(world["track"], tmp_path / "model", tmp_path / "s4", method="svd", rank=3, **OPTIONS)
