"""Capture sessions (paper §2.1) that never lose data and resume exactly where they stopped.

Per expression the session asks the subject to hold it, fires every light of the
stage once (in as many runs as it takes: a strobe that misfired, a frame a camera
dropped or a controller that reset mid-sequence only costs re-firing the lights
still missing), checks the take for subject motion (:mod:`mifacerf.capture.motion`)
and repeats a blurred take. Accepted takes become the capture folder's images; the
manifest is written last by :class:`mifacerf.formats.capture.CaptureWriter`.

On disk (``CAPTURE/``)::

    session.jsonl                                   append-only journal (mifacerf.capture.journal)
    takes/<expression>/t<NN>/<camera>/L<lll>.exr    frames of takes in progress, and of rejected takes
    images/<expression>/<camera>/L<lll>.exr         the accepted take, moved (renamed) from takes/
    quarantine/<when>/...                           files that failed verification (moved, never deleted)
    manifest.json                                   written last: the capture is complete

Guarantees: every image is written under a temporary name, fsynced and renamed; its
sha256 is journaled after the rename is durable. Nothing is ever overwritten: a file
in the way is moved to ``quarantine/``. A take is accepted only when every (camera,
light) frame is present and verifies. Resuming (:meth:`CaptureSession.open`)
re-verifies every journaled file, adopts frames written but not yet journaled,
continues the open take with only the missing lights (the motion check then judges
old and new frames together), and skips finished expressions.

Journal events: ``plan`` (first line: rig, expressions, configuration), ``start``,
``take_start``, ``sitting``, ``run``, ``frames``, ``misfire``, ``frame_missing``,
``device_reset``, ``controller_error``, ``reconnected``, ``frame_invalid``,
``adopted``, ``temp_removed``, ``motion``, ``take_end`` (accepted / rejected /
candidate), ``promote``, ``expression_complete``, ``expression_invalid``,
``interrupted``, ``session_complete``.
"""
from __future__ import annotations

import errno
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from ..formats.capture import CaptureError, CaptureWriter, ExpressionEntry, Radiometry
from ..formats.files import FolderLock, sha256_file
from ..imageio import ImageFileError, read_exr, write_exr
from ..rig import Rig
from .hardware.controller import (CommandRefused, ControllerError, ControllerTimeout, DeviceReset,
                                  StrobeController)
from .hardware.sequence import Sequence, olat_sequence
from .journal import Journal, fsync_dir, read_journal
from .motion import MotionCheck, reference_from, representative_lights
from ..errors import MifacerfError

SESSION_FORMAT = "mifacerf.capture-session"
SESSION_VERSION = 1
JOURNAL = "session.jsonl"
TAKE_PATTERN = "takes/{expression}/t{take:02d}/{camera}/L{light:03d}.exr"
IMAGE_PATTERN = "images/{expression}/{camera}/L{light:03d}.exr"


class SessionError(MifacerfError, RuntimeError):
    """A session cannot start or continue; the message says why and what to do."""


class SessionInterrupted(SessionError):
    """The session stopped before the end; everything written is safe and it can be resumed."""


@dataclass
class SessionConfig:
    """``max_takes`` per expression; ``max_runs`` per take (re-firing missing lights);
    ``reference_takes``: takes of the first expression, the sharpest becoming the motion
    reference; ``reconnect_tries`` after the controller reset or went quiet."""

    max_takes: int = 5
    max_runs: int = 6
    reference_takes: int = 2
    reconnect_tries: int = 3
    reconnect_wait_s: float = 0.5
    motion: MotionCheck = field(default_factory=MotionCheck)

    def to_dict(self) -> dict:
        return {"max_takes": self.max_takes, "max_runs": self.max_runs, "reference_takes": self.reference_takes,
                "reconnect_tries": self.reconnect_tries, "reconnect_wait_s": self.reconnect_wait_s,
                "motion": {"sample": self.motion.sample, "method": self.motion.method,
                           "threshold": self.motion.threshold}}

    @classmethod
    def from_dict(cls, d: dict) -> "SessionConfig":
        d = dict(d)
        m = d.pop("motion", {})
        return cls(**d, motion=MotionCheck(**m))


@dataclass
class Take:
    expression: str
    number: int
    frames: dict[tuple[str, int], str] = field(default_factory=dict)  # (camera, light) -> sha256
    status: str = "open"  # open | candidate | accepted | rejected
    sittings: int = 0
    scores: dict[str, float] | None = None
    runs: int = 0


@dataclass
class SessionState:
    """What the journal says happened (rebuilt from its records)."""

    plan: dict
    takes: dict[str, list[Take]] = field(default_factory=dict)
    complete: dict[str, dict[str, str]] = field(default_factory=dict)  # expression -> {rel path: sha}
    finished: bool = False
    starts: int = 0  # how many times the session has been run (1 + resumes)

    @classmethod
    def from_records(cls, records: list[dict]) -> "SessionState":
        if not records or records[0].get("event") != "plan":
            raise SessionError("the session journal does not start with its plan")
        st = cls(records[0])
        for r in records[1:]:
            st.apply(r)
        return st

    def apply(self, r: dict) -> None:
        """Update the state with one journal record."""
        ev = r["event"]
        e = r.get("expression")
        if ev == "take_start":
            self.takes.setdefault(e, []).append(Take(e, r["take"]))
        elif ev in ("sitting", "frames", "frame_invalid", "take_end", "run", "adopted"):
            take = self.take(e, r["take"])
            if take is None:
                return
            if ev == "sitting":
                take.sittings += 1
            elif ev == "run":
                take.runs += 1
            elif ev in ("frames", "adopted"):
                for light, sha in r["frames"]:
                    take.frames[(r["camera"], int(light))] = sha
            elif ev == "frame_invalid":
                take.frames.pop((r["camera"], int(r["light"])), None)
            elif ev == "take_end":
                take.status = r["status"]
                take.scores = r.get("scores", take.scores)
        elif ev == "expression_complete":
            self.complete[e] = r["checksums"]
        elif ev == "expression_invalid":
            self.complete.pop(e, None)
            take = self.take(e, r.get("take", -1))
            if take is not None:
                take.status = "rejected"
        elif ev == "session_complete":
            self.finished = True
        elif ev == "start":
            self.starts += 1

    def take(self, expression: str, number: int) -> Take | None:
        for t in self.takes.get(expression, []):
            if t.number == number:
                return t
        return None

    def accepted_scores(self) -> list[dict[str, float]]:
        return [t.scores for ts in self.takes.values() for t in ts if t.status == "accepted" and t.scores]


@dataclass
class SessionReport:
    """Totals over the whole journal (all resumed runs of the session)."""

    expressions: int = 0
    expressions_complete: int = 0
    takes: int = 0
    takes_rejected: int = 0
    takes_blurred: int = 0
    takes_moved: int = 0           # simulation only: takes in which motion was injected (operator notes)
    moved_and_caught: int = 0      # ... and of those, how many the motion check rejected
    runs: int = 0
    refire_runs: int = 0
    frames_written: int = 0
    frames_adopted: int = 0
    frames_invalid: int = 0
    misfires: int = 0
    frames_missing: int = 0
    device_resets: int = 0
    controller_errors: int = 0
    resumes: int = 0
    interruptions: int = 0
    images: int = 0
    link: dict = field(default_factory=dict)
    complete: bool = False

    def to_dict(self) -> dict:
        return dict(self.__dict__)


def summarize(records: list[dict]) -> SessionReport:
    rep = SessionReport()
    st = SessionState.from_records(records)
    rep.expressions = len(st.plan["expressions"])
    rep.expressions_complete = len(st.complete)
    rep.complete = st.finished
    link: dict[str, int] = {}
    for r in records:
        ev = r["event"]
        if ev == "take_start":
            rep.takes += 1
        elif ev == "take_end" and r["status"] == "rejected":
            rep.takes_rejected += 1
            rep.takes_blurred += int("blurred" in r.get("reason", "") or "motion" in r.get("reason", ""))
        elif ev == "run":
            rep.runs += 1
            rep.refire_runs += int(r.get("run", 1) > 1)
        elif ev == "frames":
            rep.frames_written += len(r["frames"])
        elif ev == "adopted":
            rep.frames_adopted += len(r["frames"])
        elif ev == "frame_invalid":
            rep.frames_invalid += 1
        elif ev == "misfire":
            rep.misfires += len(r["lights"])
        elif ev == "frame_missing":
            rep.frames_missing += r["count"]
        elif ev == "device_reset":
            rep.device_resets += 1
        elif ev == "controller_error":
            rep.controller_errors += 1
        elif ev == "start" and r.get("resume"):
            rep.resumes += 1
        elif ev == "interrupted":
            rep.interruptions += 1
        elif ev == "link_stats":
            for k, v in r["stats"].items():
                link[k] = link.get(k, 0) + v
    rep.link = link
    rep.images = sum(len(c) for c in st.complete.values())
    moved = {(r["expression"], r["take"]) for r in records
             if r["event"] == "operator_note" and r.get("simulated_motion_mm", 0) > 0}
    blurred = {(r["expression"], r["take"]) for r in records if r["event"] == "motion" and r.get("blurred")}
    rep.takes_moved, rep.moved_and_caught = len(moved), len(moved & blurred)
    return rep


class Operator:
    """Talks to the subject and the operator. The default prints; the simulation's poses the subject."""

    def prompt(self, expression: ExpressionEntry, take: int, sitting: int) -> dict | None:
        """Ask the subject to hold ``expression``; return when ready, optionally with a note for the journal."""

    def say(self, message: str) -> None:
        pass


def _rel(pattern: str, expression: str, camera: str, light: int, take: int = 0) -> str:
    return pattern.format(expression=expression, camera=camera, light=int(light), take=take)


class CaptureSession:
    """A capture session in folder ``root``. Create with :meth:`create`, reopen with :meth:`open`,
    then :meth:`run` it with a controller, cameras and an operator."""

    def __init__(self, root: str | os.PathLike, records: list[dict], bad_lines: list[int] | None = None):
        self.root = Path(root)
        self.state = SessionState.from_records(records)
        plan = self.state.plan
        self.rig = Rig.from_dict(plan["rig"])
        self.expressions = [ExpressionEntry(e["name"], e.get("category", "other")) for e in plan["expressions"]]
        self.radiometry = {k: Radiometry.from_dict(v) for k, v in plan.get("radiometry", {}).items()}
        self.config = SessionConfig.from_dict(plan.get("config", {}))
        self.period_us = int(plan.get("period_us", 16666))
        self.lights = self.rig.lights
        self.sample = np.asarray(plan["sample_lights"], np.int64)
        self.bad_lines = bad_lines or []
        self.journal: Journal | None = None
        self.write_image: Callable[[Path, np.ndarray], None] = write_exr  # a hook for fault injection
        #: the command that resumes this session, quoted in every interruption (the CLI sets the exact one:
        #: a hardware session needs its --port and --cameras again)
        self.resume_command = f"mifacerf capture {self.root} --resume"
        self.operator = Operator()
        self.controller: StrobeController | None = None
        self.cameras = None

    # --------------------------------------------------------------- creation
    @classmethod
    def create(cls, root, rig: Rig, expressions: list[ExpressionEntry], *, config: SessionConfig | None = None,
               radiometry: dict[str, Radiometry] | None = None, extra: dict | None = None,
               period_us: int = 16666) -> "CaptureSession":
        """Start a new session in ``root`` (must not hold a session or a capture already)."""
        root = Path(root)
        if (root / JOURNAL).exists():
            raise SessionError(f"{root} already holds a capture session ({JOURNAL}); resume it with --resume "
                               "or choose another folder")
        if (root / "manifest.json").exists():
            raise SessionError(f"{root} already holds a complete capture (manifest.json); choose another folder")
        names = [e.name for e in expressions]
        if len(set(names)) != len(names) or not names:
            raise SessionError("expression names must be unique and at least one is needed")
        if not rig.cameras or len(rig.lights) == 0:
            raise SessionError("the rig has no cameras or no lights")
        config = config or SessionConfig()
        radiometry = radiometry or {c.name: Radiometry() for c in rig.cameras}
        sample = representative_lights(rig.lights.n_positions or 1, rig.lights.n_strobes or len(rig.lights),
                                       config.motion.sample)
        try:
            root.mkdir(parents=True, exist_ok=True)
            plan = {"format": SESSION_FORMAT, "version": SESSION_VERSION, "rig": rig.to_dict(),
                    "expressions": [e.to_dict() for e in expressions],
                    "radiometry": {k: v.to_dict() for k, v in radiometry.items()},
                    "config": config.to_dict(), "period_us": period_us, "sample_lights": sample.tolist(),
                    "take_pattern": TAKE_PATTERN, "image_pattern": IMAGE_PATTERN, **(extra or {})}
            with Journal(root / JOURNAL) as j:
                rec = j.append("plan", **plan)
        except OSError as exc:
            raise SessionError(f"cannot create the session in {root}: {exc.strerror or exc}") from exc
        return cls(root, [rec])

    @classmethod
    def open(cls, root) -> "CaptureSession":
        """Reopen the session in ``root`` to resume it."""
        root = Path(root)
        if not (root / JOURNAL).exists():
            if (root / "manifest.json").exists():
                raise SessionError(f"{root} holds a finished capture without a session journal; nothing to resume")
            raise SessionError(f"{root}: no capture session to resume (no {JOURNAL})")
        contents = read_journal(root / JOURNAL)
        rec = contents.records
        if not rec or rec[0].get("event") != "plan":
            raise SessionError(f"{root / JOURNAL}: the first record is not the session plan; the journal is damaged "
                               f"(bad lines: {contents.bad_lines[:5]})")
        if rec[0].get("format") != SESSION_FORMAT or rec[0].get("version") != SESSION_VERSION:
            raise SessionError(f"{root / JOURNAL}: not a {SESSION_FORMAT} v{SESSION_VERSION} journal")
        return cls(root, rec, contents.bad_lines)

    @property
    def plan(self) -> dict:
        return self.state.plan

    def report(self) -> SessionReport:
        rep = summarize(read_journal(self.root / JOURNAL).records)
        return rep

    # ------------------------------------------------------------------ journal
    def _log(self, event: str, **data) -> dict:
        rec = self.journal.append(event, **data)
        self.state.apply(rec)
        return rec

    # --------------------------------------------------------------------- run
    def run(self, controller: StrobeController, cameras, operator: Operator | None = None,
            log: Callable[[str], None] | None = None) -> SessionReport:
        """Capture every expression not yet complete, then write the manifest; ``log(message)`` hears
        each take's outcome.

        Raises :class:`SessionInterrupted` (resumable) when the hardware, the disk or
        the operator (Ctrl-C) stops it; the journal says where it stopped. One session at a time per
        folder: the folder's lock (``.<folder>.lock`` beside it) is held while it runs, and a second
        session on the same folder is refused (a :class:`SessionError` that is also a
        :class:`~mifacerf.errors.RefusedError`: exit 3), so two never interleave their takes.
        """
        with FolderLock(self.root, SessionError, wait=False, what="capture session"):
            return self._run(controller, cameras, operator, log)

    def _run(self, controller, cameras, operator, log) -> SessionReport:
        if self.state.finished and (self.root / "manifest.json").exists():
            return self.report()
        self.controller, self.cameras = controller, cameras
        self.operator = operator or Operator()
        self.say = log or (lambda msg: None)
        missing_cams = set(c.name for c in self.rig.cameras) - set(cameras.names)
        if missing_cams:
            raise SessionError(f"the camera system lacks cameras {sorted(missing_cams)} of the session's rig")
        try:
            self.journal = Journal(self.root / JOURNAL)
        except OSError as exc:
            raise SessionInterrupted(f"cannot open the session journal: {exc.strerror or exc}") from exc
        resumed = self.state.starts > 0
        try:
            self._log("start", resume=resumed, pid=os.getpid(), bad_journal_lines=self.bad_lines)
            self._recover()
            self._hello()
            for expr in self.expressions:
                if expr.name in self.state.complete:
                    continue
                self._capture_expression(expr)
            self._finish()
        except KeyboardInterrupt:
            self._interrupted("stopped by the operator (Ctrl-C)")
            raise SessionInterrupted(self._resume_hint("stopped by the operator")) from None
        except OSError as exc:
            what = "the disk is full" if exc.errno == errno.ENOSPC else f"writing failed ({exc.strerror or exc})"
            self._interrupted(what, errno=exc.errno)
            raise SessionInterrupted(self._resume_hint(what + ("; free some space" if exc.errno == errno.ENOSPC
                                                                else ""))) from exc
        except SessionInterrupted as exc:
            self._interrupted(str(exc))
            raise
        except ControllerError as exc:
            self._interrupted(str(exc))
            raise SessionInterrupted(self._resume_hint(str(exc))) from exc
        finally:
            self._link_stats()
            self.journal.close()
        return self.report()

    def _resume_hint(self, why: str) -> str:
        done = len(self.state.complete)
        return (f"capture session interrupted: {why}. {done}/{len(self.expressions)} expressions are complete and "
                f"every image written is safe; resume with `{self.resume_command}`")

    def _interrupted(self, why: str, **extra) -> None:
        try:
            self._log("interrupted", reason=why, **extra)
        except Exception:  # noqa: BLE001 - the disk may be full; the journal is still consistent
            pass

    def _link_stats(self) -> None:
        """Journal the driver's counters since the last call (so a killed process loses none)."""
        if self.controller is None:
            return
        stats = self.controller.stats.to_dict()
        if not any(stats.values()):
            return
        try:
            self._log("link_stats", stats=stats)
            self.controller.stats = type(self.controller.stats)()
        except Exception:  # noqa: BLE001 - the disk may be full; counters are not data
            pass

    def _hello(self) -> None:
        try:
            info = self.controller.hello()
        except ControllerError as exc:
            raise SessionInterrupted(self._resume_hint(f"the strobe controller does not answer: {exc}")) from exc
        L = self.rig.lights
        if (L.n_positions, L.n_strobes) != (info.n_positions, info.n_strobes):
            raise SessionError(f"the controller drives {info.n_positions} arm positions x {info.n_strobes} strobes, "
                               f"the session's rig has {L.n_positions} x {L.n_strobes}")
        self._log("controller", info=info.__dict__)

    def _reconnect(self, why: str) -> None:
        for i in range(self.config.reconnect_tries):
            try:
                info = self.controller.hello()
                self._log("reconnected", boot_id=info.boot_id, after=why)
                return
            except ControllerError:
                time.sleep(self.config.reconnect_wait_s * (i + 1))
        raise SessionInterrupted(self._resume_hint(f"the strobe controller stopped answering ({why})"))

    # ---------------------------------------------------------------- recovery
    def _quarantine(self, path: Path) -> Path:
        rel = path.relative_to(self.root)
        dst = self.root / "quarantine" / time.strftime("%Y%m%d-%H%M%S") / rel
        dst.parent.mkdir(parents=True, exist_ok=True)
        n = 0
        while dst.exists():
            n += 1
            dst = dst.with_name(f"{rel.name}.{n}")
        os.replace(path, dst)
        fsync_dir(dst.parent)
        return dst

    def _recover(self) -> None:
        """Verify what the journal claims; adopt frames written but not journaled; drop temp files."""
        cams = [c.name for c in self.rig.cameras]
        for e, takes in self.state.takes.items():
            for take in takes:
                if take.status == "rejected" or e in self.state.complete:
                    continue
                for (cam, light), sha in list(take.frames.items()):
                    src = self.root / _rel(TAKE_PATTERN, e, cam, light, take.number)
                    dst = self.root / _rel(IMAGE_PATTERN, e, cam, light)
                    ok = False
                    for p in (src, dst) if take.status == "accepted" else (src,):
                        if p.exists():
                            if sha256_file(p) == sha:
                                ok = True
                                break
                            if p == src:
                                q = self._quarantine(p)
                                self._log("frame_invalid", expression=e, take=take.number, camera=cam, light=light,
                                          reason="checksum mismatch", quarantined=str(q.relative_to(self.root)))
                    if not ok and (cam, light) in take.frames:
                        self._log("frame_invalid", expression=e, take=take.number, camera=cam, light=light,
                                  reason="missing")
                # frames on disk the journal does not know (written, then the session died before journaling)
                if take.status in ("open", "candidate"):
                    for cam in cams:
                        d = self.root / "takes" / e / f"t{take.number:02d}" / cam
                        if not d.is_dir():
                            continue
                        adopted = []
                        for p in sorted(d.iterdir()):
                            if p.name.startswith(".") and ".tmp" in p.name:
                                p.unlink()
                                self._log("temp_removed", path=str(p.relative_to(self.root)))
                                continue
                            if not (p.suffix == ".exr" and p.name.startswith("L")):
                                continue
                            try:
                                light = int(p.stem[1:])
                            except ValueError:
                                continue
                            if (cam, light) in take.frames:
                                continue
                            c = self.rig.camera(cam)
                            try:
                                read_exr(p, channels=3, expect_shape=(c.height, c.width))
                            except ImageFileError:
                                q = self._quarantine(p)
                                self._log("frame_invalid", expression=e, take=take.number, camera=cam, light=light,
                                          reason="unreadable orphan", quarantined=str(q.relative_to(self.root)))
                                continue
                            adopted.append([light, sha256_file(p)])
                        if adopted:
                            self._log("adopted", expression=e, take=take.number, camera=cam, frames=adopted)
        # finished expressions: their images must still verify
        for e, checksums in list(self.state.complete.items()):
            bad = []
            for rel, sha in checksums.items():
                p = self.root / rel
                if not p.exists() or sha256_file(p) != sha:
                    bad.append(rel)
            if bad:
                for rel in bad:
                    if (self.root / rel).exists():
                        self._quarantine(self.root / rel)
                takes = [t for t in self.state.takes.get(e, []) if t.status == "accepted"]
                self._log("expression_invalid", expression=e, take=takes[-1].number if takes else -1,
                          reason=f"{len(bad)} image(s) missing or corrupt, e.g. {bad[0]}", bad=bad)
                # what still verifies of the accepted take is moved aside, never overwritten later
                for rel in checksums:
                    p = self.root / rel
                    if p.exists():
                        self._quarantine(p)

    # --------------------------------------------------------------- capturing
    def _capture_expression(self, expr: ExpressionEntry) -> None:
        e = expr.name
        while e not in self.state.complete:
            takes = self.state.takes.get(e, [])
            take = next((t for t in takes if t.status == "open"), None)
            accepted = next((t for t in takes if t.status == "accepted"), None)
            if accepted is not None:  # interrupted while promoting
                self._promote(accepted)
                return
            if take is None:
                n_started = len(takes)
                if n_started >= self.config.max_takes + self._reference_extra():
                    raise SessionInterrupted(self._resume_hint(
                        f"expression {e!r}: {n_started} takes and none sharp enough; check the subject and resume "
                        "(a resumed session allows more takes)"))
                number = max([t.number for t in takes], default=0) + 1
                self._log("take_start", expression=e, take=number)
                take = self.state.take(e, number)
            if self._missing(take):
                self._log("sitting", expression=e, take=take.number, sitting=take.sittings)
                self.say(f"{e}: take {take.number}" + (f", sitting {take.sittings}" if take.sittings > 1 else ""))
                note = self.operator.prompt(expr, take.number, take.sittings - 1)
                if note:  # whatever the operator wants on record (the simulation: the motion it injected)
                    self._log("operator_note", expression=e, take=take.number, **note)
                self._fill(take)
            self._judge(take)

    def _reference_extra(self) -> int:
        return self.config.reference_takes if not self.state.accepted_scores() else 0

    def _missing(self, take: Take) -> list[tuple[str, int]]:
        return [(c.name, l) for l in range(len(self.lights)) for c in self.rig.cameras
                if (c.name, l) not in take.frames]

    def _fill(self, take: Take) -> None:
        """Fire the lights still missing in ``take`` until every camera has every frame."""
        e = take.expression
        runs_here = 0
        while True:
            missing = self._missing(take)
            if not missing:
                return
            if runs_here >= self.config.max_runs:
                lights = sorted({l for _, l in missing})
                raise SessionInterrupted(self._resume_hint(
                    f"expression {e!r} take {take.number}: {len(missing)} frame(s) still missing after {runs_here} "
                    f"runs (lights {lights[:10]}{'...' if len(lights) > 10 else ''}); check those strobes"))
            lights = sorted({l for _, l in missing})
            seq = olat_sequence(self.lights.n_positions, self.lights.n_strobes, lights, period_us=self.period_us)
            runs_here += 1
            self._log("run", expression=e, take=take.number, run=take.runs + 1, n_lights=len(lights),
                      lights=lights if len(lights) < len(self.lights) else "all")
            self._one_run(take, seq)

    def _one_run(self, take: Take, seq: Sequence) -> None:
        e = take.expression
        events = []
        reset = None
        try:
            self.cameras.start(len(seq))
            self.controller.load(seq)
            events = self.controller.run(seq).events
        except DeviceReset as exc:
            events, reset = exc.events, exc
            self._log("device_reset", expression=e, take=take.number, old_boot=exc.old_boot, new_boot=exc.new_boot,
                      steps_fired=len(exc.events), of=len(seq))
        except (ControllerTimeout, CommandRefused, ControllerError) as exc:
            self._log("controller_error", expression=e, take=take.number, error=str(exc), kind=type(exc).__name__)
            try:  # the frames of this run cannot be matched to lights without the events: collected and dropped
                self.cameras.collect(timeout=0.5, expected=0)
            except Exception:  # noqa: BLE001
                pass
            self._reconnect(str(exc))
            return
        frames = self.cameras.collect(timeout=max(2.0, 2 * seq.duration_s), expected=len(events))
        seq_lights = seq.lights
        misfired, missing_frames = [], 0
        by_cam = {c: {f.trigger: f for f in fl} for c, fl in frames.items()}
        written: dict[str, list] = {}
        try:
            for ev in events:
                step = seq.steps[ev.step]
                if (ev.arm_position, ev.strobe) != (step.arm_position, step.strobe):
                    raise ControllerError(f"event for step {ev.step} reports arm {ev.arm_position} strobe {ev.strobe}, "
                                          f"the sequence has {step.arm_position}/{step.strobe}")
                light = int(seq_lights[ev.step])
                if not ev.fired:
                    misfired.append(light)
                    continue
                for cam in self.rig.cameras:
                    if (cam.name, light) in take.frames:
                        continue
                    f = by_cam.get(cam.name, {}).get(ev.trigger)
                    if f is None:
                        missing_frames += 1
                        continue
                    sha = self._store(take, cam, light, f.image)
                    if sha is not None:
                        written.setdefault(cam.name, []).append([light, sha])
        finally:
            for cam_name, fl in written.items():  # durable renames first, then the journal says so
                fsync_dir(self.root / "takes" / e / f"t{take.number:02d}" / cam_name)
                self._log("frames", expression=e, take=take.number, camera=cam_name, frames=fl)
        if misfired:
            self._log("misfire", expression=e, take=take.number, lights=misfired)
        if missing_frames:
            self._log("frame_missing", expression=e, take=take.number, count=missing_frames)
        if reset is not None:
            self._reconnect("device reset")
        self._link_stats()

    def _store(self, take: Take, cam, light: int, image: np.ndarray) -> str | None:
        path = self.root / _rel(TAKE_PATTERN, take.expression, cam.name, light, take.number)
        if image.shape[:2] != (cam.height, cam.width):
            raise SessionInterrupted(self._resume_hint(f"camera {cam.name} delivered a {image.shape[1]}x"
                                                       f"{image.shape[0]} frame, the rig says {cam.width}x{cam.height}"))
        if path.exists():  # never overwrite: a file here is not in the journal (adopted on resume)
            self._quarantine(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        self.write_image(path, image)
        return sha256_file(path)

    # ----------------------------------------------------------- motion check
    def _sample_frames(self, take: Take) -> dict[str, np.ndarray]:
        out = {}
        for cam in self.rig.cameras:
            imgs = []
            for l in self.sample:
                p = self.root / _rel(TAKE_PATTERN, take.expression, cam.name, int(l), take.number)
                if sha256_file(p) != take.frames[(cam.name, int(l))]:
                    raise CaptureError(f"{p}: checksum mismatch while checking the take")
                imgs.append(read_exr(p, channels=3, expect_shape=(cam.height, cam.width)))
            out[cam.name] = np.stack(imgs)
        return out

    def _judge(self, take: Take) -> None:
        e = take.expression
        try:
            scores = self.config.motion.scores(self._sample_frames(take))
        except (CaptureError, ImageFileError, FileNotFoundError) as exc:
            self._log("motion_check_failed", expression=e, take=take.number, error=str(exc))
            self._recover()
            return  # the loop refills what is missing
        accepted = self.state.accepted_scores()
        if accepted:
            verdict = self.config.motion.judge(scores, reference_from(accepted))
            self._log("motion", expression=e, take=take.number, **verdict.to_dict())
            if verdict.blurred:
                self.say(f"{e}: take {take.number} blurred ({', '.join(verdict.blurred_cameras)}); retaking")
                self._log("take_end", expression=e, take=take.number, status="rejected", scores=scores,
                          reason=f"subject motion: blurred in {verdict.blurred_cameras}")
                return
            self._log("take_end", expression=e, take=take.number, status="accepted", scores=scores)
            self._promote(self.state.take(e, take.number))
            return
        # no reference yet: collect `reference_takes` candidates, keep the sharpest
        self._log("take_end", expression=e, take=take.number, status="candidate", scores=scores)
        cands = [t for t in self.state.takes.get(e, []) if t.status == "candidate" and t.scores]
        if len(cands) < max(1, self.config.reference_takes):
            self.say(f"{e}: take {take.number} kept as a reference candidate")
            return
        ref = {c: max(t.scores[c] for t in cands) for c in scores}
        verdicts = {t.number: self.config.motion.judge(t.scores, ref) for t in cands}
        best = max(cands, key=lambda t: min(r for r in verdicts[t.number].ratios.values()))
        for t in cands:
            v = verdicts[t.number]
            self._log("motion", expression=e, take=t.number, **v.to_dict())
            if t is best and not v.blurred:
                continue
            self._log("take_end", expression=e, take=t.number, status="rejected", scores=t.scores,
                      reason="blurred" if v.blurred else "a sharper reference take was kept")
        if not verdicts[best.number].blurred:
            self._log("take_end", expression=e, take=best.number, status="accepted", scores=best.scores)
            self._promote(self.state.take(e, best.number))

    # --------------------------------------------------------------- promote
    def _promote(self, take: Take) -> None:
        """Move an accepted take's frames to images/ (idempotent; never overwrites)."""
        e = take.expression
        self._log("promote", expression=e, take=take.number)
        checksums = {}
        dirs = set()
        for (cam, light), sha in sorted(take.frames.items()):
            src = self.root / _rel(TAKE_PATTERN, e, cam, light, take.number)
            dst_rel = _rel(IMAGE_PATTERN, e, cam, light)
            dst = self.root / dst_rel
            if dst.exists():
                if sha256_file(dst) == sha:
                    checksums[dst_rel] = sha
                    continue
                self._quarantine(dst)
            if not src.exists():
                raise SessionInterrupted(self._resume_hint(f"{src} vanished before it could be moved to {dst_rel}"))
            dst.parent.mkdir(parents=True, exist_ok=True)
            os.replace(src, dst)
            dirs.update((src.parent, dst.parent))
            checksums[dst_rel] = sha
        for d in dirs:
            fsync_dir(d)
        for d in sorted({d for d in dirs if "takes" in d.parts}, key=lambda p: -len(p.parts)):
            for p in (d, d.parent):  # the emptied take folders (never a file)
                try:
                    p.rmdir()
                except OSError:
                    pass
        if len(checksums) != len(self.lights) * len(self.rig.cameras):
            raise SessionError(f"expression {e!r}: the accepted take has {len(checksums)} images, expected "
                               f"{len(self.lights) * len(self.rig.cameras)}")
        self._log("expression_complete", expression=e, take=take.number, checksums=checksums)
        self.say(f"{e}: complete (take {take.number})")

    # ----------------------------------------------------------------- finish
    def _finish(self) -> None:
        missing = [x.name for x in self.expressions if x.name not in self.state.complete]
        if missing:
            raise SessionError(f"expressions {missing} are not complete")
        checksums = {rel: sha for c in self.state.complete.values() for rel, sha in c.items()}
        rep = summarize(read_journal(self.root / JOURNAL).records)
        writer = CaptureWriter(self.root, self.rig, self.expressions, radiometry=self.radiometry or None,
                               extra={"session": {"journal": JOURNAL, "takes": rep.takes,
                                                  "takes_rejected": rep.takes_rejected, "runs": rep.runs,
                                                  "resumes": rep.resumes},
                                      **({"radiometric_calibration": self.plan["radiometric_calibration"]}
                                         if "radiometric_calibration" in self.plan else {})})
        writer.checksums = checksums
        writer.finish()
        self._log("session_complete", images=len(checksums))
        self.say(f"capture complete: {len(self.expressions)} expressions, {len(checksums)} images")


def verify_capture(root) -> tuple[int, list[str]]:
    """(number of images that verify by checksum, problems) for the capture folder ``root``."""
    from ..formats.capture import Capture

    cap = Capture(root)
    problems = cap.verify(checksums=True)
    total = len(cap.expression_names) * len(cap.camera_names) * cap.n_lights
    missing_sums = [e for e in cap.expression_names for c in cap.camera_names for l in range(cap.n_lights)
                    if cap.image_path(e, c, l).relative_to(cap.root).as_posix() not in cap.checksums]
    if missing_sums:
        problems.append(f"{len(missing_sums)} image(s) have no checksum in the manifest")
    return total - len(problems), problems
