"""The light stage: its lights and its cameras (paper §2).

Light stage (docs/conventions.md, "Directions"): a semicircular arm from the zenith
(+Y) to the nadir (−Y) carrying ``n_strobes`` strobes at polar angles
``θ_k = (k + ½)·π / n_strobes``, rotated about the vertical axis to ``n_positions``
azimuths ``φ_j = φ_0 + 2π j / n_positions``; azimuth is measured from +Z towards +X,
``ω = (sin θ sin φ, cos θ, sin θ cos φ)`` in **world**, pointing from the subject to the
light. Light index ``l = j · n_strobes + k``. The paper's stage: 30 strobes × 16
positions = 480 directions.

Per light: its direction, its solid angle (the area of its spherical-Voronoi cell,
scipy; the cells tile the sphere, Σ = 4π) and its irradiance calibration (RGB, the
irradiance the strobe delivers at the stage centre, relative units; images are
divided by it on load so that every light has unit irradiance).

Cameras (OpenCV conventions, :mod:`mifacerf.camera`) stand in front of the face, on a
sphere of radius ``distance`` about ``target``, at given yaw (about +Y, from +Z towards
+X) and pitch (up positive) angles.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .camera import Camera


def spherical_direction(theta, phi) -> np.ndarray:
    """Unit vectors (..., 3) in world for polar angle ``theta`` from +Y and azimuth ``phi`` from +Z to +X."""
    theta, phi = np.broadcast_arrays(np.asarray(theta, np.float64), np.asarray(phi, np.float64))
    s = np.sin(theta)
    return np.stack([s * np.sin(phi), np.cos(theta), s * np.cos(phi)], axis=-1)


def voronoi_solid_angles(directions: np.ndarray) -> np.ndarray:
    """Solid angle (sr) of each direction's spherical-Voronoi cell; (L, 3) → (L,), sums to 4π.

    Uses ``scipy.spatial.SphericalVoronoi``. Fewer than 4 directions, or directions
    that all lie on one great circle, have no proper Voronoi diagram: then the sphere is
    split evenly (documented fall-back, 4π / L each). Duplicate directions raise.
    """
    from scipy.spatial import SphericalVoronoi

    d = np.asarray(directions, np.float64)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    n = len(d)
    if n == 0:
        return np.zeros(0)
    if len(np.unique(np.round(d, 12), axis=0)) < n:
        raise ValueError("light directions contain duplicates; each light needs its own direction")
    if n < 4 or np.linalg.matrix_rank(d, tol=1e-9) < 3:
        return np.full(n, 4 * np.pi / n)
    try:
        sv = SphericalVoronoi(d, radius=1.0, center=np.zeros(3))
        areas = sv.calculate_areas()
    except Exception:  # qhull precision trouble on a degenerate layout
        return np.full(n, 4 * np.pi / n)
    if not np.all(np.isfinite(areas)) or abs(areas.sum() - 4 * np.pi) > 1e-6:
        return np.full(n, 4 * np.pi / n)
    return areas


@dataclass
class LightStage:
    """Lights of the stage. Arrays: ``directions`` (L, 3) world unit vectors towards the
    lights; ``solid_angles`` (L,) sr; ``irradiance`` (L, 3) RGB calibration; ``arm_position``
    and ``strobe`` (L,) int indices on the arm (−1 when not from an arm)."""

    directions: np.ndarray
    solid_angles: np.ndarray
    irradiance: np.ndarray
    arm_position: np.ndarray
    strobe: np.ndarray
    n_positions: int = 0
    n_strobes: int = 0

    def __post_init__(self):
        self.directions = np.asarray(self.directions, np.float64).reshape(-1, 3)
        n = len(self.directions)
        self.solid_angles = np.asarray(self.solid_angles, np.float64).reshape(n)
        self.irradiance = np.asarray(self.irradiance, np.float64).reshape(n, 3)
        self.arm_position = np.asarray(self.arm_position, np.int64).reshape(n)
        self.strobe = np.asarray(self.strobe, np.int64).reshape(n)
        norms = np.linalg.norm(self.directions, axis=1)
        if not np.allclose(norms, 1.0, atol=1e-6):
            raise ValueError("light directions must be unit vectors")
        if np.any(self.irradiance <= 0) or not np.isfinite(self.irradiance).all():
            raise ValueError("light irradiance calibration must be positive and finite")

    def __len__(self) -> int:
        return len(self.directions)

    @classmethod
    def semicircular_arm(cls, n_positions: int = 16, n_strobes: int = 30, azimuth_offset: float = 0.0,
                         irradiance_spread: float = 0.0, seed: int = 0) -> "LightStage":
        """The paper's stage, configurable in count.

        ``irradiance_spread`` > 0 draws each strobe's RGB irradiance as
        ``1 + spread·N(0, 1)`` (clipped to ±3σ) per channel, as a real, slightly
        uneven set of strobes would measure in calibration.
        """
        if n_positions < 1 or n_strobes < 1:
            raise ValueError("a light stage needs at least one arm position and one strobe")
        k = np.arange(n_strobes)
        j = np.arange(n_positions)
        theta = (k + 0.5) * np.pi / n_strobes
        phi = azimuth_offset + 2 * np.pi * j / n_positions
        jj, kk = np.meshgrid(j, k, indexing="ij")
        dirs = spherical_direction(theta[kk], phi[jj]).reshape(-1, 3)
        rng = np.random.default_rng(seed)
        irr = 1.0 + irradiance_spread * np.clip(rng.standard_normal((len(dirs), 3)), -3, 3)
        return cls(dirs, voronoi_solid_angles(dirs), irr, jj.ravel(), kk.ravel(),
                   n_positions, n_strobes)

    def subset(self, indices) -> "LightStage":
        """The stage restricted to ``indices`` (solid angles recomputed over the subset)."""
        idx = np.asarray(indices, np.int64)
        d = self.directions[idx]
        return LightStage(d, voronoi_solid_angles(d), self.irradiance[idx], self.arm_position[idx],
                          self.strobe[idx], self.n_positions, self.n_strobes)

    def to_dict(self) -> dict:
        return {
            "layout": {"kind": "semicircular_arm", "n_positions": self.n_positions,
                       "n_strobes": self.n_strobes},
            "lights": [
                {"index": i, "direction": self.directions[i].tolist(),
                 "solid_angle": float(self.solid_angles[i]),
                 "irradiance": self.irradiance[i].tolist(),
                 "arm_position": int(self.arm_position[i]), "strobe": int(self.strobe[i])}
                for i in range(len(self))
            ],
        }

    @classmethod
    def from_dict(cls, d: dict) -> "LightStage":
        lights = d["lights"]
        for i, e in enumerate(lights):
            if e.get("index", i) != i:
                raise ValueError(f"light entry {i} has index {e.get('index')}; lights must be listed in order")
        lay = d.get("layout", {})
        return cls([e["direction"] for e in lights], [e["solid_angle"] for e in lights],
                   [e.get("irradiance", [1.0, 1.0, 1.0]) for e in lights],
                   [e.get("arm_position", -1) for e in lights], [e.get("strobe", -1) for e in lights],
                   int(lay.get("n_positions", 0)), int(lay.get("n_strobes", 0)))


def camera_ring(yaw_pitch_deg, *, width: int, height: int, distance: float = 1.3,
                target=(0.0, -0.03, 0.04), face_height: float = 0.34, distortion_scale: float = 1.0,
                seed: int = 1) -> list[Camera]:
    """Cameras at the given (yaw, pitch) angles in degrees about ``target`` (world).

    Focal length frames ``face_height`` metres over the image height at ``distance``. The
    default framing (0.34 m about a point 3 cm below and 4 cm in front of the head's centre)
    keeps every fiducial of the synthetic subject, neck included, inside at least two frames.
    Each camera gets a small, seeded lens distortion and principal-point offset, as
    real zoom lenses have (``distortion_scale=0`` for ideal pinholes).
    """
    rng = np.random.default_rng(seed)
    target = np.asarray(target, np.float64)
    focal = (height / 2) / (face_height / 2 / distance)
    cams = []
    for i, (yaw, pitch) in enumerate(yaw_pitch_deg):
        yaw_r, pitch_r = np.radians(yaw), np.radians(pitch)
        offset = distance * np.array([np.sin(yaw_r) * np.cos(pitch_r), np.sin(pitch_r),
                                      np.cos(yaw_r) * np.cos(pitch_r)])
        dist = distortion_scale * np.array([-0.06 + 0.02 * rng.standard_normal(),
                                            0.03 * rng.standard_normal(),
                                            0.0005 * rng.standard_normal(),
                                            0.0005 * rng.standard_normal(), 0.0])
        pp = distortion_scale * rng.normal(0.0, 0.004 * width, size=2)
        cams.append(Camera.look_at(f"cam{i}", target + offset, target, width=width, height=height,
                                   focal=focal * (1 + 0.01 * distortion_scale * rng.standard_normal()),
                                   principal_offset=pp, dist=dist))
    return cams


#: Camera layouts (yaw, pitch) in degrees. Six cameras as in the paper: a 3 x 2 grid
#: in front of the face; three cameras: a triangle (still a proper 2-D triangulation).
CAMERA_LAYOUTS = {
    6: [(-40.0, 10.0), (0.0, 10.0), (40.0, 10.0), (-40.0, -10.0), (0.0, -10.0), (40.0, -10.0)],
    3: [(-35.0, -8.0), (0.0, 12.0), (35.0, -8.0)],
}


@dataclass
class Rig:
    """A light stage and its cameras."""

    lights: LightStage
    cameras: list[Camera] = field(default_factory=list)

    def camera(self, name: str) -> Camera:
        for c in self.cameras:
            if c.name == name:
                return c
        raise KeyError(f"no camera named {name!r} (have {[c.name for c in self.cameras]})")

    def to_dict(self) -> dict:
        return {"lights": self.lights.to_dict(), "cameras": [c.to_dict() for c in self.cameras]}

    @classmethod
    def from_dict(cls, d: dict) -> "Rig":
        return cls(LightStage.from_dict(d["lights"]), [Camera.from_dict(c) for c in d["cameras"]])


@dataclass(frozen=True)
class RigPreset:
    """Sizes of a simulated capture: light stage counts, cameras, image size, expressions, samples."""

    name: str
    n_positions: int
    n_strobes: int
    n_cameras: int
    resolution: int
    n_expressions: int
    spp: int

    def rig(self, irradiance_spread: float = 0.05) -> Rig:
        lights = LightStage.semicircular_arm(self.n_positions, self.n_strobes,
                                             irradiance_spread=irradiance_spread, seed=7)
        cams = camera_ring(CAMERA_LAYOUTS[self.n_cameras], width=self.resolution, height=self.resolution)
        return Rig(lights, cams)


#: ``tiny`` for tests (seconds), ``draft`` the demo default, ``paper`` the full rig of the paper.
#: ``draft`` stops the arm at the paper's 16 positions with 12 strobes (192 lights): on a
#: semicircular arm the lights crowd at the poles, and the arm's positions set the spacing
#: at the equator, where a face's key lights are. Measured (skin of a captured expression,
#: relit OLAT vs path-traced truth, sky / interior / gradient): 12 x 12 = 144 lights gave
#: 34.8 / 31.4 / 36.6 dB, 18 x 8 = 144 lights 35.4 / 34.3 / 36.8, 16 x 12 = 192 lights
#: 36.8 / 35.7 / 38.3, the paper's 16 x 30 = 480 lights 38.1 / 36.5 / 39.7 (README, "Where the error comes from").
PRESETS = {
    "tiny": RigPreset("tiny", n_positions=8, n_strobes=6, n_cameras=3, resolution=128, n_expressions=6, spp=4),
    "draft": RigPreset("draft", n_positions=16, n_strobes=12, n_cameras=6, resolution=256, n_expressions=24, spp=4),
    "paper": RigPreset("paper", n_positions=16, n_strobes=30, n_cameras=6, resolution=480, n_expressions=60, spp=9),
}


def preset(name: str) -> RigPreset:
    """The named :class:`RigPreset`; a clear error for unknown names."""
    try:
        return PRESETS[name]
    except KeyError:
        raise ValueError(f"unknown preset {name!r}; choose one of {', '.join(PRESETS)}") from None
