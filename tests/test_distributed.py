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
    assert_same_files(root / "one" / "truth", root / "two" / "truth")


@pytest.mark.slow
def test_synth_survives_a_killed_worker(synths, cluster, tmp_path):
    """SIGKILL one worker while the takes render and write: its takes run again on the other worker; the capture is
    byte-identical to the one-process capture and no temporary file is left (nothing half-written)."""
    import os
    import signal
    import threading

    from mifacerf.synthetic.synth import synthesize

    root, one, _ = synths
    out = tmp_path / "killed"
    killed = []

    def kill_when_images_appear():
        for _ in range(1200):
            if len(list((out / "capture").glob("images/*/*/*.exr"))) >= 30:
                pid = sorted(cluster.client.run(os.getpid).values())[0]
                os.kill(pid, signal.SIGKILL)
                killed.append(pid)
                return
            threading.Event().wait(0.1)

    t = threading.Thread(target=kill_when_images_appear, daemon=True)
    t.start()
    cap = synthesize(out, preset="tiny", expressions=EXPRESSIONS, progress=False, rig=small_rig(), executor=cluster)
    t.join(5)
    assert killed, "no worker was killed (the capture was written before the images appeared?)"
    assert_same_files(one, cap)
    assert not [p for p in cap.rglob("*") if ".tmp" in p.name]
    cluster.client.wait_for_workers(2, timeout=120)


@pytest.fixture(scope="module")
def model(synths):
    from helpers.tracking import write_truth_registration
    from mifacerf.rendering.build import build_model

    root, one, _ = synths
    reg = write_truth_registration(root / "one")
    return build_model(one, root / "model", registration=reg, progress=False).parent


@pytest.mark.slow
def test_build_on_two_workers_writes_the_same_model(synths, model, cluster, tmp_path):
    from mifacerf.rendering.build import build_model

    root, one, _ = synths
    two = build_model(one, tmp_path / "model", registration=root / "one" / "truth_registration", progress=False,
                      executor=cluster).parent
    assert_same_files(model, two)    # every field's texels and rf, geometry, blend, parts, model.json


@pytest.mark.slow
def test_compress_on_two_workers_writes_the_same_fields(model, cluster, tmp_path):
    import shutil

    from mifacerf.rendering.compression import compress_model
    from mifacerf.rendering.model import Model

    a, b = shutil.copytree(model, tmp_path / "a"), shutil.copytree(model, tmp_path / "b")
    ia = compress_model(Model(a), [2, 4], progress=False)
    ib = compress_model(Model(b), [2, 4], progress=False, executor=cluster)
    assert ia == ib and ia["fields"] == 9
    assert_same_files(a, b)    # every .pca<k>.npz and model.json


@pytest.mark.slow
def test_evaluate_on_two_workers_gives_the_same_report(synths, model, cluster, tmp_path):
    from mifacerf.evaluation.render_cases import evaluate

    root = synths[0]
    options = dict(envs=("gradient",), n=1, seed=5, spp_truth=8, size=32, progress=False)
    ra = evaluate(root / "one", model, pictures=tmp_path / "a.png", **options)
    rb = evaluate(root / "one", model, pictures=tmp_path / "b.png", executor=cluster, **options)
    untimed = lambda r: json.dumps([{k: v for k, v in c.items() if k not in ("seconds", "stages")}  # noqa: E731
                                    for c in r["cases"]], sort_keys=True)
    assert len(ra["cases"]) == 4 and untimed(ra) == untimed(rb)
    assert (tmp_path / "a.png").read_bytes() == (tmp_path / "b.png").read_bytes()
