"""Helpers of the capture tests: tiny rigs, simulated labs, sessions (all seconds-cheap), and the strobe
controller's recorded transcript (tests/capture/data/transcript_olat.jsonl)."""
from mifacerf.capture.expressions import session_expressions
from mifacerf.capture.hardware.controller import StrobeController
from mifacerf.capture.motion import MotionCheck
from mifacerf.capture.session import CaptureSession, SessionConfig
from mifacerf.capture.simulation.lab import LabOptions, SimulatedLab
from mifacerf.rig import CAMERA_LAYOUTS, LightStage, Rig, camera_ring


def tiny_rig(n_positions=4, n_strobes=4, n_cameras=2, resolution=40, irradiance_spread=0.05):
    layout = CAMERA_LAYOUTS[3][:n_cameras] if n_cameras <= 3 else CAMERA_LAYOUTS[6][:n_cameras]
    lights = LightStage.semicircular_arm(n_positions, n_strobes, irradiance_spread=irradiance_spread, seed=7)
    return Rig(lights, camera_ring(layout, width=resolution, height=resolution))


def new_session(root, rig, n_expressions=2, sample=8, **config):
    cfg = SessionConfig(motion=MotionCheck(sample=sample), reconnect_wait_s=0.01, **config)
    return CaptureSession.create(root, rig, session_expressions(n_expressions), config=cfg)


def run_lab(session, options=None, *, pty=False, timeout=0.05, retries=4, hook=None):
    """Run ``session`` against a fresh simulated lab; returns (report, lab). ``hook(session, lab)``
    may modify things before the run (fault injection)."""
    lab = SimulatedLab(session.rig, [e.name for e in session.expressions], options or LabOptions(), pty=pty)
    port = lab.start()
    try:
        if hook is not None:
            hook(session, lab)
        with StrobeController(port, timeout=timeout, retries=retries) as ctl:
            rep = session.run(ctl, lab.cameras, lab.operator)
    finally:
        lab.stop()
    return rep, lab


def scripted_exchange(ctl, lights=(0, 1, 2, 5, 6, 7)):
    """The command script of the recorded transcript (tests/capture/data/transcript_olat.jsonl)."""
    from mifacerf.capture.hardware.sequence import olat_sequence

    info = ctl.hello()
    ctl.status()
    ctl.rotate(1)
    seq = olat_sequence(info.n_positions, info.n_strobes, list(lights))
    ctl.load(seq)
    res = ctl.run(seq)
    ctl.status()
    return res


def record_transcript(path):
    """Regenerate the golden transcript: ``python tests/helpers/capture.py``."""
    from mifacerf.capture.hardware.controller import StrobeController
    from mifacerf.capture.simulation.device import Faults, SimulatedStrobeController
    from mifacerf.capture.simulation.transport import RecordingPort, SimulatedPort

    dev = SimulatedStrobeController(4, 4, 2, Faults(drop=0.15, garble=0.1, noise=0.1, misfire=0.1, seed=11))
    port = RecordingPort(SimulatedPort(dev))
    ctl = StrobeController(port, timeout=0.05, rotate_s=0.0)
    res = scripted_exchange(ctl)
    port.save(path)
    return res, ctl.stats


if __name__ == "__main__":
    import pathlib

    out = pathlib.Path(__file__).parents[1] / "capture" / "data" / "transcript_olat.jsonl"
    res, stats = record_transcript(out)
    print(f"wrote {out}: {len(res.events)} events, {stats}")


def tiny_capture_without_truth(root, expressions):
    """The ``tiny`` synthetic capture of ``expressions`` in ``root/synth``, its truth moved out of reach to
    ``root/hidden-truth`` (what a stage under test must never read); returns (capture folder, truth folder)."""
    import shutil

    from mifacerf.synthetic.synth import synthesize

    cap = synthesize(root / "synth", preset="tiny", expressions=expressions, progress=False)
    truth = root / "hidden-truth"
    shutil.move(str(root / "synth" / "truth"), truth)
    return cap, truth
