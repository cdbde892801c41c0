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

Bad input: an extension not attached to the face (no vertex shared with a face triangle) is an error
naming the gap; a driven region with no fiducial within ``falloff`` of any of its vertices falls back
to rigid with the head and says so in the report (``fallbacks``).

Not yet wired into :func:`mifacerf.registration.register.register_capture` nor produced by the
template writers (issue 16 items 1-2 open): this module is the placement rule and its checks.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry.rigid import apply, robust_rigid
from ..geometry.schaefer2006 import mls_affine

MODES = ("rigid", "driven")


@dataclass(frozen=True)
class Extension:
    """One template extension: ``vertices`` (template vertex indices, no fiducials among them),
    ``mode`` ('rigid' or 'driven'), ``falloff`` (metres; driven only)."""
    name: str
    vertices: np.ndarray
    mode: str = "rigid"
    falloff: float = 0.03

    def __post_init__(self):
        if self.mode not in MODES:
            raise ValueError(f"extension {self.name!r}: unknown mode {self.mode!r}; choose one of {', '.join(MODES)}")
        if self.mode == "driven" and not self.falloff > 0:
            raise ValueError(f"extension {self.name!r}: falloff must be > 0 metres, got {self.falloff}")


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
        rigid = apply(T, X[v])
        mode = ext.mode
        if mode == "driven":
            src, dst = X[fid][good], R[good]
            d = np.min(np.linalg.norm(X[v][:, None] - src[None], axis=2), axis=1)
            if not (d < ext.falloff).any():
                report["fallbacks"].append(f"extension {ext.name!r}: no registered fiducial within "
                                           f"{1000 * ext.falloff:.0f} mm (nearest {1000 * d.min():.1f} mm): "
                                           "rigid with the head")
                mode = "rigid"
            else:
                w = falloff_weight(d, ext.falloff)[:, None]
                driven = mls_affine(src, dst, X[v], k=min(12, len(src)))
                out[v] = rigid + w * (driven - rigid)
        if mode == "rigid":
            out[v] = rigid
        report["extensions"][ext.name] = {"mode": mode, "vertices": int(len(v))}
    return out, report
