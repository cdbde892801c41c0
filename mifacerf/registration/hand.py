"""The hand-made registration inputs in ``CAPTURE/hand/`` (format: docs/registration.md).

What a real user supplies, read and validated here; problems are collected (never
raised for a single bad item) so registration continues where it can and reports them.

* ``template.json`` — the base mesh the user built on the neutral (:class:`Template`);
* ``coarse_points.json`` — per expression the ~18 coarse points: 2-D clicks in the
  cameras (and/or the 3-D position the tool triangulated);
* ``rotoscope/<expression>.json`` — lip, eyelid and iris polylines in ≥ 2 views, the marked
  lower-teeth point, optionally the ear / nose-bridge points and where the eyes look.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..geometry.margins import margins_from_holes
from ..errors import MifacerfError

TEMPLATE_SCHEMA = "mifacerf.template/1"
COARSE_FORMAT = "mifacerf.coarse_points"
ROTOSCOPE_FORMAT = "mifacerf.rotoscope"
MARGIN_NAMES = ("lip_upper", "lip_lower", "lid_upper_L", "lid_lower_L", "lid_upper_R", "lid_lower_R")
HEAD_POINT_NAMES = ("ear_L", "ear_R", "nose_bridge")
EYE_SIDES = {"eye_left": "L", "eye_right": "R"}
DEFAULT_DOT_RADIUS = 0.0015


class HandInputError(MifacerfError, ValueError):
    """A hand-input file that cannot be used at all (the message names it)."""


@dataclass
class Template:
    """The registration template, schema ``mifacerf.template/1`` (docs/registration.md).

    ``vertices`` (T, 3) neutral positions as the user placed them; ``kinds`` (T,) strings
    (``"dot"`` for fiducials); ``names`` (T,); ``triangles`` (F, 3); ``coarse`` (K,) vertex ids of
    the coarse points; ``coarse_triangles`` (G, 3) indices into ``coarse``; ``regions``
    {name: ids}; ``margins`` {lip_upper, lip_lower, lid_upper_L, ...: ordered ids, corners at
    both ends}; ``teeth`` {"upper"/"lower": {"vertices" (n, 3) in the neutral head frame,
    "triangles", "mark" (optional strip vertex the user clicks)}}; ``eyes`` {"L"/"R": {"centre",
    "radius", "iris_radius", "iris_depth"}}; ``head_points`` {ear_L, ear_R, nose_bridge: vertex
    id}; ``dot_radius`` metres; ``raw`` the JSON dict (what the registration folder stores).
    """

    vertices: np.ndarray
    kinds: list
    names: list
    triangles: np.ndarray
    coarse: np.ndarray
    coarse_triangles: np.ndarray
    regions: dict
    margins: dict
    teeth: dict
    eyes: dict
    head_points: dict
    dot_radius: float
    raw: dict = field(repr=False, default_factory=dict)

    @property
    def n_vertices(self) -> int:
        return len(self.vertices)

    @property
    def is_dot(self) -> np.ndarray:
        return np.array([k == "dot" for k in self.kinds])

    @property
    def dot_ids(self) -> np.ndarray:
        return np.flatnonzero(self.is_dot)

    @property
    def lower_teeth_point(self) -> np.ndarray | None:
        t = self.teeth.get("lower")
        if not t or t.get("mark") is None:
            return None
        return np.asarray(t["vertices"], np.float64)[int(t["mark"])]

    def margin_ids(self) -> np.ndarray:
        ids = [np.asarray(v, np.int64) for v in self.margins.values()]
        return np.unique(np.concatenate(ids)) if ids else np.zeros(0, np.int64)

    def to_dict(self) -> dict:
        """The JSON dict, as read (schema ``mifacerf.template/1``)."""
        return dict(self.raw)

    @classmethod
    def from_dict(cls, d: dict, source: str = "template") -> "Template":
        if d.get("schema") != TEMPLATE_SCHEMA:
            raise HandInputError(f"{source}: not a {TEMPLATE_SCHEMA} document (schema={d.get('schema')!r})")
        try:
            vs = d["vertices"]
            V = np.array([v["position"] for v in vs], np.float64).reshape(-1, 3)
            kinds = [str(v["kind"]) for v in vs]
            names = [str(v.get("name", "")) for v in vs]
            F = np.asarray(d["triangles"], np.int64).reshape(-1, 3)
        except (KeyError, ValueError, TypeError) as exc:
            raise HandInputError(f"{source}: needs 'vertices' (kind, position) and 'triangles' ({exc})") from exc
        n = len(V)
        if F.size and (F.min() < 0 or F.max() >= n):
            raise HandInputError(f"{source}: triangles index vertices out of range")
        if not np.isfinite(V).all():
            raise HandInputError(f"{source}: non-finite vertex positions")
        coarse = np.asarray(d.get("coarse_points", []), np.int64).reshape(-1)
        if coarse.size and (coarse.min() < 0 or coarse.max() >= n):
            raise HandInputError(f"{source}: coarse point ids out of range")
        ct = d.get("coarse_triangles")
        if ct is None or len(ct) == 0:
            ct = auto_coarse_triangles(V[coarse]) if len(coarse) >= 3 else np.zeros((0, 3), np.int64)
        ct = np.asarray(ct, np.int64).reshape(-1, 3)
        if ct.size and (ct.min() < 0 or ct.max() >= len(coarse)):
            raise HandInputError(f"{source}: coarse_triangles index the coarse list out of range")
        margins = {k: np.asarray(v, np.int64) for k, v in (d.get("margins") or {}).items()}
        if not margins:
            margins = margins_from_holes(d.get("holes") or {}, kinds)
        teeth = {}
        for k, t in (d.get("teeth") or {}).items():
            teeth[k] = {"vertices": np.asarray(t["vertices"], np.float64).reshape(-1, 3),
                        "triangles": np.asarray(t.get("triangles", []), np.int64).reshape(-1, 3),
                        "part": t.get("part"), "mark": t.get("mark")}
        eyes = {}
        for k, e in (d.get("eyes") or {}).items():
            side = EYE_SIDES.get(k, k)
            eyes[side] = dict(e)
        head_points = {nm: i for i, nm in enumerate(names) if nm in HEAD_POINT_NAMES}
        head_points.update({k: int(v) for k, v in (d.get("head_points") or {}).items()})
        return cls(V, kinds, names, F, coarse, ct,
                   {k: np.asarray(v, np.int64) for k, v in (d.get("regions") or {}).items()},
                   margins, teeth, eyes, head_points, float(d.get("dot_radius", DEFAULT_DOT_RADIUS)), dict(d))


def auto_coarse_triangles(P: np.ndarray) -> np.ndarray:
    """A coarse mesh over points on a face: Delaunay in (azimuth, height) about the vertical axis."""
    from scipy.spatial import Delaunay

    c = P.mean(0)
    az = np.arctan2(P[:, 0] - c[0], P[:, 2] - c[2] + 0.15)  # seen from in front of the face
    pts = np.stack([az, (P[:, 1] - c[1]) / 0.1], 1)
    tri = Delaunay(pts).simplices
    # drop slivers along the hull
    e1, e2 = pts[tri[:, 1]] - pts[tri[:, 0]], pts[tri[:, 2]] - pts[tri[:, 0]]
    a = np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
    L = np.max([np.linalg.norm(pts[tri[:, i]] - pts[tri[:, (i + 1) % 3]], axis=1) for i in range(3)], axis=0)
    return tri[a / np.maximum(L ** 2, 1e-12) > 0.05]


@dataclass
class CoarseClicks:
    """One expression's coarse points: ``clicks`` {vertex id: {camera: (u, v)}};
    ``positions`` {vertex id: (3,)} as the user's tool gave them."""

    clicks: dict
    positions: dict


@dataclass
class Rotoscope:
    """One expression's rotoscoping: ``curves`` {name: {camera: (P, 2) pixels}},
    ``points`` {name: {camera: (2,)}}, ``eyes_look_at`` ("forward", a camera name, or None)."""

    curves: dict
    points: dict
    eyes_look_at: str | None = None


@dataclass
class HandInputs:
    template: Template | None
    coarse: dict          # expression -> CoarseClicks
    rotoscope: dict       # expression -> Rotoscope
    problems: list        # human-readable problems found while reading


def _read_json(path: Path, problems: list):
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        problems.append(f"{path}: missing")
    except (json.JSONDecodeError, OSError) as exc:
        problems.append(f"{path}: unreadable ({exc})")
    return None


def read_hand_inputs(capture_root: str | Path, camera_names: list[str] | None = None) -> HandInputs:
    """Read ``CAPTURE/hand/``; missing or broken pieces are listed in ``problems``."""
    hand = Path(capture_root) / "hand"
    problems: list[str] = []
    template = None
    d = _read_json(hand / "template.json", problems)
    if d is not None:
        try:
            template = Template.from_dict(d, str(hand / "template.json"))
        except HandInputError as exc:
            problems.append(str(exc))
    cams = set(camera_names or [])
    coarse: dict = {}
    d = _read_json(hand / "coarse_points.json", problems)
    if d is not None:
        for name, entry in (d.get("expressions") or {}).items():
            clicks, positions = {}, {}
            for vid, item in entry.items():
                try:
                    v = int(vid)
                except ValueError:
                    problems.append(f"coarse_points.json: {name}: bad point id {vid!r}")
                    continue
                c = {}
                for cam, uv in (item.get("clicks") or {}).items():
                    if cams and cam not in cams:
                        problems.append(f"coarse_points.json: {name}/{vid}: unknown camera {cam!r}")
                        continue
                    uv = np.asarray(uv, np.float64).reshape(-1)
                    if uv.size == 2 and np.isfinite(uv).all():
                        c[cam] = uv
                clicks[v] = c
                pos = item.get("position")
                if pos is not None:
                    pos = np.asarray(pos, np.float64).reshape(-1)
                    if pos.size == 3 and np.isfinite(pos).all():
                        positions[v] = pos
            coarse[name] = CoarseClicks(clicks, positions)
    rot: dict = {}
    rdir = hand / "rotoscope"
    if rdir.is_dir():
        for path in sorted(rdir.glob("*.json")):
            d = _read_json(path, problems)
            if d is None:
                continue
            name = d.get("expression", path.stem)
            curves = {}
            for cname, views in (d.get("curves") or {}).items():
                curves[cname] = {}
                for cam, poly in views.items():
                    poly = np.asarray(poly, np.float64).reshape(-1, 2)
                    if cams and cam not in cams:
                        problems.append(f"{path.name}: curve {cname}: unknown camera {cam!r}")
                    elif len(poly) >= 2 and np.isfinite(poly).all():
                        curves[cname][cam] = poly
            points = {}
            for pname, views in (d.get("points") or {}).items():
                points[pname] = {cam: np.asarray(uv, np.float64).reshape(2) for cam, uv in views.items()
                                 if not cams or cam in cams}
            rot[name] = Rotoscope(curves, points, d.get("eyes_look_at"))
    else:
        problems.append(f"{rdir}: missing (no lips, eyelids, irises or teeth marks)")
    return HandInputs(template, coarse, rot, problems)
