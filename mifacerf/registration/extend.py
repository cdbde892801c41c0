"""Extensions added to a finished registration, without registering the face again (issue 16).

A user who registered a capture on a face-only template and then declares extensions (scalp, ears,
neck; docs/registration.md) need not redo hours of dot snapping: :func:`extend_registration` takes
the capture's ``hand/template.json`` — the registered template's vertices unchanged and first, the
extension vertices after them — and writes a new registration folder in which every expression keeps
its registered face (vertices, status, head pose, teeth, eyes, dot-free patches, report) and gains the
extensions placed as :func:`mifacerf.registration.register.register_capture` places them
(:func:`.extensions.place_in_expression`), with texture coordinates and per-vertex visibility of the
whole mesh. Reads only the capture (manifest, ``hand/``) and the registration; never the truth.

Not the same as registering on the extended template: there, the extensions also occlude dots during
the snap (a dot behind an ear in a side view is not searched in that view).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..formats.capture import Capture
from ..formats.registration import RegisteredExpression, Registration, RegistrationWriter
from ..geometry.boubekeur2008 import check_curved, surface_entry
from ..geometry.footprint import centre_footprint
from ..geometry.visibility import Visibility
from .extensions import (check_extensions, extensions_from_template, fit_extensions_to_outlines,
                         place_in_expression)
from .hand import read_hand_inputs
from .register import Options, RegistrationInputError
from .texcoords import texture_coordinates

#: registration-wide entries carried over unchanged
META_KEYS = ("options", "hand_input_problems", "dot_filter", "head_points_neutral", "eyes_head_frame", "eyes")


def extend_registration(capture, registration=None, out=None, log=None, silhouettes: bool = True,
                        curved: int | None = None) -> Path:
    """Write ``out`` (default ``CAPTURE/registration-extended``): the registration ``registration`` (default
    ``CAPTURE/registration``) with the extensions of ``CAPTURE/hand/template.json`` placed in every
    expression. Refuses a template whose first vertices are not the registered template's.

    ``silhouettes``: first move the template's extension vertices so that, placed in the neutral, their
    outline in every capture camera lies on the subject's (:func:`.extensions.refine_template_extensions`,
    mattes from the neutral's diffuse proxies against the stage's dark background); the registration's
    ``template.json`` carries the moved positions and the neutral's report says how far they moved.
    ``curved``: the surface renders trace (``Options.curved``; default: the old registration's ``surface``,
    else ``Options``' default); the outline fit is made against it and the new folder records it."""
    log = log or (lambda msg: None)
    cap = capture if isinstance(capture, Capture) else Capture(capture)
    old = Registration(registration or cap.root / "registration", capture=cap)
    out = Path(out) if out is not None else cap.root / "registration-extended"
    hand = read_hand_inputs(cap.root, cap.camera_names)
    tpl = hand.template
    where = cap.root / "hand" / "template.json"
    if tpl is None:
        raise RegistrationInputError(f"{where}: no usable template ({'; '.join(hand.problems) or 'missing'})")
    n_face = len(old.template["vertices"])
    same = len(tpl.vertices) >= n_face and [(v["kind"], v["position"]) for v in old.template["vertices"]] == \
        [(v["kind"], v["position"]) for v in tpl.raw["vertices"][:n_face]]
    if not same:
        raise RegistrationInputError(f"{where}: its first {n_face} vertices are not those of the registered template "
                                     f"{old.root / 'template.json'}: register on it instead (mifacerf register --force)")
    try:
        exts = extensions_from_template(tpl.raw, tpl.n_vertices)
        check_extensions(tpl.vertices, tpl.triangles, tpl.dot_ids, exts)
    except ValueError as exc:
        raise RegistrationInputError(f"{where}: {exc}") from exc
    covered = np.zeros(tpl.n_vertices, bool)
    for e in exts:
        covered[e.vertices] = True
    if not exts or covered[:n_face].any() or not covered[n_face:].all():
        raise RegistrationInputError(f"{where}: the vertices after the registered template's {n_face} must be "
                                     "exactly the extensions' (and the extensions none of the registered ones)")
    cams = list(cap.rig.cameras)
    vis = Visibility(tpl.triangles, tpl.n_vertices, tol=max(0.5 * centre_footprint(cams), 5e-4))
    names = old.expression_names
    neutral = next((e.name for e in cap.expressions if e.category == "neutral" and e.name in names), names[0])
    if curved is None:
        curved = (old.meta.get("surface") or {}).get("curved", Options.curved)
    curved = check_curved(curved)
    rest, refined, raw = tpl.vertices, None, tpl.to_dict()
    if silhouettes:
        rest, refined = _refined_rest(cap, old, tpl, exts, neutral, n_face, cams, vis, curved)
        raw["vertices"] = [dict(v, position=np.round(rest[i], 7).tolist()) if i >= n_face else v
                           for i, v in enumerate(raw["vertices"])]
        log(f"extensions fitted to the neutral's outlines: {refined['summary']}")
    writer = RegistrationWriter(out, cap, raw, fresh=True)
    try:
        for key in META_KEYS:
            if key in old.meta:
                writer.set_meta(key, old.meta[key])
        writer.set_meta("surface", surface_entry(curved))
        N = None
        for name in [neutral] + [n for n in names if n != neutral]:
            r = old.expression(name)
            report = dict(old.report(name))
            V = np.concatenate([r.vertices, tpl.vertices[n_face:]])
            status = np.concatenate([r.status, np.zeros(tpl.n_vertices - n_face, r.status.dtype)])
            predicted = str((report.get("head_pose") or {}).get("source", "")).startswith("none")
            rep = place_in_expression(rest, tpl.triangles, tpl.dot_ids, exts, V, status, r.head_pose,
                                      neutral=N, head_predicted=predicted)
            if refined is not None and name == neutral:
                rep["silhouettes"] = refined
            report["extensions"] = rep
            report["flags"] = list(report.get("flags", [])) + rep["fallbacks"] + [
                "extensions placed on an existing registration (mifacerf.registration.extend)"]
            uv, visible = texture_coordinates(V, cams, vis)
            reg = RegisteredExpression(name, V, status, uv, visible, r.eye_centres, r.teeth, r.head_pose)
            for cam in cap.camera_names:
                patch = old.dotfree_patch(name, cam)
                if patch is not None:
                    writer.write_dotfree(name, cam, *patch)
            writer.write_expression(reg, report)
            if name == neutral:
                N = reg
            log(f"{name}: extensions placed")
    except BaseException:
        writer.abort()
        raise
    return writer.finish()


def _refined_rest(cap, old, tpl, exts, neutral, n_face, cams, vis, curved) -> tuple[np.ndarray, dict]:
    """The template with its extensions fitted to the neutral's outlines, and the fit's report."""
    from .proxies import proxies_for

    r = old.expression(neutral)
    V = np.concatenate([r.vertices, tpl.vertices[n_face:]])
    status = np.concatenate([r.status, np.zeros(tpl.n_vertices - n_face, r.status.dtype)])
    images = [proxies_for(cap, neutral, c.name).diffuse for c in cams]
    return fit_extensions_to_outlines(tpl.vertices, tpl.triangles, tpl.dot_ids, exts, V, status, r.head_pose,
                                      cams, images, vis, curved=curved)
