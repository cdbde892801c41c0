"""Synchronised cameras: the interface a capture session needs, and a registry of backends.

The strobe controller triggers every camera on each step of a sequence (60 Hz); a
camera delivers one :class:`Frame` per trigger it saw, stamped with the trigger
counter it received, so frames are matched to strobe events by counter, never by
arrival order. A camera that missed a trigger simply has no frame for it.

Backends implement :class:`CameraSystem` and register a factory under a name in
:data:`CAMERA_BACKENDS` (or through the ``mifacerf.camera_backends`` entry point
group, so a real backend can live in its own package). The synthetic backend
(:mod:`mifacerf.capture.simulation.cameras`) renders the synthetic subject lit by
whatever light the simulated controller actually fired.
"""
from __future__ import annotations

import abc
from dataclasses import dataclass
from typing import Callable

import numpy as np

from ...camera import Camera
from ...errors import MifacerfError


@dataclass
class Frame:
    """One image from one camera: ``image`` (H, W, 3) float32 as recorded (linear camera RGB,
    uncalibrated), ``trigger`` the controller's trigger counter stamped on it."""

    camera: str
    trigger: int
    image: np.ndarray


class CameraError(MifacerfError, RuntimeError):
    """A camera failed (not connected, stopped delivering frames)."""


class CameraSystem(abc.ABC):
    """A set of cameras that record one frame per hardware trigger.

    Use: :meth:`start` with the number of triggers about to come, run the strobe
    sequence, then :meth:`collect` the frames. ``cameras`` are the cameras' current
    geometric calibration (:class:`mifacerf.camera.Camera`, names are the capture
    folder's camera names).
    """

    cameras: list[Camera]

    @property
    def names(self) -> list[str]:
        return [c.name for c in self.cameras]

    @abc.abstractmethod
    def start(self, n_triggers: int) -> None:
        """Arm every camera for the next ``n_triggers`` triggers."""

    @abc.abstractmethod
    def collect(self, timeout: float = 10.0, expected: int | None = None) -> dict[str, list[Frame]]:
        """The frames recorded since :meth:`start`, per camera name (any order; match by ``trigger``).

        Waits up to ``timeout`` seconds for ``expected`` triggers' frames (default: the number
        given to :meth:`start`); the controller says how many triggers it actually sent.
        """

    def close(self) -> None:
        """Release the cameras."""

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


#: name -> factory(**options) -> CameraSystem
CAMERA_BACKENDS: dict[str, Callable[..., CameraSystem]] = {}


def register_backend(name: str, factory: Callable[..., CameraSystem]) -> None:
    CAMERA_BACKENDS[name] = factory


def camera_backend(name: str, **options) -> CameraSystem:
    """Instantiate the camera backend ``name`` (built-in or from the ``mifacerf.camera_backends`` entry points)."""
    if name not in CAMERA_BACKENDS:
        from importlib.metadata import entry_points

        for ep in entry_points(group="mifacerf.camera_backends"):
            if ep.name == name:
                CAMERA_BACKENDS[name] = ep.load()
    try:
        factory = CAMERA_BACKENDS[name]
    except KeyError:
        raise CameraError(f"no camera backend named {name!r}; available: {', '.join(sorted(CAMERA_BACKENDS)) or 'none'} "
                          "(real cameras register through the 'mifacerf.camera_backends' entry point group)") from None
    return factory(**options)
