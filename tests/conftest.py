"""Shared test fixtures. Tests use tiny rigs and images so the suite stays fast on 2 cores."""
import os

import numpy as np
import pytest

# Generated data (environments, the synthetic subject's atlas) is cached per test session.
os.environ.setdefault("MIFACERF_CACHE", os.path.join(os.path.dirname(__file__), "..", ".cache-tests"))
# Commands run in the test process (no local cluster per CLI test); tests/test_execution.py and the
# *_distributed tests start their own 2-worker clusters.
os.environ.setdefault("MIFACERF_WORKERS", "1")


# Fixtures that take more than ~20 s to build on the 2-core CI machine. Every test that needs one (directly
# or through another fixture) must be marked slow, so that `pytest -m "not slow"` stays quick.
SLOW_FIXTURES = {"tiny", "built_root", "toy_capture", "world"}


# Session fixtures that cost nothing to make twice (they do not tie their tests to one worker).
CHEAP_SESSION_FIXTURES = {"mi", "tmp_path_factory", "worker_id", "testrun_uid"}


def _xdist_groups(items) -> dict:
    """{test: group}: tests that share a session-scoped fixture (directly or through another fixture) are one
    group — the components of "shares a session fixture" — so that under ``pytest -n`` (pytest-xdist, ``--dist
    loadgroup``) each such fixture is built by one worker only; a test with none is its own module's group."""
    parent: dict = {}

    def find(x):
        while parent.setdefault(x, x) != x:
            parent[x] = x = parent[parent[x]]
        return x

    uses = {}
    for item in items:
        defs = getattr(getattr(item, "_fixtureinfo", None), "name2fixturedefs", {}) or {}
        ids = [f"{d[-1].baseid}::{name}" for name, d in defs.items()
               if d and d[-1].scope == "session" and name not in CHEAP_SESSION_FIXTURES]
        uses[item] = ids or [item.nodeid.split("::")[0]]
        for other in uses[item][1:]:
            parent[find(other)] = find(uses[item][0])
    return {item: find(ids[0]) for item, ids in uses.items()}


@pytest.hookimpl(tryfirst=True)      # the groups are marked before xdist's worker reads them
def pytest_collection_modifyitems(config, items):
    if config.pluginmanager.hasplugin("xdist"):
        for item, group in _xdist_groups(items).items():
            item.add_marker(pytest.mark.xdist_group(group))
    unmarked = [item.nodeid for item in items if SLOW_FIXTURES & set(getattr(item, "fixturenames", ()))
                and item.get_closest_marker("slow") is None]
    if unmarked:
        raise pytest.UsageError("these tests need a slow fixture (%s) but are not marked @pytest.mark.slow: %s"
                                % (", ".join(sorted(SLOW_FIXTURES)), ", ".join(unmarked)))


@pytest.fixture(scope="session")
def mi():
    from mifacerf.variant import ensure_variant

    return ensure_variant()


@pytest.fixture
def rng():
    return np.random.default_rng(1234)


def pytest_collection_finish(session):
    """On an xdist worker under ``--dist loadgroup``: the groups took effect (xdist marks them by suffixing the
    node ids with ``@group``; with pytest 9.2 that silently stopped working, pytest-dev/pytest-xdist#1386, and
    every worker built every fixture) — else a usage error rather than a silently slower suite."""
    if os.environ.get("PYTEST_XDIST_WORKER") and session.config.getvalue("loadgroup") and session.items:
        if "@" not in session.items[0].nodeid:
            import xdist

            raise pytest.UsageError(f"pytest-xdist {xdist.__version__} does not group the tests under pytest "
                                    f"{pytest.__version__} (pytest-dev/pytest-xdist#1386): install pytest<9.2 "
                                    "(pyproject.toml's test extra pins it) or run with -n 0")
