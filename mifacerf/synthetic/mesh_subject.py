"""Bring your own head: a neutral mesh plus expression meshes of the same topology (docs/your-own-head.md).

The expression meshes are linear blendshapes (``V = V0 + Σ w_i (V_i − V0)``) whose weights
``w_i ∈ [0, 1]`` are the parameter vector, e.g. an ARKit-style set. The result has the interface of
the procedural :class:`~mifacerf.synthetic.subject.Subject` (controls, presets, params, pose,
template, textures, ``split_skin``, ``without_dots``) and works with
:class:`~mifacerf.synthetic.scene.SubjectScene`::

    subj = load_mesh_subject("my_head/", scale=0.01, n_dots=300, shapes=["jaw*", "mouthSmile_?"])
    subj = load_mesh_subject("neutral.obj", {"jawOpen": "jawOpen.obj"}, albedo="albedo.png")
    print("\\n".join(subj.report))          # what was read, repaired, placed and measured

**The folder** holds ``neutral.obj`` (or ``.ply``), one mesh per expression (named by the file's stem),
optionally an albedo (``albedo.png``, or UDIM tiles ``albedo.1001.png``, ``albedo.1002.png`` …) and a
``subject.json``::

    {"neutral": "neutral.obj", "expressions": {"jawOpen": "jawOpen.obj", ...},
     "shapes": ["jaw*", "mouth*"],              # which expressions become controls (names or globs)
     "albedo": "albedo.png" | "albedo.<UDIM>.png",
     "scale": 0.01,                            # file units -> metres (0.01: centimetres)
     "placement": "auto" | "as_is" | [dx, dy, dz],
     "parts": {"Face": "skin", "Teeth": "teeth", "Eyelashes": "drop", ...},
     "presets": [{"name": "...", "category": "...", "weights": {"jawOpen": 0.5}}, ...]}

**Units, axes, placement.** Meshes are read in file units times ``scale`` (metres), +Y up, the face
looking along +Z (docs/conventions.md). ``placement: "auto"`` (the default) translates the head so
the midpoint of its eyeballs lands where the embedded head's is (no eyes: its nose tip on the
embedded head's), which puts it in the middle of the rig's working volume; ``"as_is"`` keeps the
file's coordinates; a list is an explicit offset (metres). The offset used is in :attr:`report`.

**Parts.** An OBJ's named groups (``g``, else ``o``, else ``usemtl``) are sub-meshes; each gets a
role: ``skin`` (textured, carries the dots and the template), ``eye`` (each side's eye groups become
the rigid part ``eye_left`` (+X) / ``eye_right``, moved by the best rigid fit of its vertices in each
pose, so gaze shapes turn it; textured with the embedded head's iris in an azimuthal map about +Z),
``teeth`` (split into ``teeth_upper`` / ``teeth_lower``: the teeth a jaw-opening shape moves, else
those below the middle; rigid), ``interior`` (gums, tongue, mouth and eye sockets: the deformable
``mouth_interior``, dark red), and ``drop`` (``lashes`` and ``hair`` are named but not rendered in
this version: dropped with a message). Defaults come from common group names
(:func:`default_role`); a group no default fits is an error asking for its role.

**Checks** (:class:`MeshSubjectError`, one line naming the file and the fix): unreadable files, NaNs,
units, expressions of another topology, selections matching nothing, UV layouts without area,
negative UVs, UDIM layouts with a one-image albedo, non-manifold skin, groups without a role, fewer
dots painted or seen than asked. Repairs (each one line in :attr:`report`): vertices no face uses
and zero-area skin triangles are left out; a skin without usable UVs and without an albedo gets an
xatlas atlas.

**Dots and template** are made on the skin the capture cameras see (:mod:`.mesh_template`); the
coverage of the visible skin is in :attr:`report` and ``template_info``.
"""
from __future__ import annotations

import copy
import fnmatch
import json
import re
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import MifacerfError
from .expressions import Control
from .presets import CATEGORIES, PRESET_SIZES, Expression
from .subject import Part, Pose, Textures, vertex_normals
from .textures import DOT_COLOUR, SKIN_BASE, build_atlas, encode_normals, rasterize

MESH_SUFFIXES = (".obj", ".ply", ".off", ".stl", ".glb", ".gltf")
ALBEDO_NAMES = ("albedo.png", "albedo.jpg", "albedo.jpeg", "albedo.exr")
ROLES = ("skin", "eye", "teeth", "interior", "lashes", "hair", "drop")
ROLE_ALIASES = {"mouth": "interior", "gums": "interior", "socket": "interior", "eyes": "eye", "eyeball": "eye",
                "tooth": "teeth", "lash": "lashes", "eyelashes": "lashes"}
#: where ``placement: "auto"`` puts the eyeballs' midpoint (else the nose tip): the embedded head's
EYES_MIDPOINT = np.array([0.0, 0.0055, 0.0655])
NOSE_TIP = np.array([0.0, -0.0267, 0.1127])
INTERIOR_COLOUR = np.array([0.36, 0.10, 0.09])


class MeshSubjectError(MifacerfError, ValueError):
    """Bad input for a mesh subject (the message names the file and the fix)."""


class MeshSubjectWarning(UserWarning):
    """A repair made while loading a mesh subject (also in ``MeshSubject.report``)."""


def default_role(group: str, n_groups: int) -> str | None:
    """The role of a sub-mesh from its name (case-insensitive), or None when no rule fits."""
    n = group.lower()
    rules = (("drop", ("occlusion", "lacrimal", "tear", "blend", "shadow", "caruncle", "cartilage")),
             ("lashes", ("lash",)),
             ("hair", ("hair", "brow", "beard", "moustache", "mustache")),
             ("interior", ("socket", "gum", "tongue", "mouth", "palate", "throat")),
             ("teeth", ("teeth", "tooth")),
             ("eye", ("sclera", "iris", "cornea", "pupil", "eyeball", "eye")),
             ("skin", ("face", "head", "neck", "skin", "scalp", "body", "ear")))
    for role, keys in rules:
        if any(k in n for k in keys):
            return role
    return "skin" if n_groups == 1 else None


# ------------------------------------------------------------------------------------------ reading
@dataclass
class _Spec:
    folder: Path | None
    neutral: Path
    expressions: dict
    albedo: object = None            # Path, {tile: Path}, or None
    scale: float = 1.0
    placement: object = "auto"
    parts: dict = field(default_factory=dict)
    presets: list | None = None
    shapes: list | None = None
    manifest: Path | None = None


def _udim_files(folder: Path, pattern: str) -> dict:
    """{tile: path} for a pattern with ``<UDIM>`` (or ``1001``-style names found in the folder)."""
    rx = re.compile("^" + re.escape(pattern).replace(re.escape("<UDIM>"), r"(1\d\d\d)") + "$")
    out = {}
    for p in sorted(folder.iterdir()):
        m = rx.match(p.name)
        if m:
            out[int(m.group(1))] = p
    return out


def _resolve(source, expressions, albedo) -> _Spec:
    src = Path(source)
    if src.is_dir():
        man = src / "subject.json"
        d = {}
        if man.exists():
            try:
                d = json.loads(man.read_text())
            except json.JSONDecodeError as exc:
                raise MeshSubjectError(f"{man}: not valid JSON (line {exc.lineno}: {exc.msg})") from None
            if not isinstance(d, dict):
                raise MeshSubjectError(f"{man}: must hold a JSON object (see docs/your-own-head.md)")
        cands = [p for p in sorted(src.iterdir()) if p.suffix.lower() in MESH_SUFFIXES]
        if "neutral" in d:
            neutral = src / d["neutral"]
        else:
            neutral = next((p for p in cands if p.stem.lower() == "neutral"), None)
            if neutral is None:
                raise FileNotFoundError(f"{src}: no neutral mesh (expected neutral.obj or neutral.ply, or "
                                        "\"neutral\" in subject.json)")
        if "expressions" in d:
            exprs = {k: src / v for k, v in d["expressions"].items()}
        else:
            exprs = {p.stem: p for p in cands if p != neutral}
        alb = d.get("albedo")
        if alb is None:
            alb = next((src / n for n in ALBEDO_NAMES if (src / n).exists()), None)
            if alb is None:
                for ext in ("png", "jpg", "exr"):
                    tiles = _udim_files(src, f"albedo.<UDIM>.{ext}")
                    if tiles:
                        alb = tiles
                        break
        elif "<UDIM>" in str(alb):
            tiles = _udim_files(src, str(alb))
            if not tiles:
                raise FileNotFoundError(f"{man}: no UDIM tile matches \"albedo\": {alb!r} (e.g. "
                                        f"{str(alb).replace('<UDIM>', '1001')})")
            alb = tiles
        else:
            alb = src / alb
        spec = _Spec(src, neutral, exprs, alb, float(d.get("scale", 1.0)), d.get("placement", "auto"),
                     dict(d.get("parts", {})), d.get("presets"), d.get("shapes"), man if man.exists() else None)
    else:
        if not src.exists():
            raise FileNotFoundError(f"neutral mesh not found: {src}")
        if expressions is None:
            exprs = {}
        elif isinstance(expressions, dict):
            exprs = {k: Path(v) for k, v in expressions.items()}
        else:
            exprs = {Path(p).stem: Path(p) for p in expressions}
        spec = _Spec(None, src, exprs, Path(albedo) if albedo is not None else None)
    if expressions and src.is_dir():
        spec.expressions = {k: Path(v) for k, v in dict(expressions).items()}
    if albedo is not None and src.is_dir():
        spec.albedo = Path(albedo)
    if not spec.neutral.exists():
        raise FileNotFoundError(f"neutral mesh not found: {spec.neutral}")
    if not spec.expressions:
        raise MeshSubjectError(f"{spec.folder or spec.neutral}: a mesh subject needs at least one expression mesh "
                               "besides the neutral")
    for k, p in spec.expressions.items():
        if not Path(p).exists():
            raise FileNotFoundError(f"expression {k!r}: mesh file not found: {p}")
    if isinstance(spec.albedo, Path) and not spec.albedo.exists():
        raise FileNotFoundError(f"albedo texture not found: {spec.albedo}")
    return spec


def _read_mesh(path: Path):
    """An :class:`~.objfile.ObjMesh` from an OBJ (our reader) or another format (trimesh, one group)."""
    from .objfile import ObjError, ObjMesh, read_obj

    if path.suffix.lower() == ".obj":
        try:
            return read_obj(path)
        except ObjError as exc:
            raise MeshSubjectError(str(exc)) from None
    import trimesh

    try:
        m = trimesh.load(str(path), process=False, maintain_order=True, force="mesh")
    except Exception as exc:  # trimesh raises many kinds
        raise MeshSubjectError(f"could not read mesh {path}: {exc}") from exc
    V = np.asarray(m.vertices, np.float64)
    F = np.asarray(m.faces, np.int64)
    if V.ndim != 2 or len(V) == 0 or len(F) == 0:
        raise MeshSubjectError(f"{path}: not a triangle mesh ({len(V)} vertices, {len(F)} faces)")
    uv = getattr(getattr(m, "visual", None), "uv", None)
    uv = np.asarray(uv, np.float64) if uv is not None and len(uv) == len(V) else None
    return ObjMesh(path, V, F, np.arange(len(F)), uv, F.copy() if uv is not None else None, ["mesh"],
                   np.zeros(len(F), np.int64), len(F), 0)


def _read_shape(path: Path, neutral, neutral_digest):
    """Positions of a blendshape file, checked against the neutral's topology."""
    from .objfile import ObjError, read_obj, read_positions

    path = Path(path)
    if path.suffix.lower() == ".obj":
        try:
            P, dig = read_positions(path)
            if dig != neutral_digest:
                m = read_obj(path, positions_only=True)
                if m.faces.shape != neutral.faces.shape or not np.array_equal(m.faces, neutral.faces):
                    return P, (len(m.positions), len(m.faces))
        except ObjError as exc:
            raise MeshSubjectError(str(exc)) from None
        return P, None
    m = _read_mesh(path)
    if m.faces.shape != neutral.faces.shape or not np.array_equal(m.faces, neutral.faces):
        return m.positions, (len(m.positions), len(m.faces))
    return m.positions, None


def _read_image(path: Path) -> np.ndarray:
    import imageio.v3 as iio

    try:
        image = np.asarray(iio.imread(path), np.float64)
    except Exception as exc:
        raise MeshSubjectError(f"{path}: cannot read the image ({exc})") from None
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=2)
    image = image[..., :3]
    if path.suffix.lower() != ".exr":   # 8/16-bit images are sRGB-encoded
        image = image / (65535.0 if image.max() > 255 else 255.0)
        image = np.where(image <= 0.04045, image / 12.92, ((image + 0.055) / 1.055) ** 2.4)
    return image.astype(np.float32)


def _select(names, patterns, where):
    if not patterns:
        return list(names)
    if isinstance(patterns, str):
        patterns = [p for p in patterns.split(",") if p]
    out = []
    for pat in patterns:
        hit = [n for n in names if fnmatch.fnmatchcase(n, pat)]
        if not hit:
            raise MeshSubjectError(f"{where}: the shape selection {pat!r} matches none of the expressions "
                                   f"({', '.join(list(names)[:12])}{' …' if len(names) > 12 else ''})")
        out += [n for n in hit if n not in out]
    return out


def load_mesh_subject(source, expressions=None, albedo=None, *, scale: float | None = None,
                      n_dots: int = 300, dot_seed: int = 0, texture_resolution: int = 1024,
                      dot_radius: float = 0.0015, shapes=None, placement=None, parts: dict | None = None,
                      cameras=None) -> "MeshSubject":
    """A :class:`MeshSubject` from a folder or from explicit files (see the module docstring).

    ``scale``, ``shapes``, ``placement`` and ``parts`` override ``subject.json``; ``cameras`` are the
    capture cameras whose view decides where dots go (default: the ``draft`` rig's)."""
    spec = _resolve(source, expressions, albedo)
    where = spec.manifest or spec.folder or spec.neutral
    if scale is not None:
        spec.scale = float(scale)
    if not (np.isfinite(spec.scale) and spec.scale > 0):
        raise MeshSubjectError(f"{where}: scale must be a positive number, got {spec.scale!r}")
    if placement is not None:
        spec.placement = placement
    if parts:
        spec.parts.update(parts)
    names = _select(spec.expressions, shapes if shapes is not None else spec.shapes, where)
    report = []
    nm = _read_mesh(spec.neutral)
    V0 = nm.positions * spec.scale
    if not np.all(np.isfinite(V0)):
        bad = int((~np.isfinite(V0)).any(axis=1).sum())
        raise MeshSubjectError(f"{spec.neutral}: {bad} vertices have NaN or infinite coordinates")
    dig = None
    if spec.neutral.suffix.lower() == ".obj":
        from .objfile import read_positions

        dig = read_positions(spec.neutral)[1]
    shapes_v = {}
    for name in names:
        path = Path(spec.expressions[name])
        P, mismatch = _read_shape(path, nm, dig)
        if mismatch is not None or len(P) != len(nm.positions):
            nv, nf = mismatch or (len(P), len(nm.faces))
            raise MeshSubjectError(
                f"expression {name!r} ({path}): {nv} vertices / {nf} faces, but the neutral ({spec.neutral}) has "
                f"{len(nm.positions)} / {len(nm.faces)}; every expression mesh must have the neutral's topology "
                "(same vertex order and faces): export each shape from the same mesh")
        P = P * spec.scale
        if not np.all(np.isfinite(P)):
            raise MeshSubjectError(f"expression {name!r} ({path}): {int((~np.isfinite(P)).any(axis=1).sum())} "
                                   "vertices have NaN or infinite coordinates")
        shapes_v[name] = P
    # roles of the groups
    roles = {}
    unknown_keys = [k for k in spec.parts if k not in nm.groups]
    if unknown_keys:
        raise MeshSubjectError(f"{where}: \"parts\" names {', '.join(map(repr, unknown_keys))}, which "
                               f"{spec.neutral.name} does not have; its groups: {', '.join(nm.groups)}")
    for g in nm.groups:
        r = spec.parts.get(g)
        r = ROLE_ALIASES.get(r, r) if r is not None else default_role(g, len(nm.groups))
        if r is None:
            raise MeshSubjectError(
                f"{spec.neutral}: no role for the group {g!r}; name it in subject.json, e.g. \"parts\": "
                f"{{\"{g}\": \"skin\"}} (roles: {', '.join(ROLES)})")
        if r not in ROLES:
            raise MeshSubjectError(f"{where}: unknown role {r!r} for the group {g!r}; roles: {', '.join(ROLES)}")
        roles[g] = r
    if "skin" not in roles.values():
        raise MeshSubjectError(f"{where}: no group has the role 'skin' (groups: {', '.join(nm.groups)}); "
                               "name the face in \"parts\"")
    by_role = {}
    for g, r in roles.items():
        by_role.setdefault(r, []).append(g)
    report.append(f"{spec.neutral.name}: {len(nm.positions)} vertices, {nm.n_polygons} polygons "
                  f"({nm.n_quads} quads) -> {len(nm.faces)} triangles; groups: "
                  + "; ".join(f"{r}: {', '.join(gs)}" for r, gs in by_role.items()))
    for r in ("lashes", "hair"):
        if r in by_role:
            report.append(f"{r} ({', '.join(by_role[r])}): not rendered in this version (dropped)")
    used = np.zeros(len(V0), bool)
    used[nm.faces.ravel()] = True
    if not used.all():
        report.append(f"{spec.neutral.name}: {int((~used).sum())} vertices no face uses: left out")
    ext = float(np.ptp(V0[np.unique(nm.faces[np.isin(nm.face_group, [nm.groups.index(g) for g in by_role['skin']])])],
                       axis=0).max())
    if not (0.05 < ext < 1.0):
        hint = next((f"--scale {s:g} (\"scale\": {s:g} in subject.json)" for s in (0.01, 0.001, 0.0254, 1.0)
                     if 0.12 < ext / spec.scale * s < 0.6), "--scale so that the head is about 0.25 m tall")
        raise MeshSubjectError(f"{spec.neutral}: the skin is {ext:.3g} m across after scale {spec.scale:g}; meshes "
                               f"are read in metres: pass {hint}")
    return MeshSubject(nm, V0, shapes_v, roles, spec, report, n_dots=n_dots, dot_seed=dot_seed,
                       texture_resolution=texture_resolution, dot_radius=dot_radius, cameras=cameras)


def _category(name: str) -> str:
    n = name.lower()
    if any(k in n for k in ("blink", "eye", "squint", "look")):
        return "eyes"
    if any(k in n for k in ("head", "neck")):
        return "head_pose"
    if any(k in n for k in ("smile", "frown", "sad", "anger", "disgust", "fear", "surprise", "brow", "sneer")):
        return "emotion"
    return "mouth"


def _components(F, n):
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    E = np.concatenate([F[:, [0, 1]], F[:, [1, 2]]])
    G = coo_matrix((np.ones(len(E)), (E[:, 0], E[:, 1])), shape=(n, n))
    return connected_components(G, directed=False)[1]


def _compact(F):
    ids = np.unique(F)
    remap = -np.ones(int(F.max()) + 1, np.int64)
    remap[ids] = np.arange(len(ids))
    return ids, remap[F]


def _sphere_fit(P):
    A = np.c_[2 * P, np.ones(len(P))]
    b = (P ** 2).sum(1)
    x = np.linalg.lstsq(A, b, rcond=None)[0]
    c = x[:3]
    return c, float(np.sqrt(max(x[3] + c @ c, 1e-12)))


class MeshSubject:
    """A subject made of a user's meshes (linear blendshapes); the :class:`Subject` interface.

    ``report``: lines saying what was read, repaired, placed and measured. ``template_info``: the
    template's visible-skin coverage and more (:func:`.mesh_template.build_mesh_template`)."""

    kind = "mesh"

    def __init__(self, mesh, V0, shapes: dict, roles: dict, spec, report, n_dots=300, dot_seed=0,
                 texture_resolution=1024, dot_radius=0.0015, cameras=None):
        self.name = str(spec.neutral)
        self.report = report
        self.shape_names = list(shapes)
        self.controls = [Control(k, 0.0, 1.0, 0.0, f"blendshape {k!r} (linear weight)") for k in self.shape_names]
        self.control_names = list(self.shape_names)
        self._index = {k: i for i, k in enumerate(self.shape_names)}
        self._manifest_presets = spec.presets
        self.texture_resolution = res = int(texture_resolution)
        self.dot_radius = float(dot_radius)
        gid = {g: i for i, g in enumerate(mesh.groups)}
        faces_of = {r: np.nonzero(np.isin(mesh.face_group, [gid[g] for g, rr in roles.items() if rr == r]))[0]
                    for r in ROLES}

        # skin: drop zero-area triangles, check manifoldness
        sk = faces_of["skin"]
        Fs = mesh.faces[sk]
        area = 0.5 * np.linalg.norm(np.cross(V0[Fs[:, 1]] - V0[Fs[:, 0]], V0[Fs[:, 2]] - V0[Fs[:, 0]]), axis=1)
        degenerate = (area < 1e-12) | (Fs[:, 0] == Fs[:, 1]) | (Fs[:, 1] == Fs[:, 2]) | (Fs[:, 0] == Fs[:, 2])
        if degenerate.any():
            report.append(f"{spec.neutral.name}: {int(degenerate.sum())} zero-area skin triangles left out")
            sk, Fs = sk[~degenerate], Fs[~degenerate]
        E = np.sort(np.concatenate([Fs[:, [0, 1]], Fs[:, [1, 2]], Fs[:, [2, 0]]]), axis=1)
        _, cnt = np.unique(E, axis=0, return_counts=True)
        if (cnt > 2).any():
            raise MeshSubjectError(f"{spec.neutral}: the skin is not manifold ({int((cnt > 2).sum())} edges shared by "
                                   "more than two faces); merge or separate the overlapping sheets, or give them "
                                   "another role in \"parts\"")

        # placement (a translation) and the stored geometry
        offset = self._placement(mesh, V0, faces_of, spec)
        self.offset = offset
        self.rest_all = V0 + offset
        self.deltas = np.stack([np.asarray(shapes[k]) + offset - self.rest_all for k in self.shape_names], 0)
        self.skin_ids, self.skin_faces = _compact(Fs)
        self.skin_faces = self.skin_faces.astype(np.int32)
        self.skin_rest = self.rest_all[self.skin_ids]
        self.neutral_skin = self.skin_rest
        ext = np.ptp(self.skin_rest, axis=0)
        report.append(f"placement: offset ({offset[0]:+.4f}, {offset[1]:+.4f}, {offset[2]:+.4f}) m "
                      f"({spec.placement if isinstance(spec.placement, str) else 'given'}); skin "
                      f"{ext[0]:.3f} x {ext[1]:.3f} x {ext[2]:.3f} m, {len(self.skin_ids)} vertices, "
                      f"{len(self.skin_faces)} triangles; {len(self.shape_names)} shapes")

        self._build_parts(mesh, faces_of)
        self._build_uv(mesh, sk, spec, res)

        # template and dots on the visible skin
        from .mesh_template import build_mesh_template, template_coverage

        if cameras is None:
            from ..rig import preset

            cameras = preset("draft").rig().cameras
        occ = self._occluder(self.pose_geometry(np.zeros(len(self.shape_names))))
        poses = [(g["skin"], self._occluder(g)) for g in map(self.pose_geometry, self._extreme_params())]
        tpl, info = build_mesh_template(self.skin_rest, self.skin_faces, occ, cameras, n_dots, dot_seed,
                                        self.eye_centres, poses=poses)
        tpl.eyes = {n: {"centre": self.eye_centres[n], "radius": self.eye_radius} for n in self.eye_centres}
        tpl.teeth = self._teeth_strips()
        tpl = self._extensions(tpl)
        info["coverage_with_extensions"] = template_coverage(self.skin_rest, self.skin_faces, info["visible"],
                                                             tpl.neutral, np.asarray(tpl.triangles),
                                                             reach=0.5 * info["spacing"])[0]
        self.template, self.template_info = tpl, info
        self.dot_tri, self.dot_bary = info["dot_tri"], info["dot_bary"]
        self.dots_neutral = np.einsum("nk,nkj->nj", self.dot_bary, self.skin_rest[self.skin_faces[self.dot_tri]])
        self.dot_names = [""] * len(self.dot_tri)
        self.skin_face_region = info["covered"] & info["visible"]
        report.append(f"template: {n_dots} dots over {info['visible_area'] * 1e4:.0f} cm² of skin two cameras "
                      f"see (spacing {info['spacing'] * 1000:.1f} mm; dots on the {info['region_area'] * 1e4:.0f} cm² "
                      f"they see in the neutral and in each of {info['n_poses']} shapes at full weight), "
                      f"{len(tpl.kinds)} vertices, "
                      f"{len(tpl.triangles)} triangles, margins: {', '.join(info['margins']) or 'none'}, marks: "
                      f"{', '.join(info['marks']) or 'none'}; covers {100 * info['coverage']:.1f} % of the visible skin "
                      f"({100 * info['region_coverage']:.1f} % of the skin seen in every shape"
                      f"{', off the ears' if info['ears_to_extensions'] else ''}; "
                      f"{100 * info['coverage_with_extensions']:.1f} % with the extensions)")

        # textures: the user's albedo (or plain skin) with the dots painted in
        self._albedo_clean = self._base_albedo(spec, res)
        self._albedo = self._paint(self._albedo_clean, res)
        self._roughness = np.full((res, res), 0.45, np.float32)
        self._normal = encode_normals(np.zeros((res * res, 2), np.float32)).reshape(res, res, 3)
        self._neutral_pose = None
        for line in report[1:]:
            if "left out" in line or "xatlas" in line or "dropped" in line:
                warnings.warn(line, MeshSubjectWarning, stacklevel=3)

    def _extreme_params(self) -> list:
        """The parameters of every shape at full weight and of the folder's named presets: the poses in
        which the dots must be seen (the captured expressions are these or blends of them)."""
        out = [self.params(**{k: 1.0}) for k in self.shape_names]
        for e in self._manifest_presets or []:
            out.append(self.params(**e["weights"]))
        return out

    def _teeth_strips(self, n_teeth: int = 10) -> dict:
        """The paper's teeth model for each teeth part: a strip along its front ``n_teeth`` tooth widths,
        vertices alternating incisal edge / gum line at ``n_teeth + 1`` evenly spaced x positions (the
        front-most teeth vertices near each: the edge is the lowest of the upper teeth, the highest of
        the lower), two triangles per tooth, facing +Z; in the part's rest frame (world at the neutral)."""
        out = {}
        for key, name in (("upper", "teeth_upper"), ("lower", "teeth_lower")):
            if name not in self.part_rest:
                continue
            P = self.part_rest[name]
            front = P[P[:, 2] > P[:, 2].max() - 0.008]
            x0, x1 = np.percentile(front[:, 0], [2, 98])
            xs = np.linspace(x0, x1, n_teeth + 1)
            half = 0.5 * (x1 - x0) / n_teeth
            V = []
            for x in xs:
                near = front[np.abs(front[:, 0] - x) < half]
                if len(near) == 0:
                    near = front[np.argsort(np.abs(front[:, 0] - x))[:3]]
                lo, hi = near[np.argmin(near[:, 1])], near[np.argmax(near[:, 1])]
                V += [lo, hi] if key == "upper" else [hi, lo]          # incisal edge, then gum line
            V = np.asarray(V)
            F = []
            for k in range(n_teeth):
                e0, g0, e1, g1 = 2 * k, 2 * k + 1, 2 * k + 2, 2 * k + 3
                F += [[e0, e1, g1], [e0, g1, g0]]
            F = np.asarray(F, np.int32)
            n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
            if n[:, 2].sum() < 0:
                F = F[:, [0, 2, 1]]
            out[key] = {"part": name, "vertices": V, "triangles": F}
        if out:
            self.report.append("teeth strips: " + ", ".join(f"{k} {len(v['triangles']) // 2} teeth" for k, v in out.items()))
        return out

    def _extensions(self, tpl):
        """The template with the extensions beyond the dots (scalp, ears, neck, back of the head; issue 16),
        cut just below the template's lowest vertex (no cut when the dots reach the skin's lowest edge); a
        skin they cannot be made on keeps the face template (reported)."""
        from .template_extensions import add_extensions

        cut = float(tpl.neutral[:, 1].min()) - 0.002
        cut = cut if cut > float(self.skin_rest[:, 1].min()) else float(self.skin_rest[:, 1].min()) - 0.001
        try:
            out = add_extensions(tpl, self.skin_rest, self.skin_faces, neck_cut_y=cut)
        except ValueError as exc:
            self.report.append(f"extensions: not made ({exc})")
            return tpl
        self.report.append(f"extensions: {len(out.kinds) - len(tpl.kinds)} vertices ("
                           + ", ".join(f"{k} {len(v['vertices'])}" for k, v in out.extensions.items()) + ")")
        return out

    # ------------------------------------------------------------------------------------ parts
    def _placement(self, mesh, V0, faces_of, spec):
        pl = spec.placement
        if isinstance(pl, (list, tuple)):
            off = np.asarray(pl, np.float64)
            if off.shape != (3,) or not np.isfinite(off).all():
                raise MeshSubjectError(f"{spec.manifest or spec.neutral}: \"placement\" must be \"auto\", \"as_is\" "
                                       f"or [dx, dy, dz] in metres, got {pl!r}")
            return off
        if pl == "as_is":
            return np.zeros(3)
        if pl != "auto":
            raise MeshSubjectError(f"{spec.manifest or spec.neutral}: \"placement\" must be \"auto\", \"as_is\" or "
                                   f"[dx, dy, dz], got {pl!r}")
        eyes = faces_of["eye"]
        skin_v = np.unique(mesh.faces[faces_of["skin"]])
        nose = V0[skin_v[np.argmax(V0[skin_v, 2])]]
        if len(eyes):
            ev = np.unique(mesh.faces[eyes])
            P = V0[ev]
            mid = 0.5 * (P[P[:, 0] >= np.median(P[:, 0])].mean(0) + P[P[:, 0] < np.median(P[:, 0])].mean(0))
            if mid[2] > nose[2]:
                raise MeshSubjectError(f"{spec.neutral}: the eyes are in front of the skin's front-most point: the "
                                       "face must look along +Z with +Y up (rotate the meshes)")
            return EYES_MIDPOINT - mid
        return NOSE_TIP - nose

    def _build_parts(self, mesh, faces_of):
        from . import parts as PT

        self.part_ids, self.part_faces, self.part_rest, self.part_uv = {}, {}, {}, {}
        self.eye_centres, self.eye_radius = {}, None
        R = self.rest_all
        ef = mesh.faces[faces_of["eye"]]
        if len(ef):
            xs = R[ef].mean(axis=1)[:, 0]
            split = np.median(R[np.unique(ef), 0])
            radii = []
            for name, sel in (("eye_left", xs >= split), ("eye_right", xs < split)):
                if not sel.any():
                    continue
                ids, F = _compact(ef[sel])
                P = R[ids]
                c, r = _sphere_fit(P)
                d = (P - c) / np.maximum(np.linalg.norm(P - c, axis=1, keepdims=True), 1e-12)
                beta = np.arccos(np.clip(d[:, 2], -1, 1))
                psi = np.arctan2(d[:, 0], d[:, 1])
                uv = np.stack([0.5 + beta / (2 * np.pi) * np.sin(psi), 0.5 + beta / (2 * np.pi) * np.cos(psi)], 1)
                self._add_part(name, ids, F)
                self.part_uv[name] = uv
                self.eye_centres[name] = c
                radii.append(r)
            self.eye_radius = float(np.mean(radii))
            self.eye_albedo, self.eye_roughness = PT.eye_textures()
            self.report.append("eyes: " + ", ".join(f"{n} centre ({c[0]:+.4f}, {c[1]:+.4f}, {c[2]:+.4f})"
                                                    for n, c in self.eye_centres.items())
                               + f", radius {self.eye_radius * 1000:.1f} mm")
        tf = mesh.faces[faces_of["teeth"]]
        if len(tf):
            comp = _components(tf, len(R))
            cid = comp[tf[:, 0]]
            tv = np.unique(tf)
            move = [float(np.linalg.norm(d[tv], axis=1).max()) for d in self.deltas]
            jaw = self.shape_names[int(np.argmax(move))] if move and max(move) > 1e-3 else None
            lower = np.zeros(len(tf), bool)
            if jaw is not None:             # the shape that moves the teeth most moves the lower ones
                move = np.linalg.norm(self.deltas[self._index[jaw]], axis=1)
                for c in np.unique(cid):
                    v = np.unique(tf[cid == c])
                    lower[cid == c] = move[v].mean() > 1e-3
            if jaw is None or lower.all() or not lower.any():
                jaw = None
                ymid = np.median(R[np.unique(tf), 1])
                for c in np.unique(cid):
                    v = np.unique(tf[cid == c])
                    lower[cid == c] = R[v, 1].mean() < ymid
            for name, sel in (("teeth_upper", ~lower), ("teeth_lower", lower)):
                if sel.any():
                    self._add_part(name, *_compact(tf[sel]))
            self.report.append(f"teeth: {int((~lower).sum())} upper / {int(lower.sum())} lower triangles"
                               + (f" (lower: those {jaw!r} moves)" if jaw else " (split by height)"))
        inf = mesh.faces[faces_of["interior"]]
        if len(inf):
            self._add_part("mouth_interior", *_compact(inf))

    def _add_part(self, name, ids, F):
        self.part_ids[name] = ids
        self.part_faces[name] = np.asarray(F, np.int32)
        self.part_rest[name] = self.rest_all[ids]

    def _occluder(self, geo):
        Vs, Fs, off = [geo["skin"]], [self.skin_faces.astype(np.int64)], len(geo["skin"])
        for name in self.part_ids:
            Vs.append(geo[name])
            Fs.append(self.part_faces[name].astype(np.int64) + off)
            off += len(geo[name])
        return np.concatenate(Vs), np.concatenate(Fs)

    def pose_geometry(self, p) -> dict:
        """{'skin': (Vs, 3), part name: (n, 3)} blended vertex positions (parts not yet rigid)."""
        Vall = self.rest_all + np.tensordot(p, self.deltas, axes=1) if len(p) else self.rest_all
        out = {"skin": Vall[self.skin_ids]}
        for name, ids in self.part_ids.items():
            out[name] = Vall[ids]
        return out

    # ------------------------------------------------------------------------------------ texture
    def _build_uv(self, mesh, sk, spec, res):
        from .objfile import pack_udim

        self._udim = None
        uvs, fuv = mesh.uvs, mesh.face_uvs
        reason = None
        if uvs is None or fuv is None:
            reason = "the skin has no texture coordinates"
        else:
            Fu = fuv[sk]
            if (Fu < 0).any():
                reason = f"{int((Fu < 0).any(axis=1).sum())} skin faces have no texture coordinates"
            elif not np.isfinite(uvs[Fu]).all():
                reason = "the skin's texture coordinates contain NaN"
            elif (uvs[np.unique(Fu)] < -1e-6).any():
                raise MeshSubjectError(f"{spec.neutral}: negative texture coordinates on the skin; UVs must lie in "
                                       "[0, 1] or in UDIM tiles (u, v ≥ 0)")
            else:
                T = uvs[Fu]
                a = 0.5 * np.abs((T[:, 1, 0] - T[:, 0, 0]) * (T[:, 2, 1] - T[:, 0, 1])
                                 - (T[:, 2, 0] - T[:, 0, 0]) * (T[:, 1, 1] - T[:, 0, 1]))
                zero = a < 1e-12
                if zero.mean() > 0.01:
                    reason = (f"{100 * zero.mean():.0f} % of the skin's faces have zero-area texture coordinates "
                              f"(u {uvs[np.unique(Fu), 0].min():.3g}..{uvs[np.unique(Fu), 0].max():.3g}, "
                              f"v {uvs[np.unique(Fu), 1].min():.3g}..{uvs[np.unique(Fu), 1].max():.3g})")
        if reason is not None:
            if spec.albedo is not None:
                raise MeshSubjectError(f"{spec.neutral}: {reason}, so the albedo cannot be mapped; export the mesh "
                                       "with its UVs (or drop the albedo to get a generated atlas)")
            from . import cache

            self.report.append(f"{spec.neutral.name}: {reason}: an xatlas atlas is made (no albedo given)")
            h = cache.key("mesh-atlas", res, self.skin_faces.shape, float(self.skin_rest.sum()),
                          float(np.abs(self.skin_rest).sum()))
            at = cache.cached(h, lambda: build_atlas(self.skin_rest, self.skin_faces, res))
            self.skin_uv, self.skin_uv_faces, self.skin_uv_vertex = at["uv"], at["uv_faces"], at["uv_vertex"]
            return
        # split skin vertices where a position has several uv: one render vertex per (position, uv) pair
        pos_c = self.skin_faces.ravel().astype(np.int64)
        uv_c = fuv[sk].ravel()
        pair = pos_c * (len(uvs) + 1) + uv_c
        upair, inv = np.unique(pair, return_inverse=True)
        self.skin_uv_vertex = (upair // (len(uvs) + 1)).astype(np.int32)
        uv_index = upair % (len(uvs) + 1)
        self.skin_uv_faces = inv.reshape(-1, 3).astype(np.int32)
        packed, layout = pack_udim(uvs[uv_index], self.skin_uv_faces)
        self.skin_uv = packed
        self._udim = layout
        tiles = sorted(k for k in layout if k != "grid")
        self.report.append(f"uv: {len(upair)} render vertices for {len(self.skin_ids)} skin positions; tiles "
                           f"{', '.join(map(str, tiles))}" + (f" packed {layout['grid']} x {layout['grid']}"
                                                              if layout["grid"] > 1 else ""))

    def _base_albedo(self, spec, res):
        from .objfile import assemble_udim

        alb = spec.albedo
        if alb is None:
            return np.tile(SKIN_BASE.astype(np.float32), (res, res, 1))
        tiles = sorted(k for k in (self._udim or {"grid": 1, 1001: (0, 0)}) if k != "grid")
        if isinstance(alb, dict):
            missing = [t for t in tiles if t not in alb]
            if missing:
                raise MeshSubjectError(f"{spec.folder}: the skin uses UDIM tile(s) {', '.join(map(str, missing))} but "
                                       f"there is no albedo for them (found {', '.join(map(str, sorted(alb)))})")
            imgs = {t: _read_image(alb[t]) for t in tiles}
            layout = self._udim if self._udim is not None else {"grid": 1, 1001: (0, 0)}
            return assemble_udim(layout, imgs, res, SKIN_BASE)
        if tiles != [1001]:
            raise MeshSubjectError(f"{alb}: one albedo image, but the skin's UVs use UDIM tiles "
                                   f"{', '.join(map(str, tiles))}; name the tiles albedo.1001.png, albedo.1002.png … "
                                   "(or \"albedo\": \"albedo.<UDIM>.png\" in subject.json)")
        return assemble_udim({"grid": 1, 1001: (0, 0)}, {1001: _read_image(alb)}, res, SKIN_BASE)

    def _paint(self, base, res):
        from scipy.spatial import cKDTree

        tri, bary, _ = rasterize(self.skin_uv, self.skin_uv_faces, res)
        cov = np.nonzero(tri >= 0)[0]
        alb = base.reshape(-1, 3).copy()
        n = len(self.dot_tri)
        if n:
            P = np.einsum("tk,tkj->tj", bary[cov], self.skin_rest[self.skin_uv_vertex[self.skin_uv_faces[tri[cov]]]])
            d, idx = cKDTree(self.dots_neutral).query(P, k=1, distance_upper_bound=4 * self.dot_radius)
            c = np.clip((self.dot_radius + 0.00012 - d) / 0.00024, 0.0, 1.0)
            alb[cov] = alb[cov] * (1 - c[:, None]) + DOT_COLOUR[None] * c[:, None]
            texels = np.bincount(idx[c > 0.5], minlength=n + 1)[:n]
            few = int((texels < 2).sum())
            if few:
                raise MeshSubjectError(
                    f"{self.name}: {few} of {n} dots get fewer than 2 texels at texture resolution {res} (the UV "
                    f"layout gives the skin {100 * len(cov) / res ** 2:.1f} % of the texture); fix the UVs or raise "
                    "the texture resolution")
            self.report.append(f"dots: {n} painted ({int(np.median(texels))} texels each, median); skin uses "
                               f"{100 * len(cov) / res ** 2:.0f} % of the {res}² texture")
        return np.clip(alb, 0.0, 1.0).reshape(res, res, 3).astype(np.float32)

    # ------------------------------------------------------------------------------------------
    def params(self, **named) -> np.ndarray:
        p = np.zeros(len(self.shape_names))
        for k, v in named.items():
            if k not in self._index:
                raise KeyError(f"unknown control {k!r}; controls: {', '.join(self.shape_names)}")
            p[self._index[k]] = float(v)
        return p

    def presets(self, n) -> list[Expression]:
        if isinstance(n, str):
            if n not in PRESET_SIZES:
                raise ValueError(f"unknown preset {n!r}; use one of {sorted(PRESET_SIZES)}")
            n = PRESET_SIZES[n]
        n = int(n)
        out = [Expression("neutral", "neutral", self.params())]
        if self._manifest_presets:
            for e in self._manifest_presets:
                cat = e.get("category", "mouth")
                out.append(Expression(e["name"], cat if cat in CATEGORIES else "mouth", self.params(**e["weights"])))
        names = self.shape_names
        for k in names:
            out.append(Expression(k, _category(k), self.params(**{k: 1.0})))
        for w in (0.5, 0.75, 0.25):
            for k in names:
                out.append(Expression(f"{k}_{int(w * 100)}", _category(k), self.params(**{k: w})))
        from itertools import combinations

        for wa, wb in ((0.6, 0.6), (0.3, 0.8), (0.8, 0.3)):    # then pairs (finite: a short list stays short)
            for a, b in combinations(names, 2):
                if len(out) >= n + len(names):
                    break
                out.append(Expression(f"{a}+{b}_{int(wa * 100)}_{int(wb * 100)}", _category(a),
                                      self.params(**{a: wa, b: wb})))
        seen, uniq = set(), []
        for e in out:
            if e.name not in seen:
                seen.add(e.name)
                uniq.append(e)
        return uniq[:n]

    def check_params(self, params):
        p = np.asarray(params, float)
        if p.shape != (len(self.shape_names),):
            raise ValueError(f"parameter vector must have shape ({len(self.shape_names)},), got {p.shape}")
        if not np.all(np.isfinite(p)):
            raise ValueError("parameter vector contains NaN or inf")
        return p

    @property
    def neutral(self) -> Pose:
        if self._neutral_pose is None:
            self._neutral_pose = self.pose(self.params())
        return self._neutral_pose

    def pose(self, params, textures: bool = True) -> Pose:
        from ..geometry.rigid import apply, rigid_from_points

        p = self.check_params(params)
        geo = self.pose_geometry(p)
        V = geo["skin"]
        N = vertex_normals(V, self.skin_faces)
        T = {"head": np.eye(4)}
        parts = {}
        for name in self.part_ids:
            F = self.part_faces[name]
            if name == "mouth_interior":
                Pv = geo[name]
                col = np.tile(INTERIOR_COLOUR, (len(Pv), 1))
                parts[name] = Part(name, Pv, F, vertex_normals(Pv, F), None, None, col)
                continue
            Tm = rigid_from_points(self.part_rest[name], geo[name])
            Pv = apply(Tm, self.part_rest[name])
            T[name] = Tm
            parts[name] = Part(name, Pv, F, vertex_normals(Pv, F), Tm, self.part_uv.get(name))
        if "teeth_lower" in T:
            T["jaw"] = T["teeth_lower"]
        dots = np.einsum("nk,nkj->nj", self.dot_bary, V[self.skin_faces[self.dot_tri]])
        tv = self.template.positions(V, parts)
        tex = Textures(self._albedo, self._roughness, self._normal) if textures else None
        return Pose(p, V, N, parts, dots, tv, tex, T)

    def without_dots(self) -> "MeshSubject":
        """The same subject with its dots washed off (evaluation's ground truth: the user's albedo
        or the plain skin as it was before the dots were painted)."""
        if getattr(self, "_dot_free", None) is None:
            clean = copy.copy(self)
            clean._albedo = self._albedo_clean
            clean._neutral_pose = None
            clean._dot_free = clean
            self._dot_free = clean
        return self._dot_free

    def split_skin(self, pose: Pose):
        m = self.skin_uv_vertex
        return pose.skin_vertices[m], pose.skin_normals[m], self.skin_uv, self.skin_uv_faces
