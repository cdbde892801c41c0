"""The execution layer (mifacerf/execution.py): one process, a local cluster of 2 worker processes, bad clusters.

The stages' distributed runs (identical outputs, a worker killed mid-run) are tested with their stages
(tests/tracking/test_drive_distributed.py, ...); here the layer itself.
"""
import os
import signal
import time

import pytest

from mifacerf.execution import ClusterError, DaskExecutor, Executor, open_executor


def square(context, x):
    return (context or 0) + x * x


def plus(context, item, *deps):
    return item + sum(deps)


def slow_pid(context, x):
    time.sleep(context)
    return x, os.getpid()


@pytest.fixture(scope="module")
def two_workers():
    ex = open_executor(2)
    assert isinstance(ex, DaskExecutor) and ex.workers == 2
    yield ex
    ex.close()


def test_one_worker_is_this_process_without_dask(monkeypatch):
    monkeypatch.delenv("MIFACERF_CLUSTER", raising=False)
    ex = open_executor(1)
    assert type(ex) is Executor and not ex.distributed
    assert ex.map(square, [3, 1, 2], 10) == [19, 11, 14]
    monkeypatch.setenv("MIFACERF_WORKERS", "1")
    assert type(open_executor()) is Executor
    monkeypatch.setenv("MIFACERF_WORKERS", "zero")
    with pytest.raises(ClusterError, match="MIFACERF_WORKERS"):
        open_executor()


def test_graph_runs_dependencies_first():
    order = []

    def f(context, item, *deps):
        order.append(item)
        return item + sum(deps)

    units = {"c": (f, None, 3, ("a", "b")), "a": (f, None, 1, ()), "b": (f, None, 2, ("a",))}
    assert Executor().graph(units) == {"a": 1, "b": 3, "c": 7} and order == [1, 2, 3]
    with pytest.raises(ValueError, match="cycle"):
        Executor().graph({"a": (f, None, 1, ("b",)), "b": (f, None, 2, ("a",))})


def test_cluster_gives_the_same_results_in_order(two_workers):
    items = list(range(20))
    assert two_workers.map(square, items, 5) == Executor().map(square, items, 5)
    units = {"c": (plus, None, 3, ("a", "b")), "a": (plus, None, 1, ()), "b": (plus, None, 2, ("a",))}
    assert two_workers.graph(units) == Executor().graph(units)
    pids = {pid for _, pid in two_workers.map(slow_pid, range(6), 0.3)}
    assert len(pids) == 2 and os.getpid() not in pids     # both workers, neither is this process


def test_a_killed_worker_loses_nothing(two_workers):
    """SIGKILL one worker while it runs a unit: its units run again on the other, every result comes back."""
    it = two_workers.imap(slow_pid, range(8), 1.0, window=8)
    first = next(it)
    time.sleep(0.3)   # the next units are running on both workers
    victim = next(pid for pid in two_workers.client.run(os.getpid).values() if pid != first[1])
    os.kill(victim, signal.SIGKILL)
    rest = list(it)
    assert [x for x, _ in [first] + rest] == list(range(8))
    # the nanny restarts the killed worker
    two_workers.client.wait_for_workers(2, timeout=60)


def test_unreachable_scheduler_is_one_clear_line_after_the_timeout():
    t0 = time.perf_counter()
    with pytest.raises(ClusterError, match=r"no Dask scheduler answers at tcp://127\.0\.0\.1:9 \(waited 2 s"):
        open_executor(cluster="tcp://127.0.0.1:9", timeout=2)
    assert time.perf_counter() - t0 < 30


def test_a_worker_with_another_version_is_refused(two_workers):
    addr = sorted(two_workers.client.scheduler_info()["workers"])[0]
    two_workers.client.run(_set_version, "0.0.1-other", workers=[addr])
    try:
        with pytest.raises(ClusterError, match=rf"worker {addr} runs mifacerf 0\.0\.1-other, this process mifacerf "):
            two_workers.check_versions()
    finally:
        two_workers.client.run(_set_version, None, workers=[addr])
    two_workers.check_versions()


def test_a_worker_that_cannot_see_the_folder_is_named(two_workers, tmp_path):
    (tmp_path / "a.txt").write_text("x")
    two_workers.check_shared(tmp_path)
    addr = sorted(two_workers.client.scheduler_info()["workers"])[-1]
    two_workers.client.run(_hide, str(tmp_path), workers=[addr])
    try:
        with pytest.raises(ClusterError, match=rf"worker {addr} cannot see the shared folder {tmp_path}: no such "
                                               "folder on that worker"):
            two_workers.check_shared(tmp_path)
    finally:
        two_workers.client.run(_hide, None, workers=[addr])


_original = {}


def _set_version(version):
    import mifacerf

    _original.setdefault("version", mifacerf.__version__)
    mifacerf.__version__ = version or _original["version"]


def _hide(path):
    """On a worker: pretend folder ``path`` is not there (None: see everything again)."""
    import mifacerf.execution as ex

    real = _original.setdefault("view", ex._folder_view)
    ex._folder_view = real if path is None else (lambda p: None if p == path else real(p))


def test_a_command_names_the_unreachable_scheduler_in_one_line(tmp_path):
    from click.testing import CliRunner

    from mifacerf.cli import main

    r = CliRunner().invoke(main, ["synth", str(tmp_path / "o"), "--preset", "tiny", "--cluster", "tcp://127.0.0.1:9"])
    assert r.exit_code == 1, r.output
    lines = [x for x in r.output.splitlines() if x.strip()]
    assert lines[0].startswith("mifacerf synth: error: no Dask scheduler answers at tcp://127.0.0.1:9 (waited 10 s")
    assert "Traceback" not in r.output and not (tmp_path / "o" / "capture").exists()
