"""``mifacerf build``: assemble the relightable morphable model from a capture and its registration.

Reads only the capture folder and the registration folder (never ground truth):
per source expression its registered geometry and, per camera, its dot-free
reflectance field restricted to the pixels where the registered template is seen
(texel map by ray casting the pixel centres: triangle, barycentrics, depth), stored
texel-major in float16; the §5 blend model (local deformation spaces, Delaunay,
culling); the eye and teeth reference expressions.

Template **extensions** (scalp, ears, neck: the template's ``extensions`` member, placed per expression by
the registration) are part of the mesh, so their fields are built like the face's (pixels where a
capture camera sees them) and their regions join the culling regions. ``model.json`` reports each one
(``extensions``: mode, anchor, vertices, triangles, texels, status, the registration's fall-backs).
Bad input: an extension not attached to the face is an error; one that no capture camera sees in any
expression is left out of the model (its triangles dropped; ``status`` says so and a warning names
it) — it could only ever render as a hole.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..execution import Executor
from ..formats.capture import Capture
from ..formats.registration import Registration, RegistrationError
from ..registration.extensions import check_extensions, extensions_from_template
from ..geometry.boubekeur2008 import surface_entry
from ..geometry.meshscene import MeshScene
from ..validation import check_field
from .parts import build_part_fields, choose_references, part_sources, part_visibility
from ..formats.model import ModelWriter


def template_arrays(template: dict) -> dict:
    """The arrays the model needs from a template dict (schema ``mifacerf.template/1``, see
    docs/registration.md): ``triangles`` (F, 3), ``fiducial`` (T,) bool (kind ``dot``),
    ``regions`` {name: vertex ids}, ``n_vertices``."""
    tri = np.asarray(template["triangles"], np.int64)
    if "vertices" in template:
        kinds = [v["kind"] for v in template["vertices"]]
    else:
        kinds = template.get("kinds")
    n = len(kinds) if kinds is not None else int(template.get("n_vertices", tri.max() + 1))
    fiducial = np.array([k == "dot" for k in kinds]) if kinds is not None else np.ones(n, bool)
    regions = {k: np.asarray(v, np.int64) for k, v in (template.get("regions") or {}).items()}
    return {"triangles": tri, "fiducial": fiducial, "regions": regions, "n_vertices": n}


def triangle_extensions(triangles, extensions, n_vertices: int) -> np.ndarray:
    """(F,) index into ``extensions`` of the extension each triangle belongs to (that of its first vertex
    in an extension; a stitch between an extension and the face belongs to the extension), -1: the face."""
    owner = np.full(n_vertices, -1, np.int64)
    for k, ext in enumerate(extensions):
        owner[np.asarray(ext.vertices, np.int64)] = k
    o = owner[np.asarray(triangles, np.int64)]
    first = np.argmax(o >= 0, axis=1)
    return np.where((o >= 0).any(1), o[np.arange(len(o)), first], -1)


def extension_report(reg, names, geometry, t, cam_idx) -> tuple[list, dict, np.ndarray]:
    """The template's extensions checked against the registered geometry: (the extensions, the build
    report {name: {...}}, (F,) bool the triangles to build — those of an extension no capture camera sees
    in any expression are left out)."""
    import warnings

    try:
        exts = extensions_from_template(reg.template, t["n_vertices"])
        if exts:
            neutral = geometry["neutral"] if "neutral" in geometry else geometry[names[0]]
            check_extensions(neutral.vertices, t["triangles"], np.flatnonzero(t["fiducial"]), exts)
    except ValueError as exc:
        raise RegistrationError(f"{reg.root / 'template.json'}: {exc}") from exc
    tri_ext = triangle_extensions(t["triangles"], exts, t["n_vertices"])
    keep = np.ones(len(t["triangles"]), bool)
    out = {}
    for k, ext in enumerate(exts):
        seen = any(bool(geometry[n].visible[cam_idx][:, ext.vertices].any()) for n in names)
        fallbacks = sorted({f"{n}: {f}" for n in names
                            for f in (reg.report(n).get("extensions") or {}).get("fallbacks", [])
                            if f"{ext.name!r}" in f})
        out[ext.name] = {"mode": ext.mode, "anchor": ext.anchor, "vertices": int(len(ext.vertices)),
                         "triangles": int((tri_ext == k).sum()), "texels": 0,
                         "status": "built" if seen else "left out: no capture camera sees it in any expression",
                         "registration_fallbacks": fallbacks}
        if not seen:
            keep &= tri_ext != k
            out[ext.name]["triangles"] = 0
            warnings.warn(f"extension {ext.name!r}: no capture camera sees it in any expression; left out of the "
                          "model (its triangles dropped)", stacklevel=3)
    return exts, out, keep


class FieldContext:
    """What every field unit of :func:`build_model` shares: the capture and registration folders, the
    template's triangles. Pickled (sent to a worker) it keeps the folders; a worker opens the registration
    once and keeps its mesh scene for its next fields (as the loop in one process does)."""

    def __init__(self, capture, registration, triangles: np.ndarray, reg=None, geometry: dict | None = None):
        self.capture, self.root, self.triangles = str(capture), str(registration), triangles
        self._reg, self._geometry, self._scene, self._placed = reg, geometry, None, None

    def __getstate__(self):
        return {**self.__dict__, "_reg": None, "_geometry": None, "_scene": None, "_placed": None}

    def registration(self) -> Registration:
        if self._reg is None:
            self._reg, self._geometry = Registration(self.root, capture=Capture(self.capture)), {}
        return self._reg

    def scene(self, name: str) -> MeshScene:
        """The mesh scene holding expression ``name``'s registered vertices."""
        if name not in self._geometry:
            self._geometry[name] = self.registration().expression(name)
        if name != self._placed:
            v = self._geometry[name].vertices
            self._placed = name
            if self._scene is None:
                self._scene = MeshScene(v, self.triangles)
            self._scene.set_vertices(v)
        return self._scene


def field_unit(context: FieldContext, unit: tuple) -> tuple:
    """One field ``(expression, camera)``: the texels where the registered template is seen (ray cast per
    pixel centre) and the field there, checked → (pixels (N, 2), tri (N,), bary (N, 3), depth (N,), rf (N, L, 3))."""
    name, cam = unit
    reg = context.registration()
    hits, _ = context.scene(name).render_hits(cam, spp=1)
    sel = np.flatnonzero(hits.valid)
    field = reg.field(name, cam.name)  # (L, H, W, 3)
    check_field(field, name, cam.name, lambda light: reg.capture.image_path(name, cam.name, light))
    rows, cols = sel // cam.width, sel % cam.width
    return np.stack([rows, cols], 1), hits.tri[sel], hits.bary[sel], hits.t[sel], field[:, rows, cols].transpose(1, 0, 2)


def build_model(capture: str | Path, out: str | Path, registration: str | Path | None = None,
                expressions: list[str] | None = None, cameras: list[str] | None = None,
                overwrite: bool = False, progress: bool = True, culling: bool = True,
                allow_partial: bool = False, executor: Executor | None = None) -> Path:
    """Build a model folder ``out`` from ``capture`` (and ``registration``, default CAPTURE/registration);
    ``progress``: a bar over the fields.

    ``executor`` (:mod:`mifacerf.execution`; default: this process) cuts each (expression, camera) field as
    one unit (:func:`field_unit`: texel map by ray casting, the field's pixels read and checked); this process
    writes them, in the jobs' order, into the model's transaction.

    Without ``expressions``, every expression of the capture must be registered: a registration that
    covers fewer (an interrupted or partial ``register``) is an error unless ``allow_partial``, which
    builds from the registered ones. The model is written as one transaction
    (:class:`mifacerf.formats.model.ModelWriter`): a failure leaves ``out`` as it was."""
    from ..blending import BlendModel

    cap = Capture(capture)
    reg = Registration(registration or Path(capture) / "registration", capture=cap)
    names = expressions or reg.expression_names
    missing = [n for n in names if n not in reg.expression_names]
    if missing:
        raise ValueError(f"expressions not registered: {', '.join(missing)}")
    if not names:
        raise ValueError("the registration holds no expressions")
    unregistered = [n for n in cap.expression_names if n not in reg.expression_names]
    if expressions is None and unregistered and not allow_partial:
        raise RegistrationError(f"{reg.root}: the registration covers {len(reg.expression_names)} of the capture's "
                                f"{len(cap.expression_names)} expressions (not registered: {', '.join(unregistered)}); "
                                "register them first (mifacerf register CAPTURE), or build from the registered ones "
                                "alone with --allow-partial")
    cams = [cap.rig.camera(c) for c in (cameras or cap.camera_names)]
    cam_idx = [cap.camera_names.index(c.name) for c in cams]
    t = reg.check_template(names, template_arrays)     # the template the registration was made on
    neutral = names[0] if "neutral" not in names else "neutral"
    geometry = {n: reg.expression(n) for n in names}
    exts, ext_report, keep = extension_report(reg, names, geometry, t, cam_idx)
    t["triangles"] = t["triangles"][keep]
    tri_ext = triangle_extensions(t["triangles"], exts, t["n_vertices"])
    writer = ModelWriter(out, cap.rig.lights.directions, cap.rig.lights.solid_angles, cams,
                         [(n, cap.expressions[cap.expression_index(n)].category) for n in names],
                         t["triangles"], template=reg.template, neutral=neutral, overwrite=overwrite)
    with writer:    # a failure discards the new folder and leaves out as it was
        jobs = [(n, cam) for n in names for cam in cams]
        context = FieldContext(capture, reg.root, t["triangles"], reg, geometry)
        fields = (executor or Executor()).imap(field_unit, jobs, context, desc="build", unit="field", progress=progress)
        for (name, cam), (pixels, tri, bary, depth, rf) in zip(jobs, fields):   # written here, in the jobs' order
            if exts:    # texels per extension (the report)
                per = np.bincount(tri_ext[tri] + 1, minlength=len(exts) + 1)[1:]
                for k, ext in enumerate(exts):
                    ext_report[ext.name]["texels"] += int(per[k])
            writer.write_field(name, cam, pixels, tri, bary, depth, rf)
        for name in names:
            r = geometry[name]
            writer.add_geometry(r.vertices, r.visible[cam_idx], r.status, r.eye_centres, r.teeth, r.head_pose)
        sources = np.stack([geometry[n].vertices for n in names])
        blend = BlendModel.fit(sources, names.index(neutral), t["triangles"], fiducial_mask=t["fiducial"],
                               regions=t["regions"] if (culling and t["regions"]) else None)
        visibility = part_visibility(reg, names, reg.template, t["triangles"], cams)
        references = choose_references(visibility)
        sources = part_sources(visibility, references)
        if ext_report:
            writer.extra["extensions"] = ext_report
        writer.extra["references"] = references
        writer.extra["part_sources"] = sources
        writer.extra["parts"] = build_part_fields(writer, reg, reg.template, t["triangles"], cams, sources,
                                                  cap.rig.lights.directions)
        writer.extra["surface"] = dict(reg.meta.get("surface") or surface_entry(1))
        writer.extra["source"] = {"capture": str(Path(capture).resolve()),
                                  "registration": str(reg.root.resolve())}
        return writer.finish(blend)
