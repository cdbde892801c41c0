"""One execution layer for the heavy stages: independent units on a dask.distributed cluster (ground floor).

A stage (``synth``, ``build``, ``compress``, ``drive``, ``evaluate render``, ``bench``) hands its
independent units — (expression, camera) images, fields, frames, cases, sweep points — to an
:class:`Executor`:

* :class:`Executor` itself runs every unit in this process, in order: today's single-process
  behaviour, no Dask at all (``--workers 1``, and the Python API's default);
* :class:`DaskExecutor` submits them to a ``dask.distributed`` cluster: by default a local cluster
  of worker processes sized to the machine (:func:`machine_workers`), or an existing scheduler
  (``--cluster tcp://HOST:8786`` or ``MIFACERF_CLUSTER``).

Both have the same three calls: :meth:`Executor.imap` (results in the units' order while the
cluster works ahead, at most ``window`` units in flight: the stage writes its outputs in order,
through the existing transactional writers of :mod:`mifacerf.formats.files`, exactly as one process
does), :meth:`Executor.map` (the list) and :meth:`Executor.graph` (units that wait for others).
A unit is ``fn(context, item)``: ``fn`` a module-level function (it is pickled by name), ``context``
what every unit shares (sent to each worker once), ``item`` the unit's own input. A worker keeps
what it loaded for a context (a model, a scene) in :func:`worker_cached`.

Workers read and write the folders at the same paths as this process (a shared filesystem); on
connecting, :func:`open_executor` checks that every worker sees the folders (:meth:`DaskExecutor.check_shared`,
naming the path on the worker that does not) and runs the same mifacerf version (refused otherwise,
both versions named). A worker killed mid-unit loses only that unit: the scheduler runs it again on
another worker (``distributed.scheduler.allowed-failures`` times), and since the stage's process
writes the outputs, nothing is half-written. docs/distributed.md has the measurements and how to
run a real cluster (``dask scheduler`` / ``dask worker``, dask-jobqueue on SLURM).

Import is light (Dask, NumPy and Mitsuba load inside the functions that use them).
"""
from __future__ import annotations

import os
import uuid
from collections import deque
from pathlib import Path

from .errors import MifacerfError

#: an existing scheduler's address (the default of ``--cluster``)
CLUSTER_ENV = "MIFACERF_CLUSTER"
#: the default of ``--workers`` (a count; 1 = one process, no Dask)
WORKERS_ENV = "MIFACERF_WORKERS"
#: seconds to wait for a scheduler to answer (and, with ``--workers N``, for its N workers)
CONNECT_TIMEOUT_S = 10.0


class ClusterError(MifacerfError):
    """The cluster cannot be used: no scheduler answers, a worker cannot see a folder, another version."""


def machine_workers() -> int:
    """The number of CPU cores this process may use (the local cluster's default size)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # macOS, Windows
        return max(1, os.cpu_count() or 1)


_worker_cache: dict = {}


def worker_cached(key, factory):
    """``factory()`` once per process for ``key`` (a model loaded by a worker, kept for its next units).

    ``key`` should change when the thing changes on disk (e.g. include the file's ``st_mtime_ns``)."""
    if key not in _worker_cache:
        if len(_worker_cache) >= 4:  # a long-lived worker serving several runs: keep the newest few
            _worker_cache.pop(next(iter(_worker_cache)))
        _worker_cache[key] = factory()
    return _worker_cache[key]


def _bar(progress: bool, total: int, desc: str | None, unit: str):
    from .progress import bar

    return bar(None, progress, total=total, desc=desc, unit=unit)


def _order(units: dict) -> list:
    """The keys of ``units`` ({key: (fn, context, item, deps)}) in an order where deps come first."""
    done, order = set(), []

    def visit(k, path=()):
        if k in done:
            return
        if k in path:
            raise ValueError(f"the units' dependencies form a cycle through {k!r}")
        if k not in units:
            raise KeyError(f"unit {path[-1]!r} waits for {k!r}, which is not a unit")
        for d in units[k][3]:
            visit(d, path + (k,))
        done.add(k)
        order.append(k)

    for k in units:
        visit(k)
    return order


class Executor:
    """Run every unit in this process, in order (``--workers 1``: today's behaviour, no Dask)."""

    distributed = False

    @property
    def workers(self) -> int:
        return 1

    def imap(self, fn, items, context=None, *, desc: str | None = None, unit: str = "unit",
             progress: bool = False, window: int | None = None):
        """``fn(context, item)`` for every item; yields the results in the items' order.

        ``progress``: a bar over the units (on a cluster: over the cluster's tasks as they finish);
        ``window``: at most this many units in flight on a cluster (default 4 per worker)."""
        items = list(items)
        b = _bar(progress, len(items), desc, unit)
        try:
            for item in items:
                result = fn(context, item)
                b.update(1)
                yield result
        finally:
            b.close()

    def map(self, fn, items, context=None, **options) -> list:
        """The list of :meth:`imap`'s results."""
        return list(self.imap(fn, items, context, **options))

    def graph(self, units: dict, *, desc: str | None = None, unit: str = "unit", progress: bool = False) -> dict:
        """Units that wait for others: ``{key: (fn, context, item, deps)}``, each called as
        ``fn(context, item, *results of deps)``; returns ``{key: result}``. Here: in an order where
        every unit comes after its dependencies (the order given where it allows)."""
        results = {}
        b = _bar(progress, len(units), desc, unit)
        try:
            for k in _order(units):
                fn, context, item, deps = units[k]
                results[k] = fn(context, item, *[results[d] for d in deps])
                b.update(1)
        finally:
            b.close()
        return results

    def check_shared(self, *paths) -> None:
        """Every worker sees ``paths`` (one process: nothing to check)."""

    def describe(self) -> str:
        return "one process"

    def close(self) -> None:
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class DaskExecutor(Executor):
    """Units on a ``dask.distributed`` cluster (``client``; ``cluster``: the local cluster it owns, or None)."""

    distributed = True

    def __init__(self, client, cluster=None, address: str | None = None):
        self.client, self.cluster, self.address = client, cluster, address

    @property
    def workers(self) -> int:
        return len(self.client.scheduler_info(n_workers=-1)["workers"])

    def describe(self) -> str:
        where = f"the scheduler at {self.address}" if self.address else "a local cluster"
        return f"{self.workers} worker(s) of {where}"

    def _scatter(self, context):
        return None if context is None else self.client.scatter(context, broadcast=False, hash=False)

    def imap(self, fn, items, context=None, *, desc: str | None = None, unit: str = "unit",
             progress: bool = False, window: int | None = None):
        items = list(items)
        window = max(1, window or 4 * max(1, self.workers))
        b = _bar(progress, len(items), desc, unit)
        tag = f"{desc or getattr(fn, '__name__', 'unit')}-{uuid.uuid4().hex[:8]}".replace(" ", "_")
        ctx = self._scatter(context)
        pending, todo = deque(), iter(enumerate(items))

        def submit():
            for i, item in todo:
                f = self.client.submit(fn, ctx, item, key=f"{tag}-{i}", pure=False)
                f.add_done_callback(lambda _: b.update(1))
                pending.append(f)
                return

        try:
            for _ in range(window):
                submit()
            while pending:
                f = pending.popleft()
                result = f.result()
                f.release()
                submit()
                yield result
        finally:
            for f in pending:
                f.cancel()
            b.close()

    def graph(self, units: dict, *, desc: str | None = None, unit: str = "unit", progress: bool = False) -> dict:
        b = _bar(progress, len(units), desc, unit)
        tag = f"{desc or 'graph'}-{uuid.uuid4().hex[:8]}".replace(" ", "_")
        contexts, futures = {}, {}
        try:
            for i, k in enumerate(_order(units)):
                fn, context, item, deps = units[k]
                if id(context) not in contexts:
                    contexts[id(context)] = self._scatter(context)
                f = self.client.submit(fn, contexts[id(context)], item, *[futures[d] for d in deps],
                                       key=f"{tag}-{i}", pure=False)
                f.add_done_callback(lambda _: b.update(1))
                futures[k] = f
            return {k: f.result() for k, f in futures.items()}
        finally:
            for f in futures.values():
                f.cancel()
            b.close()

    def check_versions(self) -> None:
        """Refuse workers that run another mifacerf version than this process (both named)."""
        __version__ = _worker_version()
        theirs = self.client.run(_worker_version)
        other = {a: v for a, v in theirs.items() if v != __version__}
        if other:
            addr, version = sorted(other.items())[0]
            raise ClusterError(f"worker {addr} runs mifacerf {version}, this process mifacerf {__version__}: "
                               f"refused ({len(other)} of {len(theirs)} worker(s) differ); install the same "
                               "mifacerf on every worker")

    def check_shared(self, *paths) -> None:
        """Every worker sees every folder of ``paths`` as this process does (its entries' names), or a
        :class:`ClusterError` naming the worker and the path on it."""
        for p in paths:
            if p is None:
                continue
            path = str(Path(p).resolve())
            mine = _folder_view(path)
            for addr, theirs in sorted(self.client.run(_folder_view, path).items()):
                if theirs != mine:
                    what = "no such folder" if theirs is None else "a different folder there (its files differ)"
                    raise ClusterError(f"worker {addr} cannot see the shared folder {path}: {what} on that worker; "
                                       "every worker must see the folders at the same path (a shared filesystem, "
                                       "docs/distributed.md)")

    def close(self) -> None:
        self.client.close()
        if self.cluster is not None:
            self.cluster.close()


def _worker_version() -> str:
    """This process's mifacerf version (the package root's, read by name: the root is the facade's floor)."""
    import importlib

    return importlib.import_module(__name__.rpartition(".")[0]).__version__


def _folder_view(path: str):
    """What a process sees at folder ``path``: None if no folder, else the sorted names of (up to 2000 of)
    its entries."""
    return None if not os.path.isdir(path) else sorted(os.listdir(path))[:2000]


def _worker_setup(threads: int) -> None:
    """On a worker: Dr.Jit's thread pool sized to the worker's share of the cores, and
    ``MIFACERF_WORKERS=1`` so that a unit never starts a cluster of its own."""
    os.environ[WORKERS_ENV] = "1"
    try:
        import drjit

        drjit.set_thread_count(threads)
    except Exception:  # noqa: BLE001 (no Dr.Jit on this worker: its units say so when they need it)
        pass


def local_cluster(workers: int):
    """(client, cluster): a ``distributed.LocalCluster`` of ``workers`` worker processes (one task at a
    time each; Dr.Jit gets cores / workers threads each) and its client."""
    import logging

    from distributed import Client, LocalCluster

    from distributed.diagnostics.plugin import WorkerPlugin

    class Setup(WorkerPlugin):  # defined here (Dask is imported only when a cluster starts); sent by value
        name = "mifacerf-setup"

        def __init__(self, threads):
            self.threads = threads

        def setup(self, worker):
            _worker_setup(self.threads)

    cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=":0",
                           silence_logs=logging.ERROR, env={WORKERS_ENV: "1"})
    client = Client(cluster)
    client.register_plugin(Setup(max(1, machine_workers() // workers)))
    return client, cluster


def connect(address: str, workers: int | None = None, timeout: float = CONNECT_TIMEOUT_S):
    """A client of the scheduler at ``address``; a :class:`ClusterError` naming it after ``timeout`` seconds
    (also when ``workers`` workers have not joined by then)."""
    from distributed import Client

    try:
        client = Client(address, timeout=timeout, set_as_default=False)
    except (OSError, TimeoutError, ValueError) as exc:
        raise ClusterError(f"no Dask scheduler answers at {address} (waited {timeout:g} s: {exc}); start one "
                           "with 'dask scheduler' and 'dask worker ADDRESS', or fix --cluster / "
                           f"{CLUSTER_ENV}") from None
    try:
        client.wait_for_workers(max(1, workers or 1), timeout=timeout)
    except (OSError, TimeoutError) as exc:
        n = len(client.scheduler_info(n_workers=-1)["workers"])
        client.close()
        raise ClusterError(f"the scheduler at {address} has {n} worker(s), {workers or 1} wanted (waited "
                           f"{timeout:g} s: {type(exc).__name__}); start them with 'dask worker {address}'") from None
    return client


def open_executor(workers: int | None = None, cluster: str | None = None, shared=(),
                  timeout: float = CONNECT_TIMEOUT_S) -> Executor:
    """The executor of a command: ``workers`` 1 → one process (no Dask); ``cluster`` (default
    ``MIFACERF_CLUSTER``) an existing scheduler's address; otherwise a local cluster of ``workers``
    (default ``MIFACERF_WORKERS``, else :func:`machine_workers`) processes. ``shared``: folders every
    worker must see (checked, as is the mifacerf version). Use it as a context manager (closes the
    client and a local cluster)."""
    if workers is None and cluster is None and os.environ.get(WORKERS_ENV, "").strip():  # an explicit cluster wins
        try:
            workers = int(os.environ[WORKERS_ENV])
        except ValueError:
            raise ClusterError(f"{WORKERS_ENV}={os.environ[WORKERS_ENV]!r} is not a number of workers") from None
        if workers < 1:
            raise ClusterError(f"{WORKERS_ENV}={workers}: at least 1 worker")
    cluster = cluster or os.environ.get(CLUSTER_ENV) or None
    if workers == 1:
        return Executor()
    if cluster is None:
        n = workers or machine_workers()
        if n <= 1:
            return Executor()
        ex = DaskExecutor(*local_cluster(n))
    else:
        ex = DaskExecutor(connect(cluster, workers, timeout), address=cluster)
    try:
        ex.check_versions()
        ex.check_shared(*shared)
    except BaseException:
        ex.close()
        raise
    return ex


def executor_options(command):
    """Decorate a click command with ``--workers`` and ``--cluster`` (its function takes them as keywords)."""
    import click

    command = click.option(
        "--cluster", default=None, metavar="tcp://HOST:8786",
        help=f"Submit the units to the Dask scheduler at this address (default: ${CLUSTER_ENV}, else a local "
             "cluster); every worker must see the folders at the same paths.")(command)
    return click.option(
        "--workers", type=click.IntRange(min=1), default=None,
        help=f"Worker processes of the local cluster (default: ${WORKERS_ENV}, else one per core); 1 = this "
             "process alone, no Dask.")(command)
