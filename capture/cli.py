"""``mifacerf capture`` and ``mifacerf calibrate …``: the light stage's command line.

Heavy imports live inside the commands so ``mifacerf --help`` stays fast.
Exit codes: 0 done; 1 error; 2 bad usage; 3 session interrupted (resumable).
"""
from __future__ import annotations

import json
import os
from pathlib import Path

import click

EXIT_INTERRUPTED = 3


class Interrupted(click.ClickException):
    exit_code = EXIT_INTERRUPTED


def _echo(msg: str) -> None:
    click.echo(msg, err=True)


# ------------------------------------------------------------------------------------ capture
@click.command("capture", context_settings={"help_option_names": ["-h", "--help"]})
@click.argument("out", type=click.Path(file_okay=False, path_type=Path))
@click.option("--simulate", is_flag=True, help="Simulated controller (over a pseudo-terminal), cameras and subject.")
@click.option("--resume", is_flag=True, help="Continue the session in OUT exactly where it stopped.")
@click.option("--port", help="Strobe controller port: a device or any pyserial URL (loop://, socket://host:port, ...).")
@click.option("--cameras", "camera_backend", default=None,
              help="Camera backend name (real cameras register via the 'mifacerf.camera_backends' entry points).")
@click.option("--preset", default="tiny", show_default=True, help="Rig size: tiny, draft or paper (mifacerf.rig).")
@click.option("--positions", type=int, help="Override the preset's arm positions.")
@click.option("--strobes", type=int, help="Override the preset's strobes per arm.")
@click.option("--resolution", type=int, help="Override the preset's image size (pixels).")
@click.option("--expressions", "n_expressions", type=int, help="First N of the paper's 60 expressions "
              "(default: the preset's count).")
@click.option("--radiometry", "radiometry_file", type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="Radiometric calibration (from `mifacerf calibrate response`) recorded in the manifest.")
@click.option("--max-takes", type=int, default=5, show_default=True, help="Takes per expression before giving up.")
@click.option("--motion-threshold", type=float, default=0.7, show_default=True,
              help="A take is blurred when its sum's sharpness falls below this fraction of the reference.")
@click.option("--motion-sample", type=int, default=32, show_default=True, help="Frames summed for the motion check.")
@click.option("--timeout", type=float, default=0.5, show_default=True, help="Seconds to wait for each reply.")
@click.option("--retries", type=int, default=4, show_default=True, help="Re-sends of an unanswered command.")
@click.option("--renderer", type=click.Choice(["procedural", "synthetic"]), default="procedural", show_default=True,
              help="[simulate] What the synthetic cameras render.")
@click.option("--fault-rate", type=float, default=0.0, show_default=True,
              help="[simulate] Link faults per frame (drop, garble, noise), strobe misfires (rate/4 per flash), "
                   "controller resets (4 x rate per run).")
@click.option("--frame-drop", type=float, default=0.0, show_default=True, help="[simulate] Camera frames lost.")
@click.option("--motion-rate", type=float, default=0.0, show_default=True, help="[simulate] Takes where the subject moves.")
@click.option("--motion-mm", type=float, default=8.0, show_default=True, help="[simulate] How far a moving subject drifts.")
@click.option("--sensor", type=click.Choice(["ideal", "realistic"]), default="ideal", show_default=True,
              help="[simulate] Camera sensor model (realistic: response curve, colour crosstalk, noise).")
@click.option("--realtime", is_flag=True, help="[simulate] Run the controller at the real 60 Hz.")
@click.option("--seed", type=int, default=0, show_default=True, help="[simulate] Random seed.")
@click.option("--crash-after-frames", type=int, hidden=True,
              help="Testing: kill the process (no clean-up) after writing this many frames.")
def capture_cmd(out, simulate, resume, port, camera_backend, preset, positions, strobes, resolution, n_expressions,
                radiometry_file, max_takes, motion_threshold, motion_sample, timeout, retries, renderer, fault_rate,
                frame_drop, motion_rate, motion_mm, sensor, realtime, seed, crash_after_frames):
    """Run a light-stage capture session into the folder OUT (paper §2.1).

    Per expression: the subject holds it, every light fires once while all cameras
    record, the sum of a sample of frames is checked for subject motion and a blurred
    take is repeated. Images are written atomically with sha256 checksums in an
    append-only journal (OUT/session.jsonl); the manifest is written last. An
    interrupted session (Ctrl-C, a silent controller, a full disk) resumes exactly
    where it stopped with --resume.
    """
    from mifacerf.capture.hardware.controller import ControllerError, PortError, StrobeController
    from mifacerf.capture.session import CaptureSession, SessionConfig, SessionError, SessionInterrupted
    from mifacerf.capture.motion import MotionCheck

    if resume:
        try:
            session = CaptureSession.open(out)
        except SessionError as exc:
            raise click.ClickException(str(exc)) from exc
        if session.state.finished and (out / "manifest.json").exists():
            _echo(f"{out}: the capture is already complete")
            return
        sim_opts = session.plan.get("simulation")
        if simulate and sim_opts is None:
            raise click.UsageError("this session was recorded with real hardware; resume it without --simulate")
        simulate = sim_opts is not None
    else:
        session = _new_session(out, simulate, preset, positions, strobes, resolution, n_expressions, radiometry_file,
                               SessionConfig(max_takes=max_takes, motion=MotionCheck(motion_sample, "laplacian",
                                                                                     motion_threshold)),
                               dict(renderer=renderer, fault_rate=fault_rate, frame_drop=frame_drop,
                                    motion_rate=motion_rate, motion_mm=motion_mm, sensor=sensor,
                                    time_scale=1.0 if realtime else 0.0, seed=seed))
    if crash_after_frames is not None:
        _arm_crash(session, crash_after_frames)

    lab = None
    try:
        if simulate:
            from mifacerf.capture.simulation.lab import LabOptions, SimulatedLab

            opts = LabOptions.from_dict(session.plan["simulation"])
            if resume:  # a resumed simulation is a new day: new random faults, same subject
                opts.seed = opts.seed + 1000 * (1 + session.report().resumes)
            lab = SimulatedLab(session.rig, [e.name for e in session.expressions], opts, pty=True)
            port = lab.start()
            cameras, operator = lab.cameras, lab.operator
            _echo(f"simulated strobe controller on {port}")
        else:
            if not port:
                raise click.UsageError("--port is required without --simulate")
            if not camera_backend:
                raise click.UsageError("--cameras BACKEND is required without --simulate")
            from mifacerf.capture.hardware.cameras import CameraError, camera_backend as make_backend

            try:
                cameras = make_backend(camera_backend, rig=session.rig)
            except CameraError as exc:
                raise click.ClickException(str(exc)) from exc
            operator = _ConsoleOperator()
        try:
            controller = StrobeController(port, timeout=timeout, retries=retries)
        except PortError as exc:
            raise Interrupted(f"{exc}\nThe session in {out} is saved; resume with `mifacerf capture {out} --resume`.")
        with controller:
            try:
                rep = session.run(controller, cameras, operator, progress=_echo)
            except SessionInterrupted as exc:
                raise Interrupted(str(exc)) from exc
            except (SessionError, ControllerError) as exc:
                raise click.ClickException(str(exc)) from exc
    finally:
        if lab is not None:
            lab.stop()
    click.echo(json.dumps(rep.to_dict(), indent=1))


def _new_session(out, simulate, preset_name, positions, strobes, resolution, n_expressions, radiometry_file, config,
                 sim_opts):
    from mifacerf.capture.expressions import session_expressions
    from mifacerf.capture.session import CaptureSession, SessionError
    from mifacerf.capture_folder import Radiometry
    from mifacerf.rig import LightStage, Rig, camera_ring, CAMERA_LAYOUTS, preset

    try:
        p = preset(preset_name)
    except ValueError as exc:
        raise click.BadParameter(str(exc), param_hint="--preset") from exc
    res = resolution or p.resolution
    lights = LightStage.semicircular_arm(positions or p.n_positions, strobes or p.n_strobes, irradiance_spread=0.05,
                                         seed=7)
    rig = Rig(lights, camera_ring(CAMERA_LAYOUTS[p.n_cameras], width=res, height=res))
    try:
        exprs = session_expressions(n_expressions or p.n_expressions)
    except ValueError as exc:
        raise click.BadParameter(str(exc), param_hint="--expressions") from exc
    radiometry, extra = None, {}
    if radiometry_file is not None:
        data = json.loads(radiometry_file.read_text())
        radiometry = {k: Radiometry.from_dict(v) for k, v in data["cameras"].items()}
        missing = set(c.name for c in rig.cameras) - set(radiometry)
        if missing:
            raise click.BadParameter(f"no calibration for cameras {sorted(missing)}", param_hint="--radiometry")
        extra["radiometric_calibration"] = {k: v for k, v in data.items() if k != "cameras"}
    if simulate:
        extra["simulation"] = sim_opts
    try:
        return CaptureSession.create(out, rig, exprs, config=config, radiometry=radiometry, extra=extra)
    except SessionError as exc:
        raise click.ClickException(str(exc)) from exc


def _arm_crash(session, n: int) -> None:
    inner = session.write_image
    count = [0]

    def write(path, image):
        inner(path, image)
        count[0] += 1
        if count[0] >= n:
            os._exit(70)  # like a power cut: no clean-up, no journal record

    session.write_image = write


class _ConsoleOperator:
    def prompt(self, expression, take: int, sitting: int) -> None:
        click.prompt(f"Subject: hold '{expression.name}' ({expression.category}), take {take}. Press Enter to fire",
                     default="", show_default=False, err=True)

    def say(self, message: str) -> None:
        _echo(message)


# ---------------------------------------------------------------------------------- calibrate
@click.group("calibrate", context_settings={"help_option_names": ["-h", "--help"]})
def calibrate_group():
    """Geometric (Zhang) and radiometric (response, colour) calibration of the cameras (paper §2.1)."""
