"""The Python API: load a model, render the face, composite it into a plate.

::

    import mifacerf as mf
    face = mf.load_model("model")
    rgba = face.render("smile=0.6,neutral=0.4", camera="cam1", env="sky")   # named weights
    rgba = face.render(mesh=target_vertices, camera=(20, 5), env="interior")  # any mesh, §5 weights
    rgb = mf.composite(rgba, mf.environment_plate("interior", face.camera((20, 5))))

Expressions: a captured expression's name, ``"name=w,name=w"`` or a dict — a linear
blend of the captured geometries and reflectance fields with the same weights at
every vertex (paper §4.3); or ``mesh=`` any (T, 3) target in the template's topology
(world, metres), blended per vertex and region with the §5 weights. Cameras: a
:class:`~mifacerf.camera.Camera`, a capture camera's name, or ``(yaw, pitch)`` degrees
on the capture cameras' ring. Environments: a generated name (sky, sunsky, interior,
gradient), a lat-long .exr/.hdr path, or an :class:`~mifacerf.environment.Environment`.
"""
from __future__ import annotations

import numpy as np

from ..camera import Camera, ring_camera
from ..environment import Environment, resolve
from ..variant import ensure_plugins
from .model import Model
from .pose_blend import blend_geometry
from .renderer import Renderer, RenderStats


def parse_weights(spec, names: list[str]) -> dict[str, float]:
    """``"smile"`` | ``"smile=0.6,neutral=0.4"`` | dict → {name: weight}, validated, normalised to sum 1."""
    if isinstance(spec, str):
        if "=" in spec:
            out = {}
            for item in spec.split(","):
                k, v = item.split("=", 1)
                out[k.strip()] = float(v)
        else:
            out = {spec.strip(): 1.0}
    else:
        out = {str(k): float(v) for k, v in dict(spec).items()}
    unknown = [k for k in out if k not in names]
    if unknown:
        raise KeyError(f"unknown expression(s) {', '.join(unknown)}; the model has: {', '.join(names)}")
    if any(not np.isfinite(v) or v < 0 for v in out.values()):
        raise ValueError("expression weights must be finite and non-negative")
    total = sum(out.values())
    if total <= 0:
        raise ValueError("expression weights must have a positive sum")
    return {k: v / total for k, v in out.items() if v > 0}


class FaceModel:
    """A model opened for rendering (fields load lazily; a warm model keeps them cached)."""

    def __init__(self, path, cache_bytes: int = 4 << 30):
        self.model = Model(path, cache_bytes=cache_bytes)
        self.renderer = Renderer(self.model)
        self._envs: dict[str, Environment] = {}

    def use_method(self, method: str = "exact", rank: int | None = None) -> "FaceModel":
        """Light this model's fields by ``method`` (a :data:`.compression.COMPRESSION_METHODS` name) at
        ``rank`` from now on (a new :attr:`renderer`); returns self. A compressed method needs the copy
        ``mifacerf compress`` writes: a ValueError names the command when the model does not list it."""
        from .compression import compression_method

        m = compression_method(method)
        if m.compress is None:
            if rank is not None:
                raise ValueError(f"the {method!r} method takes no rank (got --rank {rank})")
            if self.renderer.method != method:   # the renderer it has already lights so: kept, warm
                self.renderer = Renderer(self.model)
            return self
        have = sorted(self.model.meta.get("compressed", {}).get(method, []))
        if rank is None or int(rank) not in have:
            wanted = "a rank" if rank is None else f"rank {rank}"
            listed = f"it holds {method} ranks {', '.join(map(str, have))}" if have else f"it holds no {method} copy"
            raise ValueError(f"{self.model.root}: {wanted} of the {method!r} method is needed and {listed} "
                             f"(mifacerf compress {self.model.root} --method {method} --rank {rank or 'K'})")
        if (self.renderer.method, self.renderer.rank) != (method, int(rank)):
            self.renderer = Renderer(self.model, method=method, rank=int(rank))
        return self

    @property
    def expressions(self) -> list[str]:
        return list(self.model.expressions)

    def camera(self, camera=None, size: int | None = None) -> Camera:
        m = self.model
        if camera is None:
            cam = m.cameras[min(1, len(m.cameras) - 1)]
        elif isinstance(camera, Camera):
            cam = camera
        elif isinstance(camera, str):
            cam = m.cameras[m.camera_index(camera)]
        else:
            yaw, pitch = camera
            cam = ring_camera(m.cameras, float(yaw), float(pitch))
        return cam if size is None else cam.resized(size, size)

    def environment(self, env) -> Environment:
        if isinstance(env, Environment):
            return env
        key = str(env)
        if key not in self._envs:
            self._envs[key] = resolve(key)
        return self._envs[key]

    def target(self, expression=None, mesh=None) -> tuple[np.ndarray, np.ndarray]:
        """(target vertices (T, 3), per-vertex expression weights (T, S))."""
        m = self.model
        if (expression is None) == (mesh is None):
            raise ValueError("give exactly one of an expression (name / weights) or a target mesh")
        if mesh is not None:
            mesh = np.asarray(mesh, np.float64)
            if mesh.shape != (m.n_vertices, 3):
                raise ValueError(f"target mesh has shape {mesh.shape}; the template has ({m.n_vertices}, 3)")
            if not np.isfinite(mesh).all():
                raise ValueError("target mesh has NaN/Inf vertices")
            return mesh, m.blend.dense_weights(mesh[None])[0]
        w = parse_weights(expression, m.expressions)
        W = np.zeros((m.n_vertices, len(m.expressions)))
        for name, wt in w.items():
            W[:, m.expression_index(name)] = wt
        # the faces blended in their head frames, the head poses as rigid motions (issue 16: blends that turn the head)
        geometry, head = blend_geometry(m.vertices, m.head_pose, {m.expression_index(n): wt for n, wt in w.items()})
        self._blended_head = (tuple(w.items()), head)   # parts() of the same blend reuses it (one expm a frame)
        return geometry, W

    def parts(self, expression=None, mesh=None) -> dict:
        """Eye and teeth transforms {part: 4x4 rest→world} of a blend of captured expressions or of a mesh."""
        from .parts import target_parts_from_mesh
        from .pose_blend import blend_parts

        if not self.model.references:
            return {}
        if mesh is not None:
            return target_parts_from_mesh(self.model, np.asarray(mesh, np.float64))
        w = parse_weights(expression, self.model.expressions)
        last = getattr(self, "_blended_head", None)
        return blend_parts(self.model, w, head=last[1] if last is not None and last[0] == tuple(w.items()) else None)

    def render(self, expression=None, *, mesh=None, camera=None, env="sky", spp: int = 4, size: int | None = None,
               stats: RenderStats | None = None, seed: int = 0, parts: dict | None = None,
               eyes_teeth: bool = True) -> np.ndarray:
        """(H, W, 4) float32 RGBA, linear sRGB, premultiplied by coverage.

        ``parts`` overrides the eye/teeth transforms (e.g. from tracking); ``eyes_teeth=False``
        renders the skin only.
        """
        target, W = self.target(expression, mesh)
        if eyes_teeth and parts is None:
            parts = self.parts(expression, mesh)
        return self.renderer.render(target, W, self.camera(camera, size), self.environment(env), spp=spp,
                                    seed=seed, stats=stats, parts=parts if eyes_teeth else None)


def load_model(path, cache_bytes: int = 4 << 30) -> FaceModel:
    """Open a model folder written by ``mifacerf build`` (and register mifacerf's Mitsuba plugins)."""
    ensure_plugins()
    return FaceModel(path, cache_bytes)


def environment_plate(env, camera: Camera) -> np.ndarray:
    """The environment itself as seen by ``camera`` (H, W, 3): a background plate for :func:`composite`."""
    env = resolve(env) if isinstance(env, str) else env
    jj, ii = np.meshgrid(np.arange(camera.width), np.arange(camera.height))
    _, d = camera.pixel_rays(np.stack([jj, ii], -1).reshape(-1, 2).astype(np.float64))
    return env.lookup(d).reshape(camera.height, camera.width, 3).astype(np.float32)


def composite(rgba: np.ndarray, plate: np.ndarray) -> np.ndarray:
    """Premultiplied RGBA over a plate: ``rgb + (1 − alpha) · plate`` → (H, W, 3)."""
    rgba = np.asarray(rgba, np.float32)
    plate = np.asarray(plate, np.float32)
    if rgba.ndim != 3 or rgba.shape[2] != 4:
        raise ValueError(f"expected an (H, W, 4) RGBA image, got {rgba.shape}")
    if plate.shape[:2] != rgba.shape[:2]:
        raise ValueError(f"plate is {plate.shape[1]}x{plate.shape[0]}, render is {rgba.shape[1]}x{rgba.shape[0]}")
    return rgba[..., :3] + (1.0 - rgba[..., 3:4]) * plate[..., :3]
