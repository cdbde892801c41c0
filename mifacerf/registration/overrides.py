"""Hand fixes of registered fiducials: ``CAPTURE/hand/overrides.json`` (written by ``mifacerf studio``).

A user who sees a fiducial registered to the wrong dot (or not at all) drags its projection onto the
right dot in one or more views. The fix is kept here and honoured by every later registration of that
expression: the fiducial is placed from the user's clicks, marked registered (status 1), listed in the
expression's report as ``hand_fixed``, and never moved by the snap::

    {"format": "mifacerf.registration_overrides", "version": 1,
     "expressions": {"smile": {"123": {"clicks": {"cam0": [u, v], "cam2": [u, v]},
                                       "position": [x, y, z]}}}}

Keys are template vertex ids. With clicks in two or more views the point is triangulated from them
(through the calibrated, distorted cameras); with one click, or none, ``position`` is used (the
studio puts a one-view fix on that view's ray at the registered depth). World frame, metres; pixels in
OpenCV convention (docs/conventions.md).
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

FORMAT = "mifacerf.registration_overrides"
VERSION = 1
FILENAME = "overrides.json"


def overrides_path(capture_root: str | Path) -> Path:
    return Path(capture_root) / "hand" / FILENAME


def read_overrides(capture_root: str | Path) -> dict:
    """The whole document (an empty one when the file is absent); ``ValueError`` naming the file if unusable."""
    path = overrides_path(capture_root)
    if not path.exists():
        return {"format": FORMAT, "version": VERSION, "expressions": {}}
    try:
        d = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path}: unreadable ({exc})") from exc
    if d.get("format") != FORMAT:
        raise ValueError(f"{path}: not a {FORMAT} document (format={d.get('format')!r})")
    d.setdefault("expressions", {})
    return d


def fixed_positions(capture_root: str | Path, expression: str, cameras: list, n_vertices: int,
                    problems: list | None = None) -> dict:
    """{vertex id: (3,) world position} of the hand-fixed vertices of ``expression``.

    ``cameras``: the rig's :class:`~mifacerf.camera.Camera` list (clicks naming another camera are
    ignored); ids outside the template's ``n_vertices`` are skipped. Unusable entries are skipped and described in ``problems``."""
    from ..geometry.triangulate import triangulate

    problems = [] if problems is None else problems
    try:
        doc = read_overrides(capture_root)
    except ValueError as exc:
        problems.append(str(exc))
        return {}
    names = [c.name for c in cameras]
    out = {}
    for key, item in (doc["expressions"].get(expression) or {}).items():
        try:
            vid = int(key)
        except ValueError:
            problems.append(f"{FILENAME}: {expression}: bad vertex id {key!r}")
            continue
        if not 0 <= vid < n_vertices:
            problems.append(f"{FILENAME}: {expression}: vertex id {vid} out of range (template has {n_vertices})")
            continue
        clicks = {c: np.asarray(uv, np.float64).reshape(2) for c, uv in (item.get("clicks") or {}).items()
                  if c in names}
        clicks = {c: uv for c, uv in clicks.items() if np.isfinite(uv).all()}
        if len(clicks) >= 2:
            uv = np.full((len(cameras), 1, 2), np.nan)
            for c, p in clicks.items():
                uv[names.index(c), 0] = p
            tr = triangulate(cameras, uv)
            if tr.ok[0]:
                out[vid] = tr.points[0]
                continue
        pos = item.get("position")
        if pos is not None and np.isfinite(np.asarray(pos, np.float64)).all() and len(pos) == 3:
            out[vid] = np.asarray(pos, np.float64)
        else:
            problems.append(f"{FILENAME}: {expression}/{vid}: neither two clicks nor a position")
    return out
