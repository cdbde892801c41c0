"""Synthetic cameras: render the simulated subject lit by whatever the simulated controller fired.

:class:`SyntheticCameras` implements :class:`~mifacerf.capture.hardware.cameras.CameraSystem`.
It listens to the simulated controller's triggers (:class:`~.device.Trigger`), so a
frame shows the light that really fired (a misfire gives a dark frame), and it
renders through any OLAT renderer with the interface
``render(expression, camera, lights) -> (n, H, W, 3)`` radiance per unit irradiance:
the procedural stand-in (:mod:`.procedural`) or the synthetic subject
(:mod:`.subject`). The light's irradiance calibration ``E_l`` multiplies the
radiance, then a :class:`SensorModel` turns it into recorded camera values.

Subject motion (:class:`SimulatedSubject`): a take may drift rigidly in **world** by
``motion_mm`` over the sequence; every frame is then shifted (sub-pixel, by the
projected displacement) before recording, so the sum of frames is blurred.
"""
from __future__ import annotations

import threading
import time
import zlib
from dataclasses import dataclass, field

import numpy as np

from ...camera import Camera
from ...formats.capture import Radiometry
from ...rig import Rig
from ..hardware.cameras import CameraSystem, Frame
from .device import Trigger


@dataclass
class SensorModel:
    """Radiance (linear sRGB) -> recorded value: ``response(exposure * M^-1 @ L)`` + noise, quantised.

    ``colour_matrix`` M is the camera's true camera-RGB -> sRGB matrix (what colour
    calibration should recover); ``gamma`` > 1 gives a response ``x ** (1/gamma)``
    with a toe, clipped at 1 (None: linear, no clipping); ``noise`` the read noise
    standard deviation; ``bits`` quantisation (None: none).
    """

    exposure: float = 1.0
    colour_matrix: np.ndarray = field(default_factory=lambda: np.eye(3))
    gamma: float | None = None
    toe: float = 0.02
    noise: float = 0.0
    bits: int | None = None
    seed: int = 0

    def __post_init__(self):
        self.colour_matrix = np.asarray(self.colour_matrix, np.float64).reshape(3, 3)
        self._inv = np.linalg.inv(self.colour_matrix)
        self._rng = np.random.default_rng(self.seed)

    @classmethod
    def realistic(cls, seed: int = 0, exposure: float = 3.0) -> "SensorModel":
        """A plausible video camera: crosstalk matrix, gamma-2.2-like response, 10 bits, read noise."""
        rng = np.random.default_rng(seed)
        cam_to_srgb = np.array([[1.65, -0.45, -0.20], [-0.25, 1.45, -0.20], [0.05, -0.50, 1.45]])
        cam_to_srgb += 0.03 * rng.standard_normal((3, 3))
        return cls(exposure, cam_to_srgb, gamma=2.2, toe=0.02, noise=0.002, bits=10, seed=seed)

    @property
    def is_linear(self) -> bool:
        return self.gamma is None

    def response(self, x: np.ndarray) -> np.ndarray:
        """Linear camera value -> recorded value (monotone)."""
        if self.gamma is None:
            return x
        x = np.clip(x, 0.0, 1.0)
        a = self.toe
        return ((x + a) ** (1 / self.gamma) - a ** (1 / self.gamma)) / ((1 + a) ** (1 / self.gamma) - a ** (1 / self.gamma))

    def inverse_response(self, y: np.ndarray) -> np.ndarray:
        if self.gamma is None:
            return y
        a, g = self.toe, self.gamma
        y = np.clip(y, 0.0, 1.0)
        return (y * ((1 + a) ** (1 / g) - a ** (1 / g)) + a ** (1 / g)) ** g - a

    def record(self, radiance: np.ndarray) -> np.ndarray:
        """(..., 3) linear sRGB radiance -> (..., 3) float32 recorded values."""
        lin = self.exposure * (np.asarray(radiance, np.float64) @ self._inv.T)
        rec = self.response(lin)
        if self.noise:
            rec = rec + self.noise * self._rng.standard_normal(rec.shape)
        if self.bits:
            q = 2**self.bits - 1
            rec = np.round(np.clip(rec, 0, 1) * q) / q
        return rec.astype(np.float32)

    def true_radiometry(self, knots: int = 64) -> Radiometry:
        """The calibration that exactly undoes this sensor (what calibration should find)."""
        resp = None
        if self.gamma is not None:
            y = np.linspace(0, 1, knots)
            resp = {"x": self.response(y).tolist(), "y": y.tolist()}
        return Radiometry(self.exposure, self.colour_matrix, resp)


@dataclass
class CameraFaults:
    """``drop_frame``: probability that a camera misses a trigger (no frame)."""

    drop_frame: float = 0.0
    seed: int = 0


class SimulatedSubject:
    """The person in the chair: holds an expression per take, sometimes moves.

    ``expressions`` maps names to renderer parameters. ``motion_rate``: probability
    that a take drifts; ``motion_mm``: how far (a random direction, linearly over the
    take's ``n_lights`` triggers). ``force_motion``: set of (expression, take) pairs
    that always move (for tests).
    """

    def __init__(self, expressions: dict[str, object], *, motion_rate: float = 0.0, motion_mm: float = 8.0,
                 n_lights: int = 1, seed: int = 0, force_motion=()):
        self.expressions = dict(expressions)
        self.motion_rate, self.motion_mm = motion_rate, motion_mm
        self.n_lights = max(1, n_lights)
        self.seed = seed
        self.force_motion = set(force_motion)
        self.current: str | None = None
        self.drift = np.zeros(3)
        self.clock = 0
        self.takes_moved = 0

    def assume(self, expression: str, take: int, sitting: int = 0) -> None:
        """Adopt ``expression`` for take number ``take`` (deterministic per expression, take and sitting)."""
        if expression not in self.expressions:
            raise KeyError(f"the simulated subject has no expression {expression!r}")
        rng = np.random.default_rng([self.seed, zlib.crc32(expression.encode()), take, sitting])
        self.current = expression
        self.clock = 0
        moves = (expression, take) in self.force_motion or rng.random() < self.motion_rate
        if moves:
            d = rng.standard_normal(3)
            self.drift = d / np.linalg.norm(d) * self.motion_mm * 1e-3
            self.takes_moved += 1
        else:
            self.drift = np.zeros(3)

    def displacement(self) -> np.ndarray:
        """World displacement (3,) of the head now; advances the subject's clock by one frame."""
        f = min(1.0, self.clock / self.n_lights)
        self.clock += 1
        return self.drift * f

    @property
    def params(self):
        if self.current is None:
            raise RuntimeError("the subject has not been asked for an expression yet")
        return self.expressions[self.current]


def _shift_image(img: np.ndarray, dx: float, dy: float) -> np.ndarray:
    import cv2

    if abs(dx) < 1e-6 and abs(dy) < 1e-6:
        return img
    M = np.float32([[1, 0, dx], [0, 1, dy]])
    return cv2.warpAffine(img, M, (img.shape[1], img.shape[0]), flags=cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_CONSTANT)


class SyntheticCameras(CameraSystem):
    """Cameras of ``rig`` that render ``subject`` through ``renderer`` on each trigger of ``device``.

    ``sensors``: a :class:`SensorModel` per camera name (default: ideal linear).
    Rendering happens in :meth:`collect` (one batched render per camera and run).
    """

    def __init__(self, rig: Rig, renderer, subject: SimulatedSubject, device=None, *,
                 sensors: dict[str, SensorModel] | None = None, faults: CameraFaults | None = None,
                 head_distance: float | None = None):
        self.rig = rig
        self.cameras = list(rig.cameras)
        self.renderer = renderer
        self.subject = subject
        self.sensors = sensors or {c.name: SensorModel() for c in self.cameras}
        self.faults = faults or CameraFaults()
        self._rng = np.random.default_rng(self.faults.seed)
        self._lock = threading.Lock()
        self._triggers: list[tuple[Trigger, np.ndarray]] = []
        self._armed = 0
        self.frames_dropped = 0
        self.head_distance = head_distance
        if device is not None:
            self.attach(device)

    def attach(self, device) -> None:
        device.listeners.append(self._on_trigger)

    def _on_trigger(self, trig: Trigger) -> None:
        with self._lock:
            if len(self._triggers) < self._armed:
                self._triggers.append((trig, self.subject.displacement()))

    def start(self, n_triggers: int) -> None:
        with self._lock:
            self._triggers = []
            self._armed = int(n_triggers)

    def collect(self, timeout: float = 10.0, expected: int | None = None) -> dict[str, list[Frame]]:
        deadline = time.monotonic() + timeout
        want = self._armed if expected is None else min(expected, self._armed)
        while True:  # triggers come from the controller's thread; the run is over when we are called
            with self._lock:
                trig = list(self._triggers)
            if len(trig) >= want or time.monotonic() >= deadline:
                break
            time.sleep(0.01)
        out: dict[str, list[Frame]] = {}
        params = self.subject.params if trig else None
        for ci, cam in enumerate(self.cameras):
            mine = [(t, disp) for t, disp in trig if t.camera_mask >> ci & 1 or ci >= 8]
            lights = sorted({t.light for t, _ in mine if t.light is not None})
            rendered = dict(zip(lights, self.renderer.render(params, cam, np.array(lights)))) if lights else {}
            frames = []
            for t, disp in mine:
                if self._rng.random() < self.faults.drop_frame:
                    self.frames_dropped += 1
                    continue
                if t.light is None:
                    rad = np.zeros((cam.height, cam.width, 3), np.float32)
                else:
                    rad = rendered[t.light] * self.rig.lights.irradiance[t.light].astype(np.float32)
                    if np.any(disp):
                        dx, dy = self._image_shift(cam, disp)
                        rad = _shift_image(rad, dx, dy)
                frames.append(Frame(cam.name, t.trigger, self.sensors[cam.name].record(rad)))
            out[cam.name] = frames
        return out

    def _image_shift(self, cam: Camera, disp: np.ndarray) -> tuple[float, float]:
        """Pixel shift of the head centre when it moves by ``disp`` (world metres)."""
        c = np.zeros(3)
        uv0, _ = cam.project(c[None])
        uv1, _ = cam.project((c + disp)[None])
        d = uv1[0] - uv0[0]
        return float(d[0]), float(d[1])

