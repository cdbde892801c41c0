"""One studio session: a capture folder, its hand documents (with versions), its registration, its views.

Everything the page edits for one expression is its **hand state**::

    {"coarse":    {vertex id: {"clicks": {camera: [u, v]}, "position": [x, y, z] | None}},   # coarse_points.json
     "rotoscope": {"curves": {name: {camera: [[u, v], ...]}}, "points": {name: {camera: [u, v]}},
                   "eyes_look_at": "forward" | camera | None},                                # rotoscope/<expr>.json
     "overrides": {vertex id: {"clicks": {camera: [u, v]}, "position": [x, y, z]}}}          # overrides.json

saved into the documented files (docs/registration.md) with the project's atomic JSON writer, so a
server killed mid-save leaves the previous file whole. The state's **version** is a hash of what is on
disk: a save names the version it started from, and a save from a stale version (another tab saved
in between) is refused (:class:`Conflict`) — the refused state is kept in
``hand/studio-conflicts/`` so nothing typed is lost, and the page is told.

Reads only the capture folder (manifest, images, ``hand/``, ``cache/``, ``registration/``); never
``truth/``.
"""
from __future__ import annotations

import hashlib
import json
import re
import threading
import time
from pathlib import Path

import numpy as np

from ..formats.capture import Capture, CaptureError
from ..formats.files import write_json_atomic
from ..registration.hand import (COARSE_FORMAT, HEAD_POINT_NAMES, MARGIN_NAMES, ROTOSCOPE_FORMAT, HandInputError,
                                 Template)
from ..registration.overrides import FORMAT as OVERRIDES_FORMAT
from ..registration.overrides import VERSION as OVERRIDES_VERSION
from ..registration.overrides import overrides_path, read_overrides
from .images import KINDS, LRU, encode_png, tone_map
from ..errors import MifacerfError

CURVE_NAMES = MARGIN_NAMES + ("iris_L", "iris_R")
#: vertex kinds of ``mifacerf.template/1`` (docs/registration.md)
TEMPLATE_KINDS = ("dot", "lip_upper", "lip_lower", "lip_corner", "lid_upper", "lid_lower", "lid_corner", "nostril",
                  "ear", "nose_bridge")
#: the culling regions (docs/registration.md; blending.culling.REGION_NAMES and the synthetic subject's nose)
REGION_NAMES = ("forehead", "nose", "eye_left", "eye_right", "cheek_left", "cheek_right", "mouth", "chin",
                "throat", "neck")
POINT_NAMES = ("lower_teeth",) + HEAD_POINT_NAMES
#: how the page colours a vertex (registration.json + expressions/<expr>.npz, docs/studio.md)
STATUS_CODES = ("snapped", "consensus", "single_view", "failed", "flagged", "hand_fixed", "placed", "predicted")


class StudioError(MifacerfError, ValueError):
    """A request the studio cannot serve; the message is one line for the user."""


class Conflict(StudioError):
    """A save from a stale version: ``current`` is the state on disk, ``kept`` where the refused one went."""

    def __init__(self, msg: str, current: dict, version: str, kept: str):
        super().__init__(msg)
        self.current, self.version, self.kept = current, version, kept


def _read(path: Path):
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        return None
    except (OSError, json.JSONDecodeError) as exc:
        raise StudioError(f"{path.name}: unreadable ({exc})") from exc


def _digest(obj) -> str:
    return hashlib.sha1(json.dumps(obj, sort_keys=True).encode()).hexdigest()[:16]


class Session:
    """The capture at ``root`` (raises :class:`CaptureError` when it is not one)."""

    def __init__(self, root: str | Path):
        self.root = Path(root).resolve()
        if not (self.root / "manifest.json").exists():
            raise CaptureError(f"{self.root}: not a capture folder (no manifest.json; docs/capture-format.md)")
        self.cap = Capture(self.root)
        self.cams = list(self.cap.rig.cameras)
        self.names = [c.name for c in self.cams]
        self.hand = self.root / "hand"
        self.reg_dir = self.root / "registration"
        self.lock = threading.RLock()
        self.floats = LRU(48)
        self.pngs = LRU(256)
        self._tpl = (None, None)
        self._regs: dict = {}
        self._filter = None
        self.neutral = next((e.name for e in self.cap.expressions if e.category == "neutral"),
                            self.cap.expression_names[0])

    # ------------------------------------------------------------------ static description
    def camera(self, name: str):
        if name not in self.names:
            raise StudioError(f"unknown camera {name!r}")
        return self.cams[self.names.index(name)]

    def check_expression(self, name: str) -> str:
        if name not in self.cap.expression_names:
            raise StudioError(f"unknown expression {name!r}")
        return name

    def missing_images(self, name: str) -> int:
        n = 0
        for cam in self.names:
            for light in range(self.cap.n_lights):
                if not self.cap.image_path(name, cam, light).exists():
                    n += 1
        return n

    def require_images(self, name: str) -> None:
        """Raise :class:`StudioError` (one line) when ``name`` lacks any image (proposals and registration
        need every view's)."""
        missing = [self.cap.image_path(name, cam, light) for cam in self.names for light in range(self.cap.n_lights)
                   if not self.cap.image_path(name, cam, light).exists()]
        if missing:
            rel = missing[0].relative_to(self.root) if self.root in missing[0].parents else missing[0]
            raise StudioError(f"{name}: {len(missing)} image(s) missing (first: {rel}); proposals and registration "
                              "need every view's images")

    def info(self) -> dict:
        tpl = self.template()
        edges = []
        if tpl is not None and len(tpl.triangles):
            F = tpl.triangles
            e = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
            edges = np.unique(e, axis=0).tolist()
        return {
            "capture": str(self.root), "neutral": self.neutral, "n_lights": self.cap.n_lights,
            "cameras": [{"name": c.name, "width": c.width, "height": c.height} for c in self.cams],
            "curve_names": list(CURVE_NAMES), "point_names": list(POINT_NAMES), "status_codes": list(STATUS_CODES),
            "image_kinds": list(KINDS),
            "template": None if tpl is None else {
                "n_vertices": tpl.n_vertices, "kinds": tpl.kinds, "names": tpl.names, "edges": edges,
                "coarse": tpl.coarse.tolist(), "head_points": tpl.head_points,
                "margins": {k: v.tolist() for k, v in tpl.margins.items()}},
            "template_problem": self._tpl_problem,
            "expressions": self.expression_list(),
        }

    # ------------------------------------------------------------------ hand documents
    _tpl_problem = None

    def template(self) -> Template | None:
        path = self.hand / "template.json"
        try:
            stamp = path.stat().st_mtime_ns
        except FileNotFoundError:
            self._tpl, self._tpl_problem = (None, None), "hand/template.json missing (propose one on the neutral)"
            return None
        if self._tpl[0] != stamp:
            try:
                self._tpl = (stamp, Template.from_dict(_read(path) or {}, "hand/template.json"))
                self._tpl_problem = None
            except (HandInputError, StudioError) as exc:
                self._tpl, self._tpl_problem = (stamp, None), str(exc)
        return self._tpl[1]

    def hand_state(self, name: str) -> dict:
        self.check_expression(name)
        coarse = (_read(self.hand / "coarse_points.json") or {}).get("expressions", {}).get(name, {})
        rot = _read(self.hand / "rotoscope" / f"{name}.json") or {}
        try:
            ov = read_overrides(self.root)["expressions"].get(name, {})
        except ValueError as exc:
            raise StudioError(str(exc)) from exc
        return {"coarse": coarse,
                "rotoscope": {"curves": rot.get("curves", {}), "points": rot.get("points", {}),
                              "eyes_look_at": rot.get("eyes_look_at")},
                "overrides": ov}

    def version(self, name: str) -> str:
        return _digest(self.hand_state(name))

    def _uv(self, cam: str, uv, what: str) -> list:
        c = self.camera(cam)
        a = np.asarray(uv, np.float64).reshape(-1)
        if a.size != 2 or not np.isfinite(a).all():
            raise StudioError(f"{what}: not a pixel position ({uv!r})")
        if not (-0.5 <= a[0] <= c.width - 0.5 and -0.5 <= a[1] <= c.height - 0.5):
            raise StudioError(f"{what}: ({a[0]:.1f}, {a[1]:.1f}) is outside {cam}'s {c.width}x{c.height} image")
        return [round(float(a[0]), 3), round(float(a[1]), 3)]

    def clean_state(self, state: dict) -> dict:
        """The state with every position checked (known cameras, inside the image, finite)."""
        tpl = self.template()
        nv = tpl.n_vertices if tpl is not None else None

        def vid_ok(k):
            try:
                v = int(k)
            except (TypeError, ValueError):
                raise StudioError(f"bad vertex id {k!r}") from None
            if nv is not None and not 0 <= v < nv:
                raise StudioError(f"vertex id {v} out of range (template has {nv})")
            return str(v)

        def pos(p, what):
            if p is None:
                return None
            a = np.asarray(p, np.float64).reshape(-1)
            if a.size != 3 or not np.isfinite(a).all():
                raise StudioError(f"{what}: not a 3-D position")
            return np.round(a, 7).tolist()

        out = {"coarse": {}, "rotoscope": {"curves": {}, "points": {}, "eyes_look_at": None}, "overrides": {}}
        for key in ("coarse", "overrides"):
            for k, item in (state.get(key) or {}).items():
                v = vid_ok(k)
                clicks = {c: self._uv(c, uv, f"{key} {v} in {c}") for c, uv in (item.get("clicks") or {}).items()}
                out[key][v] = {"clicks": clicks, "position": pos(item.get("position"), f"{key} {v}")}
        rot = state.get("rotoscope") or {}
        for cname, views in (rot.get("curves") or {}).items():
            if cname not in CURVE_NAMES:
                raise StudioError(f"unknown curve {cname!r} (one of {', '.join(CURVE_NAMES)})")
            cv = {}
            for cam, poly in views.items():
                pts = [self._uv(cam, p, f"curve {cname} in {cam}") for p in poly]
                if len(pts) >= 2:
                    cv[cam] = pts
            if cv:
                out["rotoscope"]["curves"][cname] = cv
        for pname, views in (rot.get("points") or {}).items():
            if pname not in POINT_NAMES:
                raise StudioError(f"unknown point {pname!r} (one of {', '.join(POINT_NAMES)})")
            pv = {cam: self._uv(cam, p, f"point {pname} in {cam}") for cam, p in views.items()}
            if pv:
                out["rotoscope"]["points"][pname] = pv
        look = rot.get("eyes_look_at")
        if look not in (None, "forward") and look not in self.names:
            raise StudioError(f"eyes_look_at: {look!r} is neither 'forward' nor a camera")
        out["rotoscope"]["eyes_look_at"] = look
        return out

    def save_hand(self, name: str, state: dict, base_version: str | None) -> str:
        """Write ``state`` (see the module docstring) for ``name``; returns the new version."""
        self.check_expression(name)
        state = self.clean_state(state)
        with self.lock:
            current = self.hand_state(name)
            cur_v = _digest(current)
            if base_version != cur_v:
                kept = self._keep_conflict(name, state)
                raise Conflict(f"{name}: changed elsewhere (another tab?) since this page loaded it; your version "
                               f"is kept in {kept}", current, cur_v, kept)
            (self.hand / "rotoscope").mkdir(parents=True, exist_ok=True)
            if state["coarse"] != current["coarse"]:
                doc = _read(self.hand / "coarse_points.json") or {"format": COARSE_FORMAT, "version": 1}
                tpl = self.template()
                if tpl is not None:
                    doc["coarse_points"] = tpl.coarse.tolist()
                doc.setdefault("expressions", {})[name] = state["coarse"]
                doc["edited_by"] = "mifacerf studio"
                write_json_atomic(self.hand / "coarse_points.json", doc)
            if state["rotoscope"] != current["rotoscope"]:
                write_json_atomic(self.hand / "rotoscope" / f"{name}.json", {
                    "format": ROTOSCOPE_FORMAT, "version": 1, "expression": name, **state["rotoscope"]})
            if state["overrides"] != current["overrides"]:
                doc = read_overrides(self.root)
                doc.update(format=OVERRIDES_FORMAT, version=OVERRIDES_VERSION)
                if state["overrides"]:
                    doc["expressions"][name] = state["overrides"]
                else:
                    doc["expressions"].pop(name, None)
                write_json_atomic(overrides_path(self.root), doc)
            return self.version(name)

    def _keep_conflict(self, name: str, state: dict) -> str:
        d = self.hand / "studio-conflicts"
        d.mkdir(parents=True, exist_ok=True)
        rel = f"hand/studio-conflicts/{name}-{time.strftime('%Y%m%d-%H%M%S')}-{_digest(state)[:6]}.json"
        write_json_atomic(self.root / rel, {"expression": name, "refused_state": state, "saved_at": time.time()})
        return rel

    def save_template(self, doc: dict) -> None:
        """Write ``hand/template.json`` (checked by the registration's reader first)."""
        Template.from_dict(doc, "proposed template")
        self.hand.mkdir(parents=True, exist_ok=True)
        with self.lock:
            write_json_atomic(self.hand / "template.json", doc)

    # ------------------------------------------------------------------ template editing (the neutral)
    def template_doc(self) -> dict | None:
        """``hand/template.json`` as a dict (None if missing)."""
        return _read(self.hand / "template.json")

    def template_version(self) -> str:
        return _digest(self.template_doc())

    def project_all(self, positions) -> dict:
        """{camera: [[u, v], ...]} of 3-D points (n, 3) (-1e4 where a point is behind a camera)."""
        X = np.asarray(positions, np.float64).reshape(-1, 3)
        if len(X) == 0:
            return {c.name: [] for c in self.cams}
        return {c.name: np.round(np.nan_to_num(c.project(X)[0], nan=-1e4), 3).tolist() for c in self.cams}

    def template_for_editing(self) -> dict:
        doc = self.template_doc()
        if doc is None:
            return {"version": _digest(None), "template": None, "uv": {}, "problem": self._tpl_problem}
        try:
            P = [v["position"] for v in doc.get("vertices", [])]
            uv = self.project_all(P)
        except (KeyError, TypeError, ValueError):
            uv = {}
        self.template()
        return {"version": _digest(doc), "template": doc, "uv": uv, "problem": self._tpl_problem,
                "kinds": list(TEMPLATE_KINDS) + sorted({v.get("kind") for v in doc.get("vertices", [])}
                                                       - set(TEMPLATE_KINDS) - {None}),
                "region_names": list(REGION_NAMES) + sorted(set(doc.get("regions") or {}) - set(REGION_NAMES))}

    def save_template_edit(self, doc: dict, base_version: str | None, renumber: list | None = None) -> dict:
        """Write an edited template (checked by the registration's reader, margins, regions and head points
        inside it); refused with :class:`Conflict` if the file changed since ``base_version``. ``renumber``
        (old vertex id → new id, -1 for a deleted vertex; one entry per vertex of the file on disk): the
        coarse points and fixes of every expression (``coarse_points.json``, ``overrides.json``) follow."""
        if not isinstance(doc, dict):
            raise StudioError("template must be a JSON object")
        doc = dict(doc)
        doc.setdefault("schema", "mifacerf.template/1")
        try:
            tpl = Template.from_dict(doc, "edited template")
        except HandInputError as exc:
            raise StudioError(str(exc)) from exc
        n = tpl.n_vertices
        for k in tpl.kinds:
            if not k or not isinstance(k, str):
                raise StudioError(f"a vertex without a kind (e.g. {', '.join(TEMPLATE_KINDS)})")
        for what, groups in (("margin", tpl.margins), ("region", tpl.regions)):
            for name, ids in groups.items():
                ids = np.asarray(ids)
                if ids.size and (ids.min() < 0 or ids.max() >= n):
                    raise StudioError(f"{what} {name}: vertex ids out of range (template has {n})")
        for name, vid in tpl.head_points.items():
            if not 0 <= int(vid) < n:
                raise StudioError(f"head point {name}: vertex {vid} out of range")
        with self.lock:
            cur = self.template_doc()
            cur_v = _digest(cur)
            if base_version != cur_v:
                kept = self._keep_conflict("template", doc)
                raise Conflict(f"hand/template.json changed elsewhere (another tab?) since this page loaded it; "
                               f"your version is kept in {kept}", cur, cur_v, kept)
            if renumber is not None:
                n_old = len((cur or {}).get("vertices", []))
                m = [int(x) for x in renumber]
                if len(m) != n_old or any(not -1 <= x < n for x in m):
                    raise StudioError(f"renumber: {len(m)} entries for {n_old} vertices, or ids out of range")
            doc["edited_by"] = "mifacerf studio"
            self.hand.mkdir(parents=True, exist_ok=True)
            write_json_atomic(self.hand / "template.json", doc)
            if renumber is not None and m != list(range(n_old)):
                self._renumber_hand(m, tpl)
        return {"version": _digest(doc), "uv": self.project_all([v["position"] for v in doc["vertices"]])}

    def _renumber_hand(self, m: list, tpl: Template) -> None:
        """Renumber the vertex ids of every expression's coarse points and fixes (``m``: old → new, -1 gone)."""
        def remap(entry: dict) -> dict:
            return {str(m[int(k)]): v for k, v in entry.items() if 0 <= int(k) < len(m) and m[int(k)] >= 0}
        cp = _read(self.hand / "coarse_points.json")
        if cp is not None:
            cp["expressions"] = {e: remap(d) for e, d in (cp.get("expressions") or {}).items()}
            cp["coarse_points"] = tpl.coarse.tolist()
            write_json_atomic(self.hand / "coarse_points.json", cp)
        if overrides_path(self.root).exists():
            ov = read_overrides(self.root)
            ov["expressions"] = {e: remap(d) for e, d in ov["expressions"].items()}
            write_json_atomic(overrides_path(self.root), ov)

    # ------------------------------------------------------------------ registration
    def registration_meta(self) -> dict:
        return _read(self.reg_dir / "registration.json") or {}

    def registered(self, name: str):
        """(vertices (T, 3), status (T,), uv (C, T, 2), visible (C, T)) or None."""
        from ..formats.registration import RegisteredExpression, RegistrationError

        path = self.reg_dir / "expressions" / f"{name}.npz"
        try:
            stamp = path.stat().st_mtime_ns
        except FileNotFoundError:
            return None
        if self._regs.get(name, (None,))[0] != stamp:
            try:
                self._regs[name] = (stamp, RegisteredExpression.load(path, name))
            except (RegistrationError, OSError, ValueError, KeyError):
                self._regs[name] = (stamp, None)
        return self._regs[name][1]

    def vertex_status(self, name: str) -> list | None:
        """Per template vertex one of :data:`STATUS_CODES`, or None if not registered."""
        reg = self.registered(name)
        tpl = self.template()
        rep = self.registration_meta().get("expressions", {}).get(name)
        if reg is None or tpl is None or rep is None or len(reg.status) != tpl.n_vertices:
            return None
        consensus = set((rep.get("consensus") or {}).get("registered", []))
        single = set(rep.get("single_view_dots", []))
        fixed = set(rep.get("hand_fixed", []))
        flagged = set()
        for f in rep.get("flags", []):
            if "did not snap" in f or "already taken" in f:
                for m in re.findall(r"\[([0-9, ]*)\]", f):
                    flagged |= {int(x) for x in m.split(",") if x.strip()}
        out = []
        for v, (s, dot) in enumerate(zip(reg.status, tpl.is_dot)):
            if v in fixed:
                out.append("hand_fixed")
            elif v in flagged:
                out.append("flagged")
            elif not dot:
                out.append("placed" if s == 1 else "predicted")
            elif s != 1:
                out.append("failed")
            elif v in single:
                out.append("single_view")
            elif v in consensus:
                out.append("consensus")
            else:
                out.append("snapped")
        return out

    def expression_list(self) -> list:
        meta = self.registration_meta().get("expressions", {})
        coarse = (_read(self.hand / "coarse_points.json") or {}).get("expressions", {})
        out = []
        for e in self.cap.expressions:
            rep = meta.get(e.name) if self.registered(e.name) is not None else None
            rot = _read(self.hand / "rotoscope" / f"{e.name}.json") or {}
            out.append({
                "name": e.name, "category": e.category, "registered": rep is not None,
                "registered_fraction": None if rep is None else rep.get("registered_fraction"),
                "dots_registered": None if rep is None else rep.get("dots_registered"),
                "n_dots": None if rep is None else rep.get("n_dots"),
                "n_flags": None if rep is None else len(rep.get("flags", [])),
                "coarse_points": sum(1 for it in coarse.get(e.name, {}).values() if len(it.get("clicks", {})) >= 2),
                "curves": len(rot.get("curves", {})), "points": len(rot.get("points", {})),
                "missing_images": self.missing_images(e.name),
            })
        return out

    def geometry(self, name: str) -> dict:
        """What the overlays draw for ``name``: every template vertex projected into every camera."""
        self.check_expression(name)
        tpl = self.template()
        if tpl is None:
            return {"source": None}
        reg = self.registered(name)
        if reg is not None and len(reg.vertices) == tpl.n_vertices:
            uv, vis, src, V = reg.uv, reg.visible, "registered", reg.vertices
        else:
            V = tpl.vertices
            src = "template"
            if name != self.neutral:
                n = self.registered(self.neutral)
                if n is not None and len(n.vertices) == tpl.n_vertices:
                    V, src = n.vertices, f"registered {self.neutral} (this expression is not registered)"
            uv = np.stack([c.project(V)[0] for c in self.cams])
            vis = np.ones(uv.shape[:2], bool)
        rep = self.registration_meta().get("expressions", {}).get(name) if reg is not None else None
        return {"source": src, "uv": np.round(np.nan_to_num(uv, nan=-1e4), 2).tolist(),
                "visible": np.asarray(vis, bool).tolist(), "positions": np.round(V, 7).tolist(),
                "status": self.vertex_status(name),
                "report": None if rep is None else {k: rep.get(k) for k in (
                    "registered_fraction", "dots_registered", "n_dots", "flags", "time_s", "hand_fixed",
                    "single_view_dots", "lips_eyelids", "head_pose", "teeth")}}

    # ------------------------------------------------------------------ geometry for clicks
    def triangulate(self, clicks: dict, depth_from=None) -> dict:
        """A 3-D point from clicks {camera: (u, v)} (≥ 2 views: triangulated; one view and
        ``depth_from`` (3,): on that view's ray at that point's depth), its reprojection into every
        camera and the residual (pixels) in each clicked view."""
        from ..geometry.triangulate import triangulate

        clicks = {c: self._uv(c, uv, f"click in {c}") for c, uv in clicks.items()}
        X = None
        if len(clicks) >= 2:
            uv = np.full((len(self.cams), 1, 2), np.nan)
            for c, p in clicks.items():
                uv[self.names.index(c), 0] = p
            tr = triangulate(self.cams, uv)
            if tr.ok[0]:
                X = tr.points[0]
        elif len(clicks) == 1 and depth_from is not None:
            (c, p), = clicks.items()
            X = self.on_ray(c, p, np.asarray(depth_from, np.float64))
        if X is None or not np.isfinite(X).all():
            return {"ok": False, "position": None, "reprojection": {}, "residual_px": {}}
        rep = {c.name: np.round(c.project(X[None])[0][0], 3).tolist() for c in self.cams}
        res = {c: round(float(np.hypot(*(np.asarray(rep[c]) - p))), 3) for c, p in clicks.items()}
        return {"ok": True, "position": np.round(X, 7).tolist(), "reprojection": rep, "residual_px": res}

    def on_ray(self, cam: str, uv, near: np.ndarray) -> np.ndarray:
        """The point on ``cam``'s ray through pixel ``uv`` at the camera depth of ``near`` (3,)."""
        c = self.camera(cam)
        o, d = c.pixel_rays(np.asarray(uv, np.float64).reshape(1, 2))
        o, d = np.asarray(o).reshape(-1, 3)[0], np.asarray(d).reshape(-1, 3)[0]
        z = float((c.R @ near + c.t)[2])
        dz = float(c.R[2] @ d)
        oz = float((c.R @ o + c.t)[2])
        return o + d * (z - oz) / dz

    # ------------------------------------------------------------------ images
    def float_image(self, name: str, cam: str, kind: str, light: int = 0) -> np.ndarray:
        from ..registration.proxies import proxies_for

        self.check_expression(name)
        self.camera(cam)
        if kind not in KINDS:
            raise StudioError(f"unknown image kind {kind!r} (one of {', '.join(KINDS)})")
        if kind == "light" and not 0 <= light < self.cap.n_lights:
            raise StudioError(f"light {light} out of range (0-{self.cap.n_lights - 1})")
        key = (name, cam, kind, light if kind == "light" else 0)
        img = self.floats.get(key)
        if img is not None:
            return img
        try:
            if kind in ("diffuse", "p95"):
                p = proxies_for(self.cap, name, cam)
                img = p.diffuse if kind == "diffuse" else p.p95
            elif kind == "sum":
                img = self.cap.field(name, cam).sum(0)
            elif kind == "light":
                img = self.cap.field(name, cam, lights=[light])[0]
            else:
                img = self.dot_filter().strength(proxies_for(self.cap, name, cam).diffuse, cam)
        except CaptureError as exc:
            raise StudioError(str(exc).splitlines()[0]) from exc
        return self.floats.put(key, img)

    def png(self, name: str, cam: str, kind: str, light: int = 0, exposure: float = 0.0, gamma: float = 2.2) -> bytes:
        key = (name, cam, kind, light, round(float(exposure), 2), round(float(gamma), 2))
        out = self.pngs.get(key)
        if out is None:
            img = self.float_image(name, cam, kind, light)
            out = self.pngs.put(key, encode_png(tone_map(img, exposure, gamma, 1.0 if kind == "dots" else None)))
        return out

    def dot_filter(self):
        """The registration's tuned dot filter; before any registration one tuned on the template's
        fiducials (if any), else the prior yellow filter (:mod:`.proposals`)."""
        from ..registration.dots import DotFilter

        d = self.registration_meta().get("dot_filter")
        if d is not None:
            return DotFilter.from_dict(d)
        if self._filter is None:
            from .proposals import untuned_filter

            self._filter = untuned_filter(self)
        return self._filter

    def invalidate(self) -> None:
        """Forget cached images and registrations (after a registration run)."""
        self.floats.clear()
        self.pngs.clear()
        self._regs.clear()
        self._filter = None
