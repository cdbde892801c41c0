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


# ---------------------------------------------------------------- silhouettes
# The extensions' own positions come from the user's template (no fiducials: nothing in the images pins
# them), so a template placed with clicking error keeps it in every expression, and the outline a render
# shows is off the subject's by that much. The capture's images do pin one thing about them: where the
# head ends against the stage's dark background. :func:`refine_to_silhouettes` moves the extension
# vertices along their normals until the mesh's outline in every capture camera lies on the subject's.

def silhouette_matte(image, floor: float = 1e-4) -> np.ndarray:
    """(H, W) coverage of the subject in a capture image (H, W, 3) lit evenly against a dark background
    (the diffuse proxy, :mod:`.proxies`): 1 on the support eroded by one pixel, and on its border the
    pixel's brightness over that of the nearest interior pixel (an edge pixel is the surface times its
    coverage), 0 where the image is dark (below ``floor`` of its maximum)."""
    from scipy.ndimage import binary_erosion, distance_transform_edt

    lum = np.asarray(image, np.float64)
    lum = lum.mean(-1) if lum.ndim == 3 else lum
    support = lum > floor * max(float(lum.max()), 1e-30)
    inner = binary_erosion(support, np.ones((3, 3), bool), border_value=1)
    if not inner.any():
        return support.astype(np.float64)
    _, (ii, jj) = distance_transform_edt(~inner, return_indices=True)
    alpha = np.clip(lum / np.maximum(lum[ii, jj], 1e-30), 0.0, 1.0)
    alpha[inner] = 1.0
    alpha[~support] = 0.0
    return alpha


def mesh_matte(scene, camera, spp: int = 8, rays=None) -> np.ndarray:
    """(H, W) coverage of a :class:`~mifacerf.geometry.meshscene.MeshScene` in ``camera``: the share of
    each pixel's ``spp`` stratified samples (box filter, as the capture's pixels) that hit it. ``rays``: a
    :class:`MatteRays` of this camera (traced only in its band, elsewhere its ``outside`` values)."""
    rays = rays or MatteRays(camera, spp)
    hit = scene.trace(rays.origin, rays.directions).valid
    out = rays.outside.copy()
    out.reshape(-1)[rays.pixels] = hit.reshape(len(rays.pixels), rays.spp).mean(-1)
    return out


class MatteRays:
    """The sample rays of :func:`mesh_matte` in ``camera`` (``spp`` per pixel), made once for many traces:
    every pixel, or only those within ``band_px`` of the outline of ``matte`` (H, W) (elsewhere the matte
    rounded is taken as the mesh's coverage: far from the subject's outline, as
    :func:`refine_to_silhouettes` needs, where its search cannot reach)."""

    def __init__(self, camera, spp: int = 8, matte=None, band_px: float | None = None):
        from ..camera import stratified_pixel_samples

        H, W = camera.height, camera.width
        self.spp = int(spp)
        if matte is None or band_px is None:
            self.pixels = np.arange(H * W)
            self.outside = np.zeros((H, W))
        else:
            from scipy.ndimage import binary_dilation

            m = np.asarray(matte, np.float64)
            inside = m >= 0.5
            edge = (m > 0) & (m < 1) | (inside ^ binary_dilation(inside))
            r = int(np.ceil(band_px))
            yy, xx = np.mgrid[-r:r + 1, -r:r + 1]
            band = binary_dilation(edge, (xx ** 2 + yy ** 2) <= band_px ** 2)
            self.pixels = np.flatnonzero(band)
            self.outside = inside.astype(np.float64)
        uv = stratified_pixel_samples(W, H, self.spp, seed=0).reshape(H * W, self.spp, 2)[self.pixels]
        self.origin, self.directions = camera.pixel_rays(uv.reshape(-1, 2))


def _crossing(matte, u, v, t, step):
    """Per row of sample lines (u, v) (n, k) at parameters ``t`` (k,): the crossing of coverage 0.5
    from inside to outside nearest to t = 0 (inf where none)."""
    from scipy.ndimage import map_coordinates

    a = map_coordinates(np.asarray(matte, np.float64), [np.nan_to_num(v), np.nan_to_num(u)], order=1,
                        mode="constant", cval=0.0)
    inside = a >= 0.5
    cross = inside[:, :-1] & ~inside[:, 1:]
    frac = (a[:, :-1] - 0.5) / np.maximum(a[:, :-1] - a[:, 1:], 1e-12)
    tc = np.where(cross, t[None, :-1] + frac * step, np.inf)
    return np.take_along_axis(tc, np.argmin(np.abs(tc), axis=1)[:, None], 1)[:, 0]


def outline_offsets(V, N, ids, camera, matte, own, max_cos: float = 0.15, search_px: float = 4.0,
                    step_px: float = 0.25) -> tuple[np.ndarray, np.ndarray]:
    """For vertices ``ids`` on the mesh's outline in ``camera`` (normal within ``max_cos`` of
    perpendicular to the view ray), how far (m, along the normal; + outwards) the subject's outline in
    ``matte`` (H, W) lies beyond the mesh's own in ``own`` (H, W, :func:`mesh_matte`): on the image line
    through the vertex along its projected normal, each outline is the crossing of coverage 0.5 from
    inside to outside nearest to the vertex, within ``search_px``. Returns (offsets (n,), weights (n,);
    0 where not on the outline or a crossing is missing)."""
    P, n = V[ids], N[ids]
    view = P - camera.centre
    view /= np.maximum(np.linalg.norm(view, axis=1, keepdims=True), 1e-30)
    cos = np.abs((view * n).sum(1))
    eps = 1e-3
    uv0, z0 = camera.project(P)
    uv1, _ = camera.project(P + eps * n)
    du = uv1 - uv0
    jac = np.linalg.norm(du, axis=1) / eps                      # pixels per metre along the normal
    ok = (cos < max_cos) & (z0 > 0) & np.isfinite(uv0).all(1) & (jac > 1.0)
    m = du / np.maximum(np.linalg.norm(du, axis=1, keepdims=True), 1e-30)
    t = np.arange(-search_px, search_px + 1e-9, step_px)
    u = uv0[:, None, 0] + t[None] * m[:, None, 0]
    v = uv0[:, None, 1] + t[None] * m[:, None, 1]
    with np.errstate(invalid="ignore"):           # no crossing in either: inf - inf
        diff = _crossing(matte, u, v, t, step_px) - _crossing(own, u, v, t, step_px)
    ok &= np.isfinite(diff)
    off = np.where(ok, diff / np.maximum(jac, 1e-30), 0.0)
    w = np.where(ok, 1.0 - cos / max_cos, 0.0)
    return off, w


def refine_to_silhouettes(V, faces, ids, cameras, mattes, visible=None, iterations: int = 8,
                          smoothness: float = 0.1, max_step: float = 0.003, curved: int = 1, poses=(),
                          **options) -> tuple[np.ndarray, dict]:
    """Move the vertices ``ids`` of mesh ``V`` (T, 3) along their normals so that the mesh's outline in each
    of ``cameras`` lies on the subject's outline in its ``mattes`` (H, W) (:func:`silhouette_matte`).

    Each round measures, for every vertex on the outline of some camera where it is ``visible`` (C, T)
    bool (default: everywhere), the offset to the subject's outline (:func:`outline_offsets`; ``options``
    go there), and solves for a smooth displacement of all ``ids`` (weighted least squares on the
    measurements + ``smoothness`` × the squared differences across mesh edges; the other vertices of the
    mesh stay fixed, so the extensions stay stitched to the face), each step clipped to ``max_step`` m.
    ``curved``: the mesh's outline is that of its Phong surface at this level
    (:class:`~mifacerf.geometry.meshscene.CurvedMeshScene`; 1: the flat triangles) — fit against the surface
    the renders will trace, or the outline is off by the chords' sag (docs/rendering.md, "Phong surface").
    ``poses``: more views of the same vertices, each ``(V_k (T, 3), cameras_k, mattes_k, visible_k or None)``
    (the mesh in another expression, the extensions placed rigidly or nearly so): they share the one
    displacement along the normals (a rigid motion keeps a displacement along the normal one), so a
    turned head's outlines constrain vertices the first pose's outlines never pass through.
    Returns (the moved (T, 3) copy of ``V``, a report: vertices measured, mean |offset| first and last;
    ``moved_poses``: the other poses' moved copies)."""
    from scipy.sparse import coo_matrix, diags
    from scipy.sparse.linalg import spsolve

    from ..geometry.boubekeur2008 import check_curved
    from ..geometry.meshscene import CurvedMeshScene, MeshScene
    from ..geometry.visibility import vertex_normals

    curved = check_curved(curved)
    views = [(V, cameras, mattes, visible)] + [tuple(p) for p in poses]
    Vs = [np.asarray(v[0], np.float64).copy() for v in views]
    F = np.asarray(faces, np.int64)
    T = len(Vs[0])
    if any(v.shape != (T, 3) for v in Vs):
        raise ValueError(f"every pose needs ({T}, 3) vertices, got {[v.shape for v in Vs]}")
    ids = np.unique(np.asarray(ids, np.int64))
    free = np.full(T, -1, np.int64)
    free[ids] = np.arange(len(ids))
    e = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    e = np.unique(np.sort(e, axis=1), axis=0)
    e = e[(free[e] >= 0).any(1)]
    report = {"vertices": int(len(ids)), "poses": len(views), "rounds": []}
    scenes = [MeshScene(v, F) if curved == 1 else CurvedMeshScene(v, F, curved) for v in Vs]
    search = float(options.get("search_px", 4.0))
    rays = [[MatteRays(cam, matte=matte, band_px=2 * search + 2) for cam, matte in zip(view[1], view[2])]
            for view in views]
    for _ in range(max(0, int(iterations))):
        Ns = [vertex_normals(v, F) for v in Vs]
        num = np.zeros(len(ids))
        den = np.zeros(len(ids))
        for k, (_, cams, mats, vis) in enumerate(views):
            scenes[k].set_vertices(Vs[k])
            for c, (cam, matte) in enumerate(zip(cams, mats)):
                sel = ids if vis is None else ids[np.asarray(vis)[c, ids]]
                if not len(sel):
                    continue
                off, w = outline_offsets(Vs[k], Ns[k], sel, cam, matte,
                                         mesh_matte(scenes[k], cam, rays=rays[k][c]), **options)
                np.add.at(num, free[sel], w * off)
                np.add.at(den, free[sel], w)
        seen = den > 0
        if not seen.any():
            break
        d = np.where(seen, num / np.maximum(den, 1e-30), 0.0)
        # smooth displacement s of the free vertices: (W + λ L_ff) s = W d  (fixed neighbours at 0)
        a, b = free[e[:, 0]], free[e[:, 1]]
        rows, cols, vals = [], [], []
        for x, y in ((a, b), (b, a)):
            keep = x >= 0
            rows += [x[keep], x[keep]]
            cols += [x[keep], np.where(y[keep] >= 0, y[keep], x[keep])]
            vals += [np.full(keep.sum(), smoothness), np.where(y[keep] >= 0, -smoothness, 0.0)]
        L = coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                       shape=(len(ids), len(ids))).tocsr()
        A = (L + diags(den + 1e-9)).tocsc()
        s = np.clip(spsolve(A, den * d), -max_step, max_step)
        for v, N in zip(Vs, Ns):
            v[ids] += s[:, None] * N[ids]
        report["rounds"].append({"measured": int(seen.sum()), "mean_abs_offset_mm": float(1000 * np.abs(d[seen]).mean()),
                                 "mean_abs_step_mm": float(1000 * np.abs(s).mean())})
    if len(Vs) > 1:
        report["moved_poses"] = Vs[1:]
    return Vs[0], report


def fit_extensions_to_outlines(template, faces, fiducials, extensions, V, status, head, cameras, images, vis,
                               **options) -> tuple[np.ndarray, dict]:
    """The user's template (T, 3) with its extension vertices fitted to a registered expression's outlines
    (the neutral's, in practice): the extensions placed in a copy of ``V`` / ``status`` (T, 3) / (T,) from its
    registered fiducials and head pose ``head`` (:func:`place_in_expression`), a matte per camera from
    ``images`` (one evenly lit image per camera against the stage's dark background: the diffuse proxies,
    :func:`silhouette_matte`), the vertices' visibility from ``vis`` (:class:`~mifacerf.geometry.visibility.
    Visibility`), then :func:`refine_template_extensions` (``options`` go to :func:`refine_to_silhouettes`).
    Returns (template copy, report with ``moved_mm`` {mean, max} and a one-line ``summary``)."""
    from .texcoords import texture_coordinates

    X = np.asarray(template, np.float64)
    V = np.asarray(V, np.float64).copy()
    status = np.asarray(status).copy()
    place_in_expression(X, faces, fiducials, extensions, V, status, head)
    mattes = [silhouette_matte(im) for im in images]
    _, visible = texture_coordinates(V, cameras, vis)
    rest, rep = refine_template_extensions(X, faces, extensions, V, head, cameras, mattes, visible, **options)
    ids = np.unique(np.concatenate([np.asarray(e.vertices, np.int64) for e in extensions]))
    moved = np.linalg.norm(rest[ids] - X[ids], axis=1)
    first, last = (rep["rounds"][0], rep["rounds"][-1]) if rep["rounds"] else ({}, {})
    rep["moved_mm"] = {"mean": float(1000 * moved.mean()), "max": float(1000 * moved.max())}
    rep["summary"] = (f"{first.get('measured', 0)} vertices on an outline, offset to the subject's "
                      f"{first.get('mean_abs_offset_mm', 0):.2f} -> {last.get('mean_abs_offset_mm', 0):.2f} mm; "
                      f"moved {rep['moved_mm']['mean']:.2f} mm on average (max {rep['moved_mm']['max']:.2f})")
    return rest, rep


def refine_template_extensions(template, faces, extensions, V, head, cameras, mattes, visible=None,
                               **options) -> tuple[np.ndarray, dict]:
    """The user's template (T, 3) with its extension vertices moved so that, placed in the registered
    neutral ``V`` (T, 3, extensions placed; ``head`` (4, 4) its head pose), their outline matches the
    capture's (:func:`refine_to_silhouettes` on ``mattes``, one per camera): the neutral's displacement is
    carried back into the template's frame by the head pose's rotation, so every expression that places
    the extensions from the template gets it. Returns (template copy, report)."""
    X = np.asarray(template, np.float64).copy()
    ids = np.unique(np.concatenate([np.asarray(e.vertices, np.int64) for e in extensions]))
    moved, report = refine_to_silhouettes(V, faces, ids, cameras, mattes, visible, **options)
    R = np.asarray(head, np.float64)[:3, :3] if head is not None else np.eye(3)
    X[ids] += (moved[ids] - np.asarray(V, np.float64)[ids]) @ R     # R^T d for each row d
    return X, report
