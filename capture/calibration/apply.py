"""Record calibration results in a capture folder's manifest (applied by the reader on load).

:func:`apply_to_capture` replaces the cameras' geometry (``K``, ``dist``, ``R``, ``t``)
and/or ``radiometry`` blocks in ``manifest.json`` and appends a ``calibration`` record
(what, from where, when, the accuracy report). The previous manifest is kept as
``manifest.<UTC time>.json`` — nothing is silently overwritten — and the new one is
written atomically. :class:`mifacerf.formats.capture.Capture` then applies the
radiometry to every image it returns.
"""
from __future__ import annotations

import json
import shutil
import time
from pathlib import Path

from ...camera import Camera
from ...formats.capture import CaptureError, Radiometry
from ...formats.files import write_json_atomic


def apply_to_capture(capture_root, *, geometry: dict | None = None, radiometry: dict | None = None,
                     source: str = "") -> Path:
    """Write ``geometry`` (a ``mifacerf.geometric-calibration`` dict) and/or ``radiometry``
    (a ``mifacerf.radiometric-calibration`` dict) into the capture's manifest. Returns the backup path."""
    root = Path(capture_root)
    mpath = root / "manifest.json"
    if not mpath.exists():
        raise CaptureError(f"{mpath}: missing; calibrations are applied to complete captures")
    manifest = json.loads(mpath.read_text())
    cams = {c["name"]: c for c in manifest["rig"]["cameras"]}
    record = {"time": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "source": source}
    if geometry is not None:
        found = {c["camera"]["name"]: c for c in geometry["cameras"]}
        missing = sorted(set(cams) - set(found))
        if missing:
            raise CaptureError(f"the geometric calibration has no cameras {missing}")
        for name, entry in cams.items():
            cam = Camera.from_dict(found[name]["camera"])
            if (cam.width, cam.height) != (entry["width"], entry["height"]):
                cam = cam.resized(entry["width"], entry["height"])
            entry.update({k: v for k, v in cam.to_dict().items() if k != "name"})
        record["geometry"] = {"method": geometry.get("method"), "rms_px": geometry.get("rms_px"),
                              "world": geometry.get("world")}
    if radiometry is not None:
        missing = sorted(set(cams) - set(radiometry["cameras"]))
        if missing:
            raise CaptureError(f"the radiometric calibration has no cameras {missing}")
        for name, entry in cams.items():
            entry["radiometry"] = Radiometry.from_dict(radiometry["cameras"][name]).to_dict()
        record["radiometry"] = {"method": radiometry.get("method"), "report": radiometry.get("report")}
    manifest.setdefault("calibration", []).append(record)
    stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
    backup = root / f"manifest.{stamp}.json"
    n = 1
    while backup.exists():
        backup = root / f"manifest.{stamp}.{n}.json"
        n += 1
    shutil.copy2(mpath, backup)
    write_json_atomic(mpath, manifest)
    return backup
