"""Simulated chart captures for radiometric calibration (paper §2.1: "a lighting dataset of a
grayscale chart"), recorded through each camera's :class:`~.cameras.SensorModel`.

The charts (:mod:`mifacerf.capture.calibration.charts`) hang upright at the stage
centre facing the cameras (+Z). Patches are Lambertian: a patch of reflectance ``ρ``
lit by light ``l`` has radiance ``ρ ⊙ E_l · max(0, ω_l · Z) / π`` in every direction.

:func:`write_chart_dataset` writes, for every camera: the grey chart under every
light of the stage (``grey_olat``), the grey chart at several exposures under the
most frontal light (``grey_exposures``), and the ColorChecker under the three most
frontal lights (``colorchecker``); ``charts.json`` describes it (the format
``mifacerf calibrate response`` reads), ``truth.json`` holds the sensors' true
radiometry for evaluation.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ...camera import Camera, cameras_focus
from ...formats.files import write_json_atomic
from ...imageio import write_exr
from ...rig import Rig
from ..calibration.charts import (COLORCHECKER_LAYOUT, FRAME_REFLECTANCE, GREY_LAYOUT, ChartLayout,
                                  colorchecker_reference, grey_reference)
from .cameras import SensorModel

CHART_R = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])  # chart -> world, facing +Z


def chart_pose(layout: ChartLayout, centre=(0.0, 0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    w, h = layout.size
    return CHART_R, np.asarray(centre, np.float64) - CHART_R @ np.array([w / 2, h / 2, 0.0])


def project_corners(camera: Camera, layout: ChartLayout, pose) -> np.ndarray:
    R, t = pose
    c3 = np.concatenate([layout.corners(), np.zeros((4, 1))], axis=1)
    uv, _ = camera.project(c3 @ R.T + t)
    return uv


def render_chart(camera: Camera, layout: ChartLayout, reflectance: np.ndarray, pose, light_dir: np.ndarray,
                 irradiance: np.ndarray, supersample: int = 3) -> np.ndarray:
    """(H, W, 3) radiance of the chart (patches ``reflectance`` (P, 3) linear sRGB) seen by ``camera``."""
    R, t = pose
    s = supersample
    off = (np.arange(s) + 0.5) / s - 0.5
    jj, ii = np.meshgrid(np.arange(camera.width), np.arange(camera.height))
    u = (jj[..., None, None] + off[None, None, None, :]).repeat(s, axis=2)
    v = (ii[..., None, None] + off[None, None, :, None]).repeat(s, axis=3)
    o, d = camera.pixel_rays(np.stack([u, v], axis=-1).reshape(-1, 2))
    n = R[:, 2]
    denom = d @ n
    lam = ((t - o) @ n) / np.where(np.abs(denom) > 1e-12, denom, np.nan)
    p = o[None] + lam[:, None] * d
    xy = (p - t) @ R  # chart frame
    w, h = layout.size
    on = (lam > 0) & (xy[:, 0] >= 0) & (xy[:, 0] <= w) & (xy[:, 1] >= 0) & (xy[:, 1] <= h)
    pid = layout.patch_at(xy[:, :2])
    rho = np.zeros((len(d), 3))
    rho[on] = FRAME_REFLECTANCE
    sel = on & (pid >= 0)
    rho[sel] = np.asarray(reflectance)[pid[sel]]
    cos = max(0.0, float(np.asarray(light_dir) @ -n))
    rad = rho * np.asarray(irradiance)[None] * cos / np.pi
    return rad.reshape(camera.height, camera.width, s, s, 3).mean(axis=(2, 3)).astype(np.float32)


def frontal_lights(rig: Rig, k: int) -> np.ndarray:
    """The ``k`` lights most nearly facing the chart (largest +Z component)."""
    return np.argsort(-rig.lights.directions[:, 2])[:k]


def write_chart_dataset(root, rig: Rig, sensors: dict[str, SensorModel], *, exposures=(0.25, 0.5, 1.0, 2.0, 4.0), olat_exposure: float = 1.6,
                        olat_lights=None, log=None) -> Path:
    """Render and write the chart captures of every camera of ``rig`` into ``root``; ``log(camera name)``
    after each camera."""
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    grey_names, grey_y = grey_reference()
    grey_rgb = np.repeat(grey_y[:, None], 3, axis=1)
    cc_names, cc_rgb = colorchecker_reference()
    focus = cameras_focus(rig.cameras)   # held where the cameras look
    gpose, cpose = chart_pose(GREY_LAYOUT, focus), chart_pose(COLORCHECKER_LAYOUT, focus)
    L = rig.lights
    olat = np.arange(len(L)) if olat_lights is None else np.asarray(olat_lights, np.int64)
    olat = olat[L.directions[olat, 2] > 0.05]  # lights behind the chart leave it dark
    front = frontal_lights(rig, 3)
    sets = {"grey_olat": [{"light": int(l), "exposure": olat_exposure} for l in olat],
            "grey_exposures": [{"light": int(front[0]), "exposure": float(e)} for e in exposures],
            "colorchecker": [{"light": int(l), "exposure": 1.0} for l in front]}
    charts = {"grey_olat": "grey", "grey_exposures": "grey", "colorchecker": "colorchecker"}
    layouts = {"grey": GREY_LAYOUT, "colorchecker": COLORCHECKER_LAYOUT}
    poses = {"grey": gpose, "colorchecker": cpose}
    refl = {"grey": grey_rgb, "colorchecker": cc_rgb}
    for cam in rig.cameras:
        sensor = sensors[cam.name]
        for set_name, entries in sets.items():
            chart = charts[set_name]
            for k, e in enumerate(entries):
                rad = render_chart(cam, layouts[chart], refl[chart], poses[chart], L.directions[e["light"]],
                                   L.irradiance[e["light"]])
                img = sensor.record(rad * e["exposure"])
                path = root / set_name / cam.name / f"{k:03d}.exr"
                path.parent.mkdir(parents=True, exist_ok=True)
                write_exr(path, img)
        if log:
            log(cam.name)
    desc = {
        "format": "mifacerf.chart-captures", "version": 1,
        "rig": rig.to_dict(),
        "charts": {"grey": {"layout": GREY_LAYOUT.to_dict(), "patches": grey_names,
                            "reference": "ColorChecker24 neutral row (colour-science)",
                            "pose": {"R": gpose[0].tolist(), "t": gpose[1].tolist()}},
                   "colorchecker": {"layout": COLORCHECKER_LAYOUT.to_dict(), "patches": cc_names,
                                    "reference": "ColorChecker24 - After November 2014 (colour-science)",
                                    "pose": {"R": cpose[0].tolist(), "t": cpose[1].tolist()}}},
        "corners": {chart: {cam.name: project_corners(cam, layouts[chart], poses[chart]).tolist()
                            for cam in rig.cameras} for chart in layouts},
        "sets": {name: {"chart": charts[name], "images": entries, "pattern": name + "/{camera}/{index:03d}.exr"}
                 for name, entries in sets.items()},
    }
    write_json_atomic(root / "charts.json", desc)
    truth = {c.name: sensors[c.name].true_radiometry().to_dict() for c in rig.cameras}
    (root / "truth.json").write_text(json.dumps({"cameras": truth}, indent=1))
    return root
