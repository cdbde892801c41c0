"""A simulated light-stage lab: controller (over a pseudo-terminal or in-process), cameras, subject.

:class:`SimulatedLab` wires :class:`~.device.SimulatedStrobeController`,
:class:`~.cameras.SyntheticCameras` and :class:`~.cameras.SimulatedSubject` together
for a rig, so a :class:`~mifacerf.capture.session.CaptureSession` can run against it
exactly as against hardware: the session only sees a serial port URL (or port
object) and a camera system.

Its options are plain data (:meth:`SimulatedLab.to_dict`) so a session records them
in its plan and a resumed session rebuilds the same simulated world.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np

from ...rig import Rig
from ..session import Operator
from .cameras import CameraFaults, SensorModel, SimulatedSubject, SyntheticCameras
from .device import Faults, SimulatedStrobeController
from .transport import PtySimulator, SimulatedPort


@dataclass
class LabOptions:
    """Everything that defines a simulated lab, as plain data.

    ``renderer``: ``"procedural"`` (the stand-in head) or ``"synthetic"`` (the synthetic
    subject, :mod:`mifacerf.capture.simulation.subject`). ``fault_rate``: link and strobe
    faults (:meth:`Faults.uniform`); ``frame_drop``: per camera frame; ``motion_rate``:
    per take, drifting ``motion_mm``. ``sensor``: ``"ideal"`` or ``"realistic"``
    (response curve, colour crosstalk, noise). ``time_scale``: 1 = real 60 Hz timing.
    """

    renderer: str = "procedural"
    fault_rate: float = 0.0
    frame_drop: float = 0.0
    motion_rate: float = 0.0
    motion_mm: float = 8.0
    sensor: str = "ideal"
    time_scale: float = 0.0
    seed: int = 0
    force_motion: list = field(default_factory=list)  # [[expression, take], ...]

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "LabOptions":
        return cls(**d)


class SimOperator(Operator):
    """Poses the simulated subject when the session asks for an expression."""

    def __init__(self, subject: SimulatedSubject, say=None):
        self.subject = subject
        self._say = say

    def prompt(self, expression, take: int, sitting: int) -> dict:
        self.subject.assume(expression.name, take, sitting)
        return {"simulated_motion_mm": round(float(np.linalg.norm(self.subject.drift)) * 1000, 3)}

    def say(self, message: str) -> None:
        if self._say:
            self._say(message)


def make_renderer(name: str, rig: Rig, seed: int = 0):
    if name == "procedural":
        from .procedural import ProceduralHead

        return ProceduralHead(rig.lights, seed=seed)
    if name == "synthetic":
        from .subject import SyntheticSubjectRenderer

        return SyntheticSubjectRenderer(rig)
    raise ValueError(f"unknown simulated renderer {name!r}; choose 'procedural' or 'synthetic'")


def expression_params(renderer, name: str, index: int):
    if hasattr(renderer, "expression_params"):
        return renderer.expression_params(name, index)
    from .procedural import default_expression_params

    return default_expression_params(name, index)


class SimulatedLab:
    """The simulated controller, cameras and subject for ``rig`` and ``expressions`` (names)."""

    def __init__(self, rig: Rig, expressions: list[str], options: LabOptions | None = None, *, pty: bool = True):
        self.rig = rig
        self.options = o = options or LabOptions()
        L = rig.lights
        self.faults = Faults.uniform(o.fault_rate, seed=o.seed) if o.fault_rate else Faults(seed=o.seed)
        self.device = SimulatedStrobeController(L.n_positions, L.n_strobes, len(rig.cameras), self.faults,
                                                time_scale=o.time_scale)
        self.renderer = make_renderer(o.renderer, rig, o.seed)
        params = {name: expression_params(self.renderer, name, i) for i, name in enumerate(expressions)}
        self.subject = SimulatedSubject(params, motion_rate=o.motion_rate, motion_mm=o.motion_mm,
                                        n_lights=len(L), seed=o.seed,
                                        force_motion={tuple(x) for x in o.force_motion})
        if o.sensor == "ideal":
            sensors = {c.name: SensorModel() for c in rig.cameras}
        elif o.sensor == "realistic":
            sensors = {c.name: SensorModel.realistic(seed=o.seed * 100 + i) for i, c in enumerate(rig.cameras)}
        else:
            raise ValueError(f"unknown sensor model {o.sensor!r}; choose 'ideal' or 'realistic'")
        self.cameras = SyntheticCameras(rig, self.renderer, self.subject, self.device, sensors=sensors,
                                        faults=CameraFaults(o.frame_drop, seed=o.seed + 1))
        self.operator = SimOperator(self.subject)
        self._pty = PtySimulator(self.device) if pty else None
        self.port = None

    def start(self):
        """Start the controller; returns what to give the driver: a port URL (pty) or a port object."""
        if self._pty is not None:
            self._pty.start()
            self.port = self._pty.url
        else:
            self.port = SimulatedPort(self.device)
        return self.port

    def stop(self) -> None:
        if self._pty is not None:
            self._pty.stop()

    def __enter__(self) -> "SimulatedLab":
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    def stats(self) -> dict:
        return {"device": asdict(self.device.counts), "frames_dropped": self.cameras.frames_dropped,
                "takes_moved": self.subject.takes_moved}
