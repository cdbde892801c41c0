"""Bring your own subject: a neutral mesh plus expression meshes of the same topology.

The expression meshes are treated as linear blendshapes (``V = V0 + Σ w_i (V_i − V0)``) whose
weights ``w_i ∈ [0, 1]`` are the parameter vector, e.g. an ARKit-style set. The result has the same
interface as the procedural :class:`~mifacerf.synthetic.subject.Subject` (controls, presets, params,
pose, template, textures, ``split_skin``) and works with :class:`~mifacerf.synthetic.scene.SubjectScene`.
It has no eyes, teeth or mouth interior (``pose.parts`` is empty; the template has no teeth strips
or eyes).

::

    subj = load_mesh_subject("my_subject/")           # a folder, see below
    subj = load_mesh_subject("neutral.obj", {"jawOpen": "jawOpen.obj", ...}, albedo="albedo.png")

A folder holds ``neutral.obj`` (or ``.ply``) and one mesh per expression (named by the file's stem),
optionally ``albedo.png`` / ``.jpg`` and a ``subject.json`` manifest::

    {"neutral": "neutral.obj", "expressions": {"jawOpen": "jawOpen.obj", ...},
     "albedo": "albedo.png", "scale": 1.0,
     "presets": [{"name": "...", "category": "...", "weights": {"jawOpen": 0.5}}, ...]}

Meshes are in metres in the world frame of ``docs/conventions.md`` (+Y up, the face looking along
+Z); ``scale`` converts other units (0.01 for centimetres). Texture coordinates come from the neutral
mesh when it has them, else from xatlas (cached). Without an albedo texture the skin is a plain skin
colour. Fiducial dots (``n_dots``) are placed by ``trimesh.sample.sample_surface_even`` with a fixed
seed on the neutral and painted into the albedo. The template is the dots, triangulated in a
cylindrical chart about the vertical axis through the mesh centre (triangles over holes such as open
eyes or mouth are dropped); its 18 coarse points are spread over the dots by farthest-point
sampling, and its regions are assigned from positions in the face's bounding box.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .expressions import Control
from .presets import CATEGORIES, PRESET_SIZES, Expression
from .subject import Pose, Textures, vertex_normals
from .template import REGION_NAMES, Template, delaunay_with_holes, flip_improve, improve, _peel3d  # noqa: F401
from .textures import DOT_COLOUR, SKIN_BASE, build_atlas, encode_normals, rasterize
from ..errors import MifacerfError

MESH_SUFFIXES = (".obj", ".ply", ".off", ".stl", ".glb", ".gltf")
ALBEDO_NAMES = ("albedo.png", "albedo.jpg", "albedo.jpeg", "albedo.exr")


class MeshSubjectError(MifacerfError, ValueError):
    """Bad input for a mesh subject (topology mismatch, NaNs, units ...)."""


def _load_mesh(path: Path, scale: float):
    import trimesh

    if not path.exists():
        raise FileNotFoundError(f"mesh file not found: {path}")
    try:
        m = trimesh.load(str(path), process=False, maintain_order=True, force="mesh")
    except Exception as exc:  # trimesh raises many kinds
        raise MeshSubjectError(f"could not read mesh {path}: {exc}") from exc
    V = np.asarray(m.vertices, np.float64) * scale
    F = np.asarray(m.faces, np.int64)
    if V.ndim != 2 or V.shape[1] != 3 or len(V) == 0 or len(F) == 0:
        raise MeshSubjectError(f"{path}: not a triangle mesh ({len(V)} vertices, {len(F)} faces)")
    if not np.all(np.isfinite(V)):
        bad = int((~np.isfinite(V)).any(axis=1).sum())
        raise MeshSubjectError(f"{path}: {bad} vertices have NaN or infinite coordinates")
    uv = None
    vis = getattr(m, "visual", None)
    if vis is not None and getattr(vis, "uv", None) is not None and len(vis.uv) == len(V):
        uv = np.asarray(vis.uv, np.float64)
        if not np.all(np.isfinite(uv)):
            uv = None
    return V, F, uv


def _resolve(source, expressions, albedo):
    """(neutral path, {name: path}, albedo path or None, scale, manifest presets or None)."""
    src = Path(source)
    scale, presets = 1.0, None
    if src.is_dir():
        man = src / "subject.json"
        if man.exists():
            d = json.loads(man.read_text())
            neutral = src / d.get("neutral", "neutral.obj")
            exprs = {k: src / v for k, v in d.get("expressions", {}).items()}
            alb = src / d["albedo"] if d.get("albedo") else None
            scale = float(d.get("scale", 1.0))
            presets = d.get("presets")
        else:
            cands = [p for p in sorted(src.iterdir()) if p.suffix.lower() in MESH_SUFFIXES]
            neutral = next((p for p in cands if p.stem.lower() == "neutral"), None)
            if neutral is None:
                raise FileNotFoundError(f"{src}: no neutral mesh (expected neutral.obj or neutral.ply)")
            exprs = {p.stem: p for p in cands if p != neutral}
            alb = next((src / n for n in ALBEDO_NAMES if (src / n).exists()), None)
        if expressions:
            exprs = {k: Path(v) for k, v in dict(expressions).items()}
        if albedo is not None:
            alb = Path(albedo)
    else:
        if not src.exists():
            raise FileNotFoundError(f"neutral mesh not found: {src}")
        neutral = src
        if expressions is None:
            exprs = {}
        elif isinstance(expressions, dict):
            exprs = {k: Path(v) for k, v in expressions.items()}
        else:
            exprs = {Path(p).stem: Path(p) for p in expressions}
        alb = Path(albedo) if albedo is not None else None
    if not exprs:
        raise MeshSubjectError("a mesh subject needs at least one expression mesh besides the neutral")
    for k, p in exprs.items():
        if not Path(p).exists():
            raise FileNotFoundError(f"expression {k!r}: mesh file not found: {p}")
    if alb is not None and not alb.exists():
        raise FileNotFoundError(f"albedo texture not found: {alb}")
    return neutral, exprs, alb, scale, presets


def load_mesh_subject(source, expressions=None, albedo=None, *, scale: float | None = None,
                      n_dots: int = 300, dot_seed: int = 0, texture_resolution: int = 1024,
                      dot_radius: float = 0.0015) -> "MeshSubject":
    """A :class:`MeshSubject` from a folder or from explicit files (see the module docstring)."""
    neutral, exprs, alb, man_scale, man_presets = _resolve(source, expressions, albedo)
    s = float(scale) if scale is not None else man_scale
    V0, F, uv = _load_mesh(neutral, s)
    shapes = {}
    for name, path in exprs.items():
        V, Fi, _ = _load_mesh(Path(path), s)
        if len(V) != len(V0) or Fi.shape != F.shape or not np.array_equal(Fi, F):
            raise MeshSubjectError(
                f"expression {name!r} ({path}): {len(V)} vertices / {len(Fi)} faces, but the neutral "
                f"({neutral}) has {len(V0)} / {len(F)}; every expression mesh must have the neutral's "
                "topology (same vertex order and faces)")
        shapes[name] = V
    ext = np.ptp(V0, axis=0).max()
    if not (0.02 < ext < 2.0):
        raise MeshSubjectError(
            f"the neutral mesh is {ext:.3g} units across; meshes must be in metres (pass scale=0.01 "
            "for centimetres, 0.001 for millimetres)")
    image = None
    if alb is not None:
        import imageio.v3 as iio

        image = np.asarray(iio.imread(alb), np.float64)
        if image.ndim == 2:
            image = np.repeat(image[..., None], 3, axis=2)
        image = image[..., :3]
        if image.max() > 1.0:
            image = image / (65535.0 if image.max() > 255 else 255.0)
        if alb.suffix.lower() != ".exr":   # 8/16-bit images are sRGB-encoded
            image = np.where(image <= 0.04045, image / 12.92, ((image + 0.055) / 1.055) ** 2.4)
    return MeshSubject(V0, F, shapes, uv=uv, albedo=image, n_dots=n_dots, dot_seed=dot_seed,
                       texture_resolution=texture_resolution, dot_radius=dot_radius,
                       manifest_presets=man_presets, name=str(neutral))


def _category(name: str) -> str:
    n = name.lower()
    if any(k in n for k in ("blink", "eye", "squint", "look")):
        return "eyes"
    if any(k in n for k in ("head", "neck")):
        return "head_pose"
    if any(k in n for k in ("smile", "frown", "sad", "anger", "disgust", "fear", "surprise", "brow", "sneer")):
        return "emotion"
    return "mouth"


class MeshSubject:
    """A subject made of user meshes (linear blendshapes); the :class:`Subject` interface."""

    kind = "mesh"

    def __init__(self, neutral, faces, shapes: dict, uv=None, albedo=None, n_dots=300, dot_seed=0,
                 texture_resolution=1024, dot_radius=0.0015, manifest_presets=None, name="mesh"):
        self.name = name
        self.skin_rest = np.asarray(neutral, np.float64)
        self.neutral_skin = self.skin_rest
        self.skin_faces = np.asarray(faces, np.int32)
        self.shape_names = list(shapes)
        self.deltas = np.stack([np.asarray(shapes[k]) - self.skin_rest for k in self.shape_names], 0)
        self.controls = [Control(k, 0.0, 1.0, 0.0, f"blendshape {k!r} (linear weight)") for k in self.shape_names]
        self.control_names = list(self.shape_names)
        self._index = {k: i for i, k in enumerate(self.shape_names)}
        self._manifest_presets = manifest_presets
        self.texture_resolution = int(texture_resolution)
        self.dot_radius = float(dot_radius)
        self.part_rest, self.part_faces = {}, {}
        self.eye_centres, self.eye_radius = {}, None

        # texture coordinates
        res = self.texture_resolution
        if uv is not None and np.all(uv >= -1e-6) and np.all(uv <= 1 + 1e-6):
            self.skin_uv = np.clip(uv, 0.0, 1.0)
            self.skin_uv_faces = self.skin_faces.copy()
            self.skin_uv_vertex = np.arange(len(self.skin_rest), dtype=np.int32)
        else:
            from . import cache

            h = cache.key("mesh-atlas", res, self.skin_faces.shape, float(self.skin_rest.sum()),
                          float(np.abs(self.skin_rest).sum()))
            at = cache.cached(h, lambda: build_atlas(self.skin_rest, self.skin_faces, res))
            self.skin_uv, self.skin_uv_faces, self.skin_uv_vertex = at["uv"], at["uv_faces"], at["uv_vertex"]

        # dots
        self.dot_tri, self.dot_bary = self._sample_dots(n_dots, dot_seed)
        self.dots_neutral = np.einsum("nk,nkj->nj", self.dot_bary, self.skin_rest[self.skin_faces[self.dot_tri]])
        self.dot_names = [""] * len(self.dot_tri)

        # textures: the user's albedo (or plain skin) with the dots painted in
        self._albedo = self._paint(albedo, res)
        self._roughness = np.full((res, res), 0.45, np.float32)
        self._normal = encode_normals(np.zeros((res * res, 2), np.float32)).reshape(res, res, 3)
        self.template = self._build_template()
        self.skin_face_region = np.ones(len(self.skin_faces), bool)
        self._neutral_pose = None

    # ------------------------------------------------------------------------------------------
    def _sample_dots(self, n, seed):
        import trimesh

        m = trimesh.Trimesh(self.skin_rest, self.skin_faces, process=False)
        area = m.area
        radius = 0.6 * np.sqrt(area / max(n, 1))
        pts, fid = trimesh.sample.sample_surface_even(m, n, radius=radius, seed=seed)
        for shrink in (0.8, 0.6, 0.4):   # smaller spacing when the surface is too small for n
            if len(pts) >= n:
                break
            pts, fid = trimesh.sample.sample_surface_even(m, n, radius=shrink * radius, seed=seed)
        bary = trimesh.triangles.points_to_barycentric(m.triangles[fid], pts)
        bary = np.clip(bary, 0.0, None)
        bary /= bary.sum(axis=1, keepdims=True)
        return np.asarray(fid, np.int32), bary

    def _paint(self, image, res):
        tri, bary, _ = rasterize(self.skin_uv, self.skin_uv_faces, res)
        cov = np.nonzero(tri >= 0)[0]
        if image is None:
            alb = np.tile(SKIN_BASE.astype(np.float32), (res * res, 1))
        else:
            # resample the user's image to the working resolution (nearest)
            H0, W0 = image.shape[:2]
            rr = np.minimum(((np.arange(res) + 0.5) / res * H0).astype(int), H0 - 1)
            cc = np.minimum(((np.arange(res) + 0.5) / res * W0).astype(int), W0 - 1)
            alb = image[rr][:, cc].reshape(-1, 3).astype(np.float32)
        if len(self.dot_tri):
            from scipy.spatial import cKDTree

            P = np.einsum("tk,tkj->tj", bary[cov], self.skin_rest[self.skin_faces[tri[cov]]])
            d, _ = cKDTree(self.dots_neutral).query(P, k=1, distance_upper_bound=4 * self.dot_radius)
            c = np.clip((self.dot_radius + 0.00012 - d) / 0.00024, 0.0, 1.0)
            alb[cov] = alb[cov] * (1 - c[:, None]) + DOT_COLOUR[None] * c[:, None]
        return np.clip(alb, 0.0, 1.0).reshape(res, res, 3).astype(np.float32)

    def _build_template(self) -> Template:
        from scipy.spatial import cKDTree

        P = self.dots_neutral
        c = self.skin_rest.mean(axis=0)
        R = np.median(np.hypot(self.skin_rest[:, 0] - c[0], self.skin_rest[:, 2] - c[2]))
        X = np.stack([np.arctan2(P[:, 0] - c[0], P[:, 2] - c[2]) * R, P[:, 1]], 1)
        T, _, _ = delaunay_with_holes(X, [])
        # drop triangles whose centroid is far from the surface (spanning a hole: eyes, mouth)
        import trimesh

        m = trimesh.Trimesh(self.skin_rest, self.skin_faces, process=False)
        samples, _ = trimesh.sample.sample_surface(m, 60000, seed=1)
        tree = cKDTree(samples)
        cen = P[T].mean(axis=1)
        edge = np.max(np.linalg.norm(P[T] - np.roll(P[T], 1, axis=1), axis=2), axis=1)
        d, _ = tree.query(cen)
        T = T[d < 0.25 * edge + 0.0005]
        T = improve(P, X, T)
        T = _peel3d(P, T, {})
        kinds = ["dot"] * len(P)
        # coarse points: farthest-point sampling over the dots
        k = min(18, len(P))
        chosen = [int(np.argmin(np.linalg.norm(P - P.mean(axis=0), axis=1)))]
        dist = np.linalg.norm(P - P[chosen[0]], axis=1)
        while len(chosen) < k:
            j = int(np.argmax(dist))
            chosen.append(j)
            dist = np.minimum(dist, np.linalg.norm(P - P[j], axis=1))
        coarse = np.array(chosen, int)
        Tc, _, _ = delaunay_with_holes(X[coarse], [], peel_ratio=3.0)
        names = [""] * len(P)
        for i, j in enumerate(coarse):
            names[j] = f"coarse_{i:02d}"
        regions = _bbox_regions(P, self.skin_rest)
        return Template(kinds, names, P.copy(), T, coarse, [names[j] for j in coarse], Tc, regions, {}, {}, {},
                        ["skin"] * len(P), self.dot_tri.astype(int), self.dot_bary.copy(), "mesh",
                        extra={"skin_faces": self.skin_faces, "chart": X})

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
        i = 0
        while len(out) < n and len(names) > 1:
            a, b = names[i % len(names)], names[(i * 7 + 3) % len(names)]
            if a != b:
                out.append(Expression(f"{a}+{b}_{i}", _category(a), self.params(**{a: 0.6, b: 0.6})))
            i += 1
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
        p = self.check_params(params)
        V = self.skin_rest + np.tensordot(p, self.deltas, axes=1)
        N = vertex_normals(V, self.skin_faces)
        dots = np.einsum("nk,nkj->nj", self.dot_bary, V[self.skin_faces[self.dot_tri]])
        tex = Textures(self._albedo, self._roughness, self._normal) if textures else None
        T = {"head": np.eye(4)}
        return Pose(p, V, N, {}, dots, dots.copy(), tex, T)

    def split_skin(self, pose: Pose):
        m = self.skin_uv_vertex
        return pose.skin_vertices[m], pose.skin_normals[m], self.skin_uv, self.skin_uv_faces


def _bbox_regions(P, V):
    lo, hi = V.min(axis=0), V.max(axis=0)
    u = (P - lo) / np.maximum(hi - lo, 1e-12)          # 0..1 in each axis
    x, y = u[:, 0] - 0.5, u[:, 1]
    out = {k: [] for k in REGION_NAMES}
    for i in range(len(P)):
        if y[i] > 0.75:
            r = "forehead"
        elif y[i] > 0.55:
            r = "nose" if abs(x[i]) < 0.08 else ("eye_left" if x[i] > 0 else "eye_right")
        elif y[i] > 0.40:
            r = "nose" if abs(x[i]) < 0.08 else ("cheek_left" if x[i] > 0 else "cheek_right")
        elif y[i] > 0.22:
            r = "mouth" if abs(x[i]) < 0.18 else ("cheek_left" if x[i] > 0 else "cheek_right")
        elif y[i] > 0.10:
            r = "chin" if abs(x[i]) < 0.2 else ("cheek_left" if x[i] > 0 else "cheek_right")
        else:
            r = "throat" if abs(x[i]) < 0.2 else "neck"
        out[r].append(i)
    return {k: np.array(v, int) for k, v in out.items()}
