"""Template extensions: surfaces the cameras see beyond the fiducials (paper §3 "extensions").

An extension is a region of the template — scalp or hair cap, ears, neck down to a cut, the back of
the head — that carries no fiducials, so the registration cannot place it from dots. Each expression
places it from what is registered:

* ``rigid``: with the head pose (scalp, hair, ears): the rigid map of the template's fiducials onto
  the registered ones (or the head transform the caller gives);
* ``driven``: a smooth deformation driven by the nearest registered fiducials (neck, jaw underside,
  temple): a moving-least-squares affine map of the fiducials' motion (:func:`mls_affine`), blended
  into the rigid placement with a falloff in the distance to the nearest fiducial — full at the
  fiducials, rigid beyond ``falloff`` metres — so the skin between follows the face and the far end
  of the region moves with the head.

Each extension has an ``anchor``: ``head`` (default) or ``body`` — what it follows where no fiducial
drives it. ``body`` is the capture's world frame (the subject's shoulders do not move between
expressions): the base of the neck, which must not turn with the head.

Bad input: an extension not attached to the face (no vertex shared with a face triangle, or a
group of extensions connected to each other but not to the face) is an error naming the gap; a driven
region with no fiducial within ``falloff`` of any of its vertices falls back to rigid with its anchor
and says so in the report (``fallbacks``).

The template declares extensions in its ``extensions`` member (docs/registration.md, read by
:func:`extensions_from_template`); :func:`mifacerf.registration.register.register_capture` places them
per expression after the fiducials are registered.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry.rigid import apply, robust_rigid
from ..geometry.schaefer2006 import mls_affine

MODES = ("rigid", "driven")
ANCHORS = ("head", "body")


@dataclass(frozen=True)
class Extension:
    """One template extension: ``vertices`` (template vertex indices, no fiducials among them),
    ``mode`` ('rigid' or 'driven'), ``falloff`` (metres; driven only), ``anchor`` ('head' or 'body')."""
    name: str
    vertices: np.ndarray
    mode: str = "rigid"
    falloff: float = 0.03
    anchor: str = "head"

    def __post_init__(self):
        if self.mode not in MODES:
            raise ValueError(f"extension {self.name!r}: unknown mode {self.mode!r}; choose one of {', '.join(MODES)}")
        if self.anchor not in ANCHORS:
            raise ValueError(f"extension {self.name!r}: unknown anchor {self.anchor!r}; choose one of "
                             f"{', '.join(ANCHORS)}")
        if self.mode == "driven" and not self.falloff > 0:
            raise ValueError(f"extension {self.name!r}: falloff must be > 0 metres, got {self.falloff}")


def extensions_from_template(template: dict, n_vertices: int | None = None) -> list[Extension]:
    """The :class:`Extension` list a template dict declares (its optional ``extensions`` member,
    docs/registration.md); [] for a template without one. Refuses ids out of range, an empty extension
    and a vertex in two extensions, naming the extension."""
    decl = template.get("extensions") or {}
    if not isinstance(decl, dict):
        raise ValueError("template 'extensions' must be an object {name: {vertices, mode, ...}}")
    n = len(template.get("vertices", [])) if n_vertices is None else int(n_vertices)
    out, owner = [], {}
    for name, e in decl.items():
        try:
            v = np.asarray(e["vertices"], np.int64).reshape(-1)
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"extension {name!r}: needs 'vertices', a list of template vertex ids ({exc})") from exc
        if not len(v):
            raise ValueError(f"extension {name!r} has no vertices")
        if v.min() < 0 or v.max() >= n:
            raise ValueError(f"extension {name!r}: vertex ids outside [0, {n})")
        for i in v.tolist():
            if i in owner:
                raise ValueError(f"vertex {i} is in two extensions ({owner[i]!r} and {name!r})")
            owner[i] = name
        out.append(Extension(str(name), v, str(e.get("mode", "rigid")), float(e.get("falloff", 0.03)),
                             str(e.get("anchor", "head"))))
    return out


def check_extensions(template, faces, fiducials, extensions) -> None:
    """Every extension attached to the face: none holds a fiducial, each shares a vertex with a triangle
    outside it (:func:`check_attached`) and every connected piece of the mesh that holds extension
    vertices also holds face vertices (no group of extensions stitched to each other alone)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    X = np.asarray(template, np.float64)
    F = np.asarray(faces, np.int64)
    fid_set = set(np.asarray(fiducials, int).tolist())
    is_ext = np.zeros(len(X), bool)
    for ext in extensions:
        v = np.asarray(ext.vertices, int)
        if fid_set & set(v.tolist()):
            raise ValueError(f"extension {ext.name!r} holds fiducials; an extension carries none")
        check_attached(ext.name, v, F, X)
        is_ext[v] = True
    if not is_ext.any() or not len(F):
        return
    e = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    G = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(len(X), len(X)))
    _, comp = connected_components(G, directed=False)
    used = np.zeros(len(X), bool)
    used[F.ravel()] = True
    face_comps = set(comp[used & ~is_ext].tolist())
    for ext in extensions:
        v = np.asarray(ext.vertices, int)
        lone = [c for c in set(comp[v].tolist()) if c not in face_comps]
        if lone:
            pts = X[v][np.isin(comp[v], lone)]
            rest = X[used & ~is_ext]
            gap = np.min(np.linalg.norm(pts[:, None] - rest[None], axis=2)) if len(rest) else float("nan")
            raise ValueError(f"extension {ext.name!r} is not attached to the face: its piece of the mesh "
                             f"reaches no face vertex (gap {1000 * gap:.1f} mm to the nearest face vertex); "
                             "stitch it to the face's border")


def falloff_weight(distance, falloff: float) -> np.ndarray:
    """1 at a fiducial, 0 from ``falloff`` on, smooth (C1 smoothstep) between."""
    s = np.clip(1.0 - np.asarray(distance, np.float64) / falloff, 0.0, 1.0)
    return s * s * (3.0 - 2.0 * s)


def check_attached(name: str, vertices, faces, template) -> None:
    """Raise when extension ``vertices`` share no vertex with a triangle of the face (the rest)."""
    ext = np.zeros(len(template), bool)
    ext[np.asarray(vertices, int)] = True
    faces = np.asarray(faces, int)
    in_ext = ext[faces]
    face_tris = ~in_ext.all(1)                        # triangles with a non-extension vertex: the face
    if (in_ext[face_tris]).any():
        return
    rest = np.unique(faces[face_tris])
    if not len(rest):
        raise ValueError(f"extension {name!r}: the template has no face triangles to attach it to")
    X = np.asarray(template, np.float64)
    gap = np.min(np.linalg.norm(X[np.asarray(vertices, int)][:, None] - X[rest][None], axis=2))
    raise ValueError(f"extension {name!r} is not attached to the face: it shares no vertex with a face "
                     f"triangle (gap {1000 * gap:.1f} mm to the nearest face vertex); stitch it to the face's border")


def place_extensions(template, faces, fiducials, registered, extensions, head=None) -> tuple[np.ndarray, dict]:
    """Place every extension for one expression.

    ``template`` (V, 3) neutral template positions; ``faces`` (F, 3); ``fiducials`` (K,) template
    indices of the fiducials; ``registered`` (K, 3) their registered positions in this expression
    (NaN rows: not registered); ``extensions`` list of :class:`Extension`; ``head`` optional (4, 4)
    head transform (default: a robust rigid fit of the fiducials). Returns the (V, 3) template with
    the extensions' vertices placed (other vertices untouched) and a report
    ``{"extensions": {name: {"mode", "vertices"}}, "fallbacks": [message, ...]}``.
    """
    X = np.asarray(template, np.float64)
    fid = np.asarray(fiducials, int)
    R = np.asarray(registered, np.float64)
    good = np.isfinite(R).all(1)
    if good.sum() < 3:
        raise ValueError(f"{int(good.sum())} registered fiducials: at least 3 are needed to place extensions")
    T = robust_rigid(X[fid], R) if head is None else np.asarray(head, np.float64)
    out = X.copy()
    report = {"extensions": {}, "fallbacks": []}
    fid_set = set(fid.tolist())
    for ext in extensions:
        v = np.asarray(ext.vertices, int)
        if fid_set & set(v.tolist()):
            raise ValueError(f"extension {ext.name!r} holds fiducials; an extension carries none")
        check_attached(ext.name, v, faces, X)
        rigid = apply(T, X[v]) if ext.anchor == "head" else X[v].copy()
        mode = ext.mode
        if mode == "driven":
            src, dst = X[fid][good], R[good]
            d = np.min(np.linalg.norm(X[v][:, None] - src[None], axis=2), axis=1)
            if not (d < ext.falloff).any():
                report["fallbacks"].append(f"extension {ext.name!r}: no registered fiducial within "
                                           f"{1000 * ext.falloff:.0f} mm (nearest {1000 * d.min():.1f} mm): "
                                           f"rigid with the {ext.anchor}")
                mode = "rigid"
            else:
                w = falloff_weight(d, ext.falloff)[:, None]
                driven = mls_affine(src, dst, X[v], k=min(12, len(src)))
                out[v] = rigid + w * (driven - rigid)
        if mode == "rigid":
            out[v] = rigid
        report["extensions"][ext.name] = {"mode": mode, "anchor": ext.anchor, "vertices": int(len(v))}
    return out, report


def place_in_expression(template, faces, fiducials, extensions, V, status, head, neutral=None,
                        head_predicted: bool = False) -> dict:
    """One registered expression's extensions: ``V`` (T, 3) and ``status`` (T,) updated in place.

    ``template`` (T, 3) the user's neutral template (the extensions' own positions); ``V``/``status`` the
    expression's registered vertices (fiducials with status 1 drive); ``head`` (4, 4) its head pose
    (neutral → expression); ``neutral``: the registered neutral (``vertices``, ``status``), None when this
    *is* the neutral — the driven map is then the fiducials' motion from the user's template positions.
    Status of the extension vertices: 1 (placed from registered data) unless ``head_predicted`` or fewer
    than three fiducials are registered (then left where the template has them, 0). Returns the report
    of :func:`place_extensions` (``mode`` 'template' for that last case)."""
    fid = np.asarray(fiducials, int)
    base = np.asarray(template, np.float64).copy()
    R = np.asarray(V, np.float64)[fid].copy()
    ok = np.asarray(status)[fid] == 1
    if neutral is not None:
        base[fid] = neutral.vertices[fid]
        ok &= np.asarray(neutral.status)[fid] == 1
    R[~ok] = np.nan
    try:
        P, rep = place_extensions(base, faces, fid, R, extensions, head=head)
        placed = not head_predicted
    except ValueError as exc:             # fewer than three registered fiducials
        P, placed = base, False
        rep = {"extensions": {e.name: {"mode": "template", "anchor": e.anchor, "vertices": int(len(e.vertices))}
                              for e in extensions},
               "fallbacks": [f"{exc}: every extension left where the template has it (predicted)"]}
    ids = np.unique(np.concatenate([np.asarray(e.vertices, int) for e in extensions]))
    V[ids] = P[ids]
    status[ids] = 1 if placed else 0
    return rep
