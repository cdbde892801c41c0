"""``mifacerf build``: assemble the relightable morphable model from a capture and its registration.

Reads only the capture folder and the registration folder (never ground truth):
per source expression its registered geometry and, per camera, its dot-free
reflectance field restricted to the pixels where the registered template is seen
(texel map by ray casting the pixel centres: triangle, barycentrics, depth), stored
texel-major in float16; the §5 blend model (local deformation spaces, Delaunay,
culling); the eye and teeth reference expressions.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..formats.capture import Capture
from ..formats.registration import Registration, RegistrationError
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


def build_model(capture: str | Path, out: str | Path, registration: str | Path | None = None,
                expressions: list[str] | None = None, cameras: list[str] | None = None,
                overwrite: bool = False, progress: bool = True, culling: bool = True,
                allow_partial: bool = False) -> Path:
    """Build a model folder ``out`` from ``capture`` (and ``registration``, default CAPTURE/registration);
    ``progress``: a bar over the fields.

    Without ``expressions``, every expression of the capture must be registered: a registration that
    covers fewer (an interrupted or partial ``register``) is an error unless ``allow_partial``, which
    builds from the registered ones. The model is written as one transaction
    (:class:`mifacerf.formats.model.ModelWriter`): a failure leaves ``out`` as it was."""
    from ..blending import BlendModel
    from ..progress import bar

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
    writer = ModelWriter(out, cap.rig.lights.directions, cap.rig.lights.solid_angles, cams,
                         [(n, cap.expressions[cap.expression_index(n)].category) for n in names],
                         t["triangles"], template=reg.template, neutral=neutral, overwrite=overwrite)
    with writer:    # a failure discards the new folder and leaves out as it was
        scene = None
        jobs = [(n, cam) for n in names for cam in cams]
        it = bar(jobs, progress, desc="build", unit="field")
        geometry = {}
        for name, cam in it:
            r = reg.expression(name)
            if name not in geometry:
                geometry[name] = r
                if scene is None:
                    scene = MeshScene(r.vertices, t["triangles"])
                scene.set_vertices(r.vertices)
            hits, _ = scene.render_hits(cam, spp=1)
            sel = np.flatnonzero(hits.valid)
            field = reg.field(name, cam.name)  # (L, H, W, 3)
            check_field(field, name, cam.name, lambda light: reg.capture.image_path(name, cam.name, light))
            rows, cols = sel // cam.width, sel % cam.width
            rf = field[:, rows, cols].transpose(1, 0, 2)
            writer.write_field(name, cam, np.stack([rows, cols], 1), hits.tri[sel], hits.bary[sel], hits.t[sel],
                               rf)
        for name in names:
            r = geometry[name]
            writer.add_geometry(r.vertices, r.visible[cam_idx], r.status, r.eye_centres, r.teeth, r.head_pose)
        sources = np.stack([geometry[n].vertices for n in names])
        blend = BlendModel.fit(sources, names.index(neutral), t["triangles"], fiducial_mask=t["fiducial"],
                               regions=t["regions"] if (culling and t["regions"]) else None)
        visibility = part_visibility(reg, names, reg.template, t["triangles"], cams)
        references = choose_references(visibility)
        sources = part_sources(visibility, references)
        writer.extra["references"] = references
        writer.extra["part_sources"] = sources
        writer.extra["parts"] = build_part_fields(writer, reg, reg.template, t["triangles"], cams, sources,
                                                  cap.rig.lights.directions)
        writer.extra["source"] = {"capture": str(Path(capture).resolve()),
                                  "registration": str(reg.root.resolve())}
        return writer.finish(blend)
