"""The procedural synthetic subject: :class:`Subject`, :class:`Pose`, :func:`default_subject`.

::

    subj = default_subject()                 # deterministic; expensive steps cached on disk
    p = subj.params(smile_L=1, jaw_open=0.2) # parameter vector (others at their defaults)
    pose = subj.pose(p)                      # all geometry (world frame, float64) + textures

**Skin topology and seams.** ``pose.skin_vertices`` (V, 3) and ``subj.skin_faces`` (F, 3) are the
skin as one connected surface (the mouth and eye slits are cut: their upper and lower margins are
distinct vertices). The UV atlas splits vertices along chart seams: ``subj.skin_uv`` (V_uv, 2) with
``subj.skin_uv_faces`` (F, 3) (same face order as ``skin_faces``) and ``subj.skin_uv_vertex`` (V_uv,)
giving the skin vertex of every uv vertex. A renderer uses ``skin_vertices[skin_uv_vertex]`` with
``skin_uv_faces``; :meth:`Subject.split_skin` does this, normals included (computed on the unsplit
surface, so seams do not show).

**Parts** (``pose.parts``): ``eye_left``, ``eye_right``, ``teeth_upper``, ``teeth_lower`` (rigid:
``transform`` maps the part's rest vertices ``Subject.part_rest[name]`` to world) and
``mouth_interior`` (deformable, ``transform`` None). Rest frames are the head frame at the neutral
head pose.

**Textures** (``pose.textures``): ``albedo`` (H, W, 3) linear sRGB in [0, 1], ``roughness`` (H, W)
(principled roughness), ``normal_map`` (H, W, 3) tangent-space normals encoded ``(n + 1)/2``; see
:mod:`.textures` for the texel ↔ uv convention and the tangent frame. Eye textures are static:
``subj.eye_albedo``, ``subj.eye_roughness``.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

from . import cache
from . import head as H
from . import parts as PT
from .dots import DOT_RADIUS, choose_dots
from ..geometry.rigid import apply
from .expressions import CONTROL_INDEX, CONTROL_NAMES, CONTROLS, SkinRig, default_params
from .presets import Expression, presets as _presets
from .textures import SkinTextures, build_atlas, rasterize

RIGID_PARTS = ("eye_left", "eye_right", "teeth_upper", "teeth_lower")
PART_NAMES = ("skin",) + RIGID_PARTS + ("mouth_interior",)


@dataclass
class Part:
    """One part of the subject in one pose (world frame)."""
    name: str
    vertices: np.ndarray                 # (n, 3)
    faces: np.ndarray                    # (m, 3) int32, outward
    normals: np.ndarray                  # (n, 3) unit vertex normals
    transform: np.ndarray | None = None  # (4, 4) rest -> world for rigid parts
    uv: np.ndarray | None = None         # (n, 2) for textured parts (eyes)
    vertex_colors: np.ndarray | None = None  # (n, 3) linear RGB (mouth interior)

    @property
    def rigid(self) -> bool:
        return self.transform is not None


@dataclass
class Textures:
    albedo: np.ndarray       # (H, W, 3) float32
    roughness: np.ndarray    # (H, W) float32
    normal_map: np.ndarray   # (H, W, 3) float32 in [0, 1]


@dataclass
class Pose:
    """All geometry of one parameter vector, world frame, float64."""
    params: np.ndarray
    skin_vertices: np.ndarray      # (V, 3)
    skin_normals: np.ndarray       # (V, 3)
    parts: dict                    # name -> Part
    dots: np.ndarray               # (D, 3) dot centres
    template_vertices: np.ndarray  # (T, 3)
    textures: Textures
    transforms: dict               # 'head', 'jaw', 'eye_left', 'eye_right', 'teeth_upper', 'teeth_lower'
    wrinkles: dict = field(default_factory=dict)   # family -> per-vertex activation (V,)
    lid_angles: dict = field(default_factory=dict)


def vertex_normals(V, F):
    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    N = np.zeros_like(V)
    for k in range(3):
        N[:, 0] += np.bincount(F[:, k], n[:, 0], len(V))
        N[:, 1] += np.bincount(F[:, k], n[:, 1], len(V))
        N[:, 2] += np.bincount(F[:, k], n[:, 2], len(V))
    return N / np.maximum(np.linalg.norm(N, axis=1, keepdims=True), 1e-30)


def barycentric_points(V, F, tri, bary):
    return np.einsum("nk,nkj->nj", bary, V[F[tri]])


class Subject:
    """The procedural head (see the module docstring)."""

    kind = "procedural"

    def __init__(self, texture_resolution: int = 1024):
        self.texture_resolution = int(texture_resolution)
        self.grid = H.load_skin_grid()
        self.rig = SkinRig(self.grid)
        self.controls = list(CONTROLS)
        self.control_names = list(CONTROL_NAMES)
        self.skin_faces = self.grid.faces
        self.skin_rest = self.grid.vertices
        # parts at rest
        ev, ef, euv, _ = PT.eyeball_mesh()
        self.part_rest, self.part_faces, self.part_uv = {}, {}, {}
        for name, sgn in (("eye_left", 1.0), ("eye_right", -1.0)):
            self.part_rest[name] = ev + H.EYE_CENTRE * np.array([sgn, 1, 1])
            self.part_faces[name] = ef
            self.part_uv[name] = euv
        for name, spec in (("teeth_upper", PT.UPPER), ("teeth_lower", PT.LOWER)):
            self.part_rest[name], self.part_faces[name] = PT.teeth_mesh(spec)
        self.sock = PT.MouthSock(self.grid.slits["mouth"], self.grid.vertices)
        self.part_faces["mouth_interior"] = self.sock.faces
        self.eye_albedo, self.eye_roughness = PT.eye_textures()
        self.eye_centres = {n: H.EYE_CENTRE * np.array([s, 1, 1]) for n, s in (("eye_left", 1), ("eye_right", -1))}
        self.eye_radius = H.EYE_RADIUS

        # neutral skin, dots
        st0 = self.rig.deform(default_params())
        self.neutral_skin = st0.head_frame_vertices
        self.dot_radius = DOT_RADIUS
        from .template import marked_vertices

        marks = self.neutral_skin[[v for _, _, v in marked_vertices(self.neutral_skin)]]
        self.dot_tri, self.dot_bary, self.dot_names = choose_dots(self.neutral_skin, self.skin_faces, avoid=marks)
        self.dots_neutral = barycentric_points(self.neutral_skin, self.skin_faces, self.dot_tri, self.dot_bary)

        # atlas (cached) and textures (static part cached)
        res = self.texture_resolution
        at = cache.cached(cache.key("atlas", res, self.skin_faces.shape, float(self.skin_rest.sum())),
                          lambda: build_atlas(self.skin_rest, self.skin_faces, res, self._texture_importance()))
        self.atlas = at
        self.skin_uv = at["uv"]
        self.skin_uv_faces = at["uv_faces"]
        self.skin_uv_vertex = at["uv_vertex"]
        akey = cache.key("raster", res, self.skin_faces.shape, float(self.skin_rest.sum()))
        rast = cache.cached(akey, lambda: dict(zip(("tri", "bary", "inside"),
                                                    rasterize(at["uv"], at["uv_faces"], res))))
        raster = (rast["tri"], rast["bary"].astype(np.float32), rast["inside"])
        # the static maps are cached in float16, and a freshly built subject uses them rounded the same way,
        # so a process with a cold cache renders bit for bit the subject a process with a warm one does
        # (SkinTextures rounds the maps it computes to float16 as the cache stores them)
        static = cache.load(cache.key("skin-static", res, float(self.dots_neutral.sum())))
        self.tex = SkinTextures(self.neutral_skin, self.skin_faces, at, res, self.dots_neutral, DOT_RADIUS,
                                static=static, raster=raster)
        if static is None:
            try:
                cache.save(cache.key("skin-static", res, float(self.dots_neutral.sum())), **self.tex.static_arrays())
            except OSError:
                pass

        # registration template
        from .template import build_template

        self.template = build_template(self)
        self.skin_face_region = self._face_region()
        self._neutral_pose = None

    def _texture_importance(self) -> np.ndarray:
        """(F,) bool: skin faces that get full texel density (the face and the front of the neck;
        the hair, the back of the head and neck get less)."""
        from .textures import hair_mask, head_azimuth

        C = self.neutral_skin[self.skin_faces].mean(axis=1)
        front = np.abs(head_azimuth(C)) < np.radians(105)
        return front & (hair_mask(C) < 0.5) & (C[:, 1] > H.NECK_BASE_Y + 0.015)

    def _face_region(self) -> np.ndarray:
        """(F,) bool: skin triangles inside the area the template mesh covers (lips and lid margins
        included)."""
        import matplotlib.tri as mtri

        from .template import SkinChart, _point_in_poly

        tpl = self.template
        chart = SkinChart(self.grid, self.grid.vertices)
        F = self.skin_faces
        C = chart.points(F, np.arange(len(F)), np.full((len(F), 3), 1.0 / 3.0))
        X = tpl.extra["chart"]
        tri = mtri.Triangulation(X[:, 0], X[:, 1], np.asarray(tpl.face_triangles))
        inside = tri.get_trifinder()(C[:, 0], C[:, 1]) >= 0
        for loop in tpl.holes.values():
            inside |= _point_in_poly(C, X[np.asarray(loop)])
        return inside

    # ------------------------------------------------------------------------------------------
    def params(self, **named) -> np.ndarray:
        """Parameter vector from named control values (others at their defaults)."""
        p = default_params()
        for k, v in named.items():
            if k not in CONTROL_INDEX:
                raise KeyError(f"unknown control {k!r}; controls: {', '.join(CONTROL_NAMES)}")
            p[CONTROL_INDEX[k]] = float(v)
        return p

    def presets(self, n) -> list[Expression]:
        return _presets(n)

    @property
    def neutral(self) -> "Pose":
        if self._neutral_pose is None:
            self._neutral_pose = self.pose(default_params())
        return self._neutral_pose

    def check_params(self, params) -> np.ndarray:
        p = np.asarray(params, float)
        if p.shape != (len(CONTROLS),):
            raise ValueError(f"parameter vector must have shape ({len(CONTROLS)},), got {p.shape}")
        if not np.all(np.isfinite(p)):
            raise ValueError("parameter vector contains NaN or inf")
        return p

    def pose(self, params, textures: bool = True) -> Pose:
        """Geometry (and, unless ``textures=False``, textures) for one parameter vector."""
        p = self.check_params(params)
        st = self.rig.deform(p)
        V = st.vertices
        N = vertex_normals(V, self.skin_faces)
        parts = {}
        T = {"head": st.head, "jaw": st.jaw, "eye_left": st.eyes["eye_left"],
             "eye_right": st.eyes["eye_right"], "teeth_upper": st.head, "teeth_lower": st.jaw}
        for name in RIGID_PARTS:
            Tm = T[name]
            Pv = apply(Tm, self.part_rest[name])
            parts[name] = Part(name, Pv, self.part_faces[name], vertex_normals(Pv, self.part_faces[name]),
                               Tm, self.part_uv.get(name))
        T_rel = np.linalg.inv(st.head) @ st.jaw
        sv = self.sock.vertices(st.head_frame_vertices, T_rel, st.head)
        parts["mouth_interior"] = Part("mouth_interior", sv, self.sock.faces,
                                       vertex_normals(sv, self.sock.faces), None, None,
                                       self.sock.vertex_colours)
        dots = barycentric_points(V, self.skin_faces, self.dot_tri, self.dot_bary)
        tv = self.template.positions(V, parts) if self.template is not None else np.zeros((0, 3))
        if textures:
            alb, nm, acts = self.tex.for_pose(st.head_frame_vertices)
            tex = Textures(alb, self.tex.roughness, nm)
        else:
            tex, acts = None, {}
        return Pose(p, V, N, parts, dots, tv, tex, T, acts, st.lid_angles)

    def without_dots(self) -> "Subject":
        """The same subject with its fiducial dots washed off (evaluation's ground truth: the model
        renders dot-free faces, paper §4.2). Shares everything but the skin's static albedo and
        roughness, which are rebuilt without dots (cached on disk like the dotted ones)."""
        import copy

        if getattr(self, "_dot_free", None) is None:
            res = self.texture_resolution
            key = cache.key("skin-static-nodots", res, float(self.skin_rest.sum()))
            static = cache.load(key)
            if static is None:      # rounded as the cache stores it (cold and warm caches agree bit for bit)
                static = {k: v.astype(np.float16) for k, v in
                          self.tex._static_maps(np.zeros((0, 3)), DOT_RADIUS).items()}
                try:
                    cache.save(key, **static)
                except OSError:
                    pass
            clean = copy.copy(self)
            clean.tex = copy.copy(self.tex)
            for name in ("albedo", "roughness"):
                a = np.asarray(static[name], np.float32).copy()
                a.flags.writeable = False
                setattr(clean.tex, name, a)
            clean._neutral_pose = None
            clean._dot_free = clean
            self._dot_free = clean
        return self._dot_free

    def split_skin(self, pose: Pose):
        """Skin for a renderer: (positions (V_uv, 3), normals (V_uv, 3), uv (V_uv, 2), faces (F, 3))."""
        m = self.skin_uv_vertex
        return pose.skin_vertices[m], pose.skin_normals[m], self.skin_uv, self.skin_uv_faces


@lru_cache(maxsize=4)
def default_subject(texture_resolution: int = 1024) -> Subject:
    """The default procedural subject (deterministic, cached per process and on disk)."""
    return Subject(texture_resolution)
