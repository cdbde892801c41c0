"""Ground truth of a synth output: any parameter vector, camera and environment, path-traced.

Evaluation's window onto the synthetic subject (``OUT/truth`` and the subject's generator):
nothing in registration, model building or rendering may use it.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..camera import Camera, ring_camera
from ..formats.capture import Capture
from ..environment import Environment, resolve
from .synth import read_truth, subject_from_truth
from .truth import render_truth


class TruthRenderer:
    """Renders the subject of a ``mifacerf synth`` output folder.

    ``subject``: the synthetic subject; ``truth``: ``truth.json``; ``cameras``: the capture's cameras.
    """

    def __init__(self, subject, truth: dict, cameras: list[Camera], dots: bool = False):
        # the model renders dot-free faces (the dots are removed from its data), so by default the
        # ground truth shows the subject with its dots washed off
        self.subject = subject if dots or not hasattr(subject, "without_dots") else subject.without_dots()
        self.truth = truth
        self.cameras = cameras
        self.controls = [c.name for c in subject.controls]
        self.expressions = {e["name"]: np.asarray(e["params"], np.float64) for e in truth["expressions"]}
        self._scenes: dict[str, object] = {}

    @classmethod
    def from_synth(cls, out, dots: bool = False) -> "TruthRenderer":
        out = Path(out)
        truth = read_truth(out)
        cap = Capture(out / "capture")
        return cls(subject_from_truth(out, cap.rig.cameras), truth, cap.rig.cameras, dots=dots)

    # ------------------------------------------------------------- parameters
    def params_from_spec(self, spec: str, is_params: bool = False) -> np.ndarray:
        """``name`` | ``name=w,name=w`` (a blend of captured parameter vectors) | ``control=value,...``."""
        if is_params:
            named = dict(_pairs(spec))
            unknown = [k for k in named if k not in self.controls]
            if unknown:
                raise KeyError(f"unknown control(s) {', '.join(unknown)}; controls: {', '.join(self.controls)}")
            return self.subject.params(**named)
        if "=" not in spec:
            if spec not in self.expressions:
                raise KeyError(f"unknown expression {spec!r}; captured: {', '.join(self.expressions)}")
            return self.expressions[spec].copy()
        return self.blend(dict(_pairs(spec)))

    def blend(self, weights: dict[str, float]) -> np.ndarray:
        """The weighted sum of captured parameter vectors (weights normalised to sum to 1)."""
        unknown = [k for k in weights if k not in self.expressions]
        if unknown:
            raise KeyError(f"unknown expression(s) {', '.join(unknown)}")
        total = sum(weights.values())
        if total <= 0:
            raise ValueError("blend weights must have a positive sum")
        return sum(w / total * self.expressions[k] for k, w in weights.items())

    # ---------------------------------------------------------------- cameras
    def camera(self, name: str | None = None, yaw: float | None = None, pitch: float = 0.0,
               size: int | None = None) -> Camera:
        """A capture camera by name, or a novel pinhole camera at (yaw, pitch) degrees on the capture ring."""
        base = self.cameras[min(1, len(self.cameras) - 1)]
        if yaw is None:
            cam = base if name is None else next((c for c in self.cameras if c.name == name), None)
            if cam is None:
                raise KeyError(f"no camera {name!r}; cameras: {', '.join(c.name for c in self.cameras)}")
        else:
            cam = ring_camera(self.cameras, yaw, pitch)
        return cam if size is None else cam.resized(size, size)

    # ----------------------------------------------------------------- render
    def scene(self, env: Environment, objects: dict | None = None):
        """The subject's scene under ``env``; ``objects`` {name: Mitsuba dict}: extra shapes and emitters in it
        (a hat, a sun), one scene per distinct set."""
        from . import SubjectScene

        key = env.name if not objects else (env.name, repr(sorted((k, repr(v)) for k, v in objects.items())))
        if key not in self._scenes:
            self._scenes[key] = SubjectScene(self.subject, extra={"env": env.mitsuba_dict(), **(objects or {})})
        return self._scenes[key]

    def render(self, params: np.ndarray, camera: Camera, env: str | Environment = "sky", spp: int = 256,
               seed: int = 0, objects: dict | None = None) -> np.ndarray:
        """(H, W, 4) RGBA path-traced ground truth (``objects``: extra shapes and emitters, :meth:`scene`)."""
        env = resolve(env) if isinstance(env, str) else env
        sc = self.scene(env, objects)
        sc.set_pose(self.subject.pose(np.asarray(params, np.float64)))
        return render_truth(sc.scene, camera, spp=spp, seed=seed)


def _pairs(spec: str):
    for item in spec.split(","):
        if not item.strip():
            continue
        if "=" not in item:
            raise ValueError(f"expected name=value in {spec!r}")
        k, v = item.split("=", 1)
        yield k.strip(), float(v)


def truth_expression(out, name: str) -> dict:
    """The stored truth arrays of one captured expression (evaluation only)."""
    path = Path(out) / "truth" / "expressions" / f"{name}.npz"
    if not path.exists():
        raise FileNotFoundError(f"{path}: no truth for expression {name!r}")
    return dict(np.load(path))


__all__ = ["TruthRenderer", "truth_expression"]
