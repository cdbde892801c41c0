"""``mifacerf capture`` and ``mifacerf calibrate …``: the light stage's command line.

Heavy imports live inside the commands so ``mifacerf --help`` stays fast.
Exit codes: 0 done; 1 error; 2 bad usage; 3 session interrupted (resumable).
"""
from __future__ import annotations

import json
import os
from pathlib import Path

import click

from .calibration.radiometric import DEFAULT_RESPONSE_METHOD, RESPONSE_METHODS

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
@click.option("--positions", type=click.IntRange(min=1), help="Override the preset's arm positions.")
@click.option("--strobes", type=click.IntRange(min=1), help="Override the preset's strobes per arm.")
@click.option("--resolution", type=click.IntRange(min=1), help="Override the preset's image size (pixels).")
@click.option("--expressions", "n_expressions", type=click.IntRange(min=1), help="First N of the paper's 60 expressions "
              "(default: the preset's count).")
@click.option("--radiometry", "radiometry_file", type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="Radiometric calibration (from `mifacerf calibrate response`) recorded in the manifest.")
@click.option("--max-takes", type=click.IntRange(min=1), default=5, show_default=True, help="Takes per expression before giving up.")
@click.option("--motion-threshold", type=click.FloatRange(0, 1), default=0.7, show_default=True,
              help="A take is blurred when its sum's sharpness falls below this fraction of the reference.")
@click.option("--motion-sample", type=click.IntRange(min=1), default=32, show_default=True, help="Frames summed for the motion check.")
@click.option("--timeout", type=click.FloatRange(min=0, min_open=True), default=0.5, show_default=True, help="Seconds to wait for each reply.")
@click.option("--retries", type=click.IntRange(min=0), default=4, show_default=True, help="Re-sends of an unanswered command.")
@click.option("--renderer", type=click.Choice(["procedural", "synthetic"]), default="procedural", show_default=True,
              help="[simulate] What the synthetic cameras render.")
@click.option("--fault-rate", type=click.FloatRange(0, 1), default=0.0, show_default=True,
              help="[simulate] Link faults per frame (drop, garble, noise), strobe misfires (rate/4 per flash), "
                   "controller resets (4 x rate per run).")
@click.option("--frame-drop", type=click.FloatRange(0, 1), default=0.0, show_default=True, help="[simulate] Camera frames lost.")
@click.option("--motion-rate", type=click.FloatRange(0, 1), default=0.0, show_default=True, help="[simulate] Takes where the subject moves.")
@click.option("--motion-mm", type=click.FloatRange(min=0), default=8.0, show_default=True, help="[simulate] How far a moving subject drifts.")
@click.option("--sensor", type=click.Choice(["ideal", "realistic"]), default="ideal", show_default=True,
              help="[simulate] Camera sensor model (realistic: response curve, colour crosstalk, noise).")
@click.option("--realtime", is_flag=True, help="[simulate] Run the controller at the real 60 Hz.")
@click.option("--seed", type=click.IntRange(min=0), default=0, show_default=True, help="[simulate] Random seed.")
@click.option("--crash-after-frames", type=click.IntRange(min=1), hidden=True,
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

    if not simulate and not resume:
        if not port:
            raise click.UsageError("--port is required without --simulate")
        if not camera_backend:
            raise click.UsageError("--cameras BACKEND is required without --simulate")
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
        if not simulate and not (port and camera_backend):
            raise click.UsageError("resuming a hardware session needs --port and --cameras")
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
        try:
            controller = StrobeController(port, timeout=timeout, retries=retries)
        except PortError as exc:
            raise Interrupted(f"{exc}\nThe session in {out} is saved; resume with "
                              f"`{resume_command(out, simulate, port, camera_backend, timeout, retries)}`"
                              + ("" if simulate else " (with the right --port if this one is wrong).")) from None
        if not simulate:
            from mifacerf.capture.hardware.cameras import CameraError, camera_backend as make_backend

            try:
                cameras = make_backend(camera_backend, rig=session.rig)
            except CameraError as exc:
                controller.close()
                raise click.ClickException(str(exc)) from exc
            operator = _ConsoleOperator()
        session.resume_command = resume_command(out, simulate, port, camera_backend, timeout, retries)
        with controller:
            try:
                rep = session.run(controller, cameras, operator, log=_echo)
            except SessionInterrupted as exc:
                raise Interrupted(str(exc)) from exc
            except (SessionError, ControllerError) as exc:
                raise click.ClickException(str(exc)) from exc
            except OSError as exc:   # a write failed (disk full, folder removed...): what is written is kept
                from mifacerf.errors import message_of

                raise Interrupted(f"{message_of(exc)}\nThe session in {out} is saved up to the last complete "
                                  "image; resume with "
                                  f"`{resume_command(out, simulate, port, camera_backend, timeout, retries)}`"
                                  ".") from None
    finally:
        if lab is not None:
            lab.stop()
    click.echo(json.dumps(rep.to_dict(), indent=1))


def resume_command(out, simulate: bool, port, camera_backend, timeout: float, retries: int) -> str:
    """The exact command that resumes the session in ``out`` (a hardware session needs its port and
    cameras again; timeout and retries are not recorded, so non-default values are repeated)."""
    import shlex

    words = ["mifacerf", "capture", str(out), "--resume"]
    if not simulate:
        words += ["--port", str(port), "--cameras", str(camera_backend)]
        if timeout != 0.5:
            words += ["--timeout", repr(timeout)]
        if retries != 4:
            words += ["--retries", str(retries)]
    return " ".join(shlex.quote(w) for w in words)


def _new_session(out, simulate, preset_name, positions, strobes, resolution, n_expressions, radiometry_file, config,
                 sim_opts):
    from mifacerf.capture.expressions import session_expressions
    from mifacerf.capture.session import CaptureSession, SessionError
    from mifacerf.formats.capture import Radiometry
    from mifacerf.rig import LightStage, Rig, camera_ring, CAMERA_LAYOUTS, preset

    try:
        p = preset(preset_name)
    except ValueError as exc:
        raise click.BadParameter(str(exc), param_hint="--preset") from exc
    given = lambda value, default: default if value is None else value  # noqa: E731 (0 is refused by the option)
    res = given(resolution, p.resolution)
    lights = LightStage.semicircular_arm(given(positions, p.n_positions), given(strobes, p.n_strobes),
                                         irradiance_spread=0.05, seed=7)
    rig = Rig(lights, camera_ring(CAMERA_LAYOUTS[p.n_cameras], width=res, height=res))
    try:
        if simulate and sim_opts.get("renderer") == "synthetic":  # the synthetic subject's own expressions
            from mifacerf.capture.simulation.subject import subject_expressions

            exprs = subject_expressions(given(n_expressions, p.n_expressions))
        else:
            exprs = session_expressions(given(n_expressions, p.n_expressions))
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


def _rig_from_options(preset_name: str, resolution: int | None):
    from mifacerf.rig import preset

    try:
        p = preset(preset_name)
    except ValueError as exc:
        raise click.BadParameter(str(exc), param_hint="--preset") from exc
    rig = p.rig()
    if resolution:
        rig.cameras = [c.resized(resolution, resolution) for c in rig.cameras]
    return rig


@calibrate_group.command("render-boards")
@click.argument("out", type=click.Path(file_okay=False, path_type=Path))
@click.option("--preset", default="draft", show_default=True, help="Rig whose cameras are simulated.")
@click.option("--resolution", type=click.IntRange(min=1), help="Render the stills at this size instead of the preset's.")
@click.option("--views", type=click.IntRange(min=1), default=20, show_default=True, help="Board poses.")
@click.option("--board", "board_spec", default="9x7:0.03:0.022", show_default=True,
              help="SQUARESxSQUARES:square_m:marker_m (ChArUco, DICT_4X4_50).")
@click.option("--spp", type=click.IntRange(min=1), default=4, show_default=True, help="Samples per pixel.")
@click.option("--tilt", type=click.FloatRange(0, 89), default=55.0, show_default=True, help="Largest board tilt in degrees.")
@click.option("--seed", type=click.IntRange(min=0), default=0, show_default=True)
def render_boards_cmd(out, preset, resolution, views, board_spec, spp, tilt, seed):
    """Simulate calibration stills: a ChArUco board rendered by Mitsuba into the rig's cameras (truth.json holds
    the intrinsics, distortion and poses used)."""
    from mifacerf.capture.simulation.boards import write_board_dataset

    rig = _rig_from_options(preset, resolution)
    write_board_dataset(out, rig.cameras, _parse_board(board_spec), n_views=views, spp=spp, tilt_deg=tilt, seed=seed,
                        log=lambda c: _echo(f"rendered {c}"))
    _echo(f"wrote {views} views x {len(rig.cameras)} cameras to {out}")


def _parse_board(spec: str):
    from mifacerf.capture.calibration.charuco import BoardSpec

    try:
        size, square, marker = spec.split(":")
        nx, ny = (int(v) for v in size.lower().split("x"))
        return BoardSpec(nx, ny, float(square), float(marker))
    except ValueError as exc:
        raise click.BadParameter(f"{spec!r}: expected e.g. 9x7:0.03:0.022 ({exc})", param_hint="--board") from exc


@calibrate_group.command("geometry")
@click.argument("boards", type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option("--out", type=click.Path(dir_okay=False, path_type=Path), help="Calibration JSON (default BOARDS/geometry.json).")
@click.option("--model", type=click.Choice(["full", "radial", "k1", "none"]), default="full", show_default=True,
              help="Distortion terms estimated (OpenCV k1,k2,p1,p2; k3 = 0).")
@click.option("--principal-prior", type=click.FloatRange(min=0), default=0.01, show_default=True,
              help="Hold principal points near the image centre: standard deviation as a fraction of the width "
                   "(0: estimate freely; narrow zoom lenses need the prior).")
@click.option("--no-world", is_flag=True, help="Use the first camera's frame, ignoring the world pose of the world view.")
@click.option("--truth", type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="Ground truth (simulated boards' truth.json): report the errors.")
@click.option("--apply", "apply_to", type=click.Path(exists=True, file_okay=False, path_type=Path),
              help="Write the cameras into this capture folder's manifest (the old one is kept).")
def geometry_cmd(boards, out, model, principal_prior, no_world, truth, apply_to):
    """Zhang's calibration of every camera and their relative poses from ChArUco stills in BOARDS (paper §2.1)."""
    import numpy as np

    from mifacerf.camera import Camera
    from mifacerf.capture.calibration.zhang2000 import (CalibrationError, calibrate_rig, detect_views, pose_errors,
                                                        relative_pose_errors)
    from mifacerf.capture.simulation.boards import read_board_dataset
    from mifacerf.formats.files import write_json_atomic

    try:
        board, images, desc = read_board_dataset(boards)
    except (FileNotFoundError, KeyError, ValueError) as exc:
        raise click.ClickException(str(exc)) from exc
    sizes = {}
    for cam, imgs in images.items():
        shapes = {im.shape for im in imgs if im is not None}
        if len(shapes) != 1:
            raise click.ClickException(f"camera {cam}: {len(shapes)} different image sizes (or no image)")
        h, w = shapes.pop()
        sizes[cam] = (w, h)
    det = detect_views(board, images)
    for cam, d in det.items():
        _echo(f"{cam}: board found in {len(d)}/{len(images[cam])} views")
    world = desc.get("world_pose")
    try:
        cal = calibrate_rig(board, det, sizes, model=model,
                            principal_prior_px=(principal_prior * max(max(s) for s in sizes.values()))
                            if principal_prior > 0 else None,
                            world_view=None if no_world or world is None else desc.get("world_view", 0),
                            world_pose=None if no_world or world is None else
                            (np.asarray(world["R"]), np.asarray(world["t"])))
    except CalibrationError as exc:
        raise click.ClickException(str(exc)) from exc
    result = cal.to_dict()
    if truth is not None:
        t = json.loads(truth.read_text())
        tcams = [Camera.from_dict(c) for c in t["cameras"]]
        est = [cal.camera(c.name) for c in tcams]
        result["errors"] = {"absolute": [{"camera": c.name, **pose_errors(e, c)} for e, c in zip(est, tcams)],
                            "relative": relative_pose_errors(est, tcams)}
    out = out or boards / "geometry.json"
    write_json_atomic(out, result)
    for c in cal.cameras:
        line = f"{c.camera.name}: f={c.camera.K[0, 0]:.1f}px pp=({c.camera.K[0, 2]:.1f},{c.camera.K[1, 2]:.1f}) " \
               f"rms={c.rms:.3f}px views={len(c.views)} outliers={c.outliers}"
        if truth is not None:
            e = next(x for x in result["errors"]["absolute"] if x["camera"] == c.camera.name)
            line += f" | err f={100 * e['focal_rel']:.2f}% pp={e['principal_px']:.2f}px rot={e['rotation_deg']:.3f}deg " \
                    f"centre={1000 * e['centre_m']:.1f}mm"
        click.echo(line)
    click.echo(f"rms reprojection error {cal.rms:.3f} px ({cal.world}); wrote {out}")
    if apply_to is not None:
        from mifacerf.capture.calibration.apply import apply_to_capture

        backup = apply_to_capture(apply_to, geometry=result, source=str(out))
        click.echo(f"applied to {apply_to}/manifest.json (previous kept as {backup.name})")


@calibrate_group.command("render-charts")
@click.argument("out", type=click.Path(file_okay=False, path_type=Path))
@click.option("--preset", default="tiny", show_default=True)
@click.option("--resolution", type=click.IntRange(min=1), help="Image size instead of the preset's.")
@click.option("--sensor", type=click.Choice(["realistic", "ideal"]), default="realistic", show_default=True)
@click.option("--seed", type=click.IntRange(min=0), default=0, show_default=True)
def render_charts_cmd(out, preset, resolution, sensor, seed):
    """Simulate chart captures: the grey chart under every light and at several exposures, and the
    ColorChecker, recorded by each camera's sensor model (truth.json holds the true radiometry)."""
    from mifacerf.capture.simulation.cameras import SensorModel
    from mifacerf.capture.simulation.charts import write_chart_dataset

    rig = _rig_from_options(preset, resolution)
    sensors = {c.name: (SensorModel.realistic(seed=seed * 100 + i) if sensor == "realistic" else SensorModel())
               for i, c in enumerate(rig.cameras)}
    write_chart_dataset(out, rig, sensors, log=lambda c: _echo(f"rendered {c}"))
    _echo(f"wrote chart captures to {out}")


@calibrate_group.command("response")
@click.argument("charts", type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option("--out", type=click.Path(dir_okay=False, path_type=Path), help="Calibration JSON (default CHARTS/radiometry.json).")
@click.option("--method", type=click.Choice(list(RESPONSE_METHODS)), default=DEFAULT_RESPONSE_METHOD, show_default=True,
              help="Response from the grey chart under every light, or at several exposures.")
@click.option("--truth", type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="Ground truth (simulated charts' truth.json): report the response-curve error.")
@click.option("--apply", "apply_to", type=click.Path(exists=True, file_okay=False, path_type=Path),
              help="Write the radiometry into this capture folder's manifest (the old one is kept).")
def response_cmd(charts, out, method, truth, apply_to):
    """Camera response curves, exposure and colour matrices from chart captures in CHARTS (paper §2.1)."""
    import numpy as np

    from mifacerf.capture.calibration.debevec1997 import curve_error
    from mifacerf.capture.calibration.radiometric import RadiometryError, calibrate_radiometry, to_json
    from mifacerf.formats.capture import Radiometry
    from mifacerf.formats.files import write_json_atomic
    from mifacerf.imageio import ImageFileError

    try:
        results = calibrate_radiometry(charts, method=method)
    except (RadiometryError, ImageFileError) as exc:
        raise click.ClickException(str(exc)) from exc
    data = to_json(results, str(charts), method)
    if truth is not None:
        t = json.loads(truth.read_text())["cameras"]
        errs = {}
        for c, r in results.items():
            tr = Radiometry.from_dict(t[c])
            true_inv = (lambda x, tr=tr: np.interp(x, tr.response["x"], tr.response["y"])) if tr.response else (lambda x: x)
            errs[c] = curve_error(r.radiometry.response, true_inv)
        data["errors"] = errs
    out = out or charts / "radiometry.json"
    write_json_atomic(out, data)
    for c, r in results.items():
        rep = r.report()
        line = f"{c}: exposure={r.radiometry.exposure:.3f} ΔE2000 mean={rep['delta_e2000_mean']:.2f} " \
               f"max={rep['delta_e2000_max']:.2f}"
        if truth is not None:
            line += f" | response error rms={100 * data['errors'][c]['rms']:.2f}% max={100 * data['errors'][c]['max']:.2f}%"
        click.echo(line)
    click.echo(f"wrote {out}")
    if apply_to is not None:
        from mifacerf.capture.calibration.apply import apply_to_capture

        backup = apply_to_capture(apply_to, radiometry=data, source=str(out))
        click.echo(f"applied to {apply_to}/manifest.json (previous kept as {backup.name})")
