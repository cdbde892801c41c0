"""Radiometric calibration of the cameras from chart captures (paper §2.1), method by name.

Input: a chart-capture folder (``charts.json``, see
:mod:`mifacerf.capture.simulation.charts` for the layout; a real one holds the same
with photographs and hand-clicked chart corners). Per camera:

1. **Response curve** by :func:`.debevec1997.recover_response`, from
   ``method="grey_olat"`` (the grey chart under every light: unknown irradiance per
   light, known patch reflectances — the paper's "lighting dataset of a grayscale
   chart") or ``method="exposures"`` (the grey chart at known exposure times:
   unknown patch radiance — Debevec & Malik's original setting).
2. **Colour matrix and exposure** from the ColorChecker (:mod:`.colour_correction`).

Output: a :class:`mifacerf.formats.capture.Radiometry` per camera (``exposure``,
``colour_matrix``, ``response``) plus a report (CIEDE2000 of the corrected checker,
the response fit's residual), as the JSON ``mifacerf calibrate response`` writes and
``mifacerf capture --radiometry`` / ``--apply`` record in a capture's manifest.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ...formats.capture import Radiometry
from ...imageio import read_exr
from ...rig import Rig
from .charts import ChartLayout, colorchecker_reference, grey_reference, patch_means
from .colour_correction import delta_e2000, factor_exposure, fit_colour_matrix
from .debevec1997 import ResponseError, recover_response
from ...errors import MifacerfError



class RadiometryError(MifacerfError, ValueError):
    """A chart-capture folder that is missing something, or data too poor to calibrate."""


@dataclass
class CameraRadiometry:
    radiometry: Radiometry
    delta_e: np.ndarray          # (24,) CIEDE2000 of the corrected checker patches
    response_residual: float     # rms of the response fit, in ln units

    def report(self) -> dict:
        return {"delta_e2000_mean": float(np.mean(self.delta_e)), "delta_e2000_max": float(np.max(self.delta_e)),
                "delta_e2000": np.round(self.delta_e, 3).tolist(), "response_residual_ln": self.response_residual}


def _load(root: Path) -> dict:
    p = root / "charts.json"
    if not p.exists():
        raise RadiometryError(f"{p}: missing; not a chart-capture folder")
    d = json.loads(p.read_text())
    if d.get("format") != "mifacerf.chart-captures":
        raise RadiometryError(f"{p}: not a chart-capture description")
    return d


def _measure(root: Path, desc: dict, set_name: str, camera: str) -> tuple[np.ndarray, list[dict]]:
    """Patch means (N images, P patches, 3) of one image set for one camera."""
    s = desc["sets"].get(set_name)
    if s is None:
        raise RadiometryError(f"{root}: no image set {set_name!r} (have {sorted(desc['sets'])})")
    chart = desc["charts"][s["chart"]]
    layout = ChartLayout(**chart["layout"])
    try:
        corners = np.asarray(desc["corners"][s["chart"]][camera], np.float64)
    except KeyError:
        raise RadiometryError(f"{root}: no chart corners for camera {camera!r} ({s['chart']})") from None
    out = []
    for k, _ in enumerate(s["images"]):
        img = read_exr(root / s["pattern"].format(camera=camera, index=k), channels=3)
        means, counts = patch_means(img, corners, layout)
        if np.any(counts < 3):
            raise RadiometryError(f"{set_name}/{camera}/{k:03d}: chart patches cover too few pixels "
                                  f"({counts.min()}); move the chart closer or check its corners")
        out.append(means)
    return np.asarray(out), s["images"]


def _grey_olat(root: Path, desc: dict, camera: str):
    """Response data ``grey_olat``: the grey chart under every light (known patch reflectances)."""
    _, grey = grey_reference()
    z, _ = _measure(root, desc, "grey_olat", camera)              # (N lights, 6 patches, 3)
    z = np.transpose(z, (0, 2, 1)).reshape(-1, z.shape[1])       # rows: (light, channel)
    return z, np.log(grey), 1


def _exposures(root: Path, desc: dict, camera: str):
    """Response data ``exposures``: the grey chart at known exposure times (unknown patch radiance)."""
    z, entries = _measure(root, desc, "grey_exposures", camera)  # (N exposures, 6, 3)
    z = np.transpose(z, (1, 2, 0)).reshape(-1, z.shape[0])       # rows: (patch, channel), cols: exposures
    return z, np.log([e["exposure"] for e in entries]), 1


#: where the response curve's data come from: name → f(root, chart description, camera) →
#: (pixel values z, log of the known factor, its axis) for :func:`.debevec1997.recover_response`;
#: the first is the default
RESPONSE_METHODS = {"grey_olat": _grey_olat, "exposures": _exposures}
DEFAULT_RESPONSE_METHOD = "grey_olat"


def response_data(root: Path, desc: dict, camera: str, method: str = DEFAULT_RESPONSE_METHOD):
    """The response curve's data for ``camera`` by ``method`` (:data:`RESPONSE_METHODS`)."""
    from ...methods import lookup

    return lookup(RESPONSE_METHODS, method, "response")(root, desc, camera)


def calibrate_camera(root, camera: str, *, method: str = DEFAULT_RESPONSE_METHOD, n_knots: int = 33,
                     smoothness: float = 1.0) -> CameraRadiometry:
    """Response curve, exposure and colour matrix of ``camera`` from the chart captures in ``root``."""
    root = Path(root)
    desc = _load(root)
    rig = Rig.from_dict(desc["rig"])
    z, log_known, axis = response_data(root, desc, camera, method)
    try:
        curve = recover_response(z, log_known, axis, n_knots=n_knots, smoothness=smoothness)
    except ResponseError as exc:
        raise RadiometryError(f"camera {camera}: {exc}") from exc
    response = {"x": curve["x"], "y": curve["y"]}
    # --- colour matrix from the ColorChecker under each of its lights
    zc, entries = _measure(root, desc, "colorchecker", camera)        # (K, 24, 3)
    _, ref = colorchecker_reference()
    R = np.asarray(desc["charts"]["colorchecker"]["pose"]["R"])
    normal = -R[:, 2]
    cams, targets, whites = [], [], []
    for k, e in enumerate(entries):
        l = e["light"]
        cos = max(0.0, float(rig.lights.directions[l] @ normal))
        white = rig.lights.irradiance[l] * cos / np.pi * e["exposure"]  # radiance of a perfect white
        lin = np.interp(zc[k], response["x"], response["y"])
        cams.append(lin)
        targets.append(ref * white[None])
        whites.append(np.repeat(white[None], len(ref), axis=0))
    cams, targets, whites = np.concatenate(cams), np.concatenate(targets), np.concatenate(whites)
    unclipped = np.all(zc.reshape(-1, 3) < 0.98, axis=1)
    M_full = fit_colour_matrix(cams, targets, weights=unclipped.astype(float) + 1e-3)
    exposure, colour_matrix = factor_exposure(M_full)
    est = (cams @ M_full.T) / whites
    de = delta_e2000(np.clip(est, 0, None), ref[np.arange(len(est)) % len(ref)])
    de = de.reshape(len(entries), len(ref)).mean(axis=0)
    return CameraRadiometry(Radiometry(exposure, colour_matrix, response), de, curve["residual_rms"])


def calibrate_radiometry(root, cameras: list[str] | None = None, **kw) -> dict[str, CameraRadiometry]:
    """:func:`calibrate_camera` for every camera of the chart captures (or ``cameras``)."""
    root = Path(root)
    desc = _load(root)
    names = cameras or [c["name"] for c in desc["rig"]["cameras"]]
    return {c: calibrate_camera(root, c, **kw) for c in names}


def to_json(results: dict[str, CameraRadiometry], source: str, method: str) -> dict:
    return {"format": "mifacerf.radiometric-calibration", "version": 1, "source": source,
            "method": {"response": f"debevec1997/{method}", "colour": "ColorChecker24 least squares (colour-science)"},
            "cameras": {c: r.radiometry.to_dict() for c, r in results.items()},
            "report": {c: r.report() for c, r in results.items()}}
