"""A triangle mesh in its own Mitsuba scene, for ray casting (visibility, rasterisation, renders).

Vertices are updated in place (``mi.traverse``), so one scene serves every
expression and frame. Hits are reported as (triangle, barycentrics, distance):
barycentric ``(b0, b1, b2)`` weights the triangle's vertices ``faces[tri]`` in order.
Positions and distances are world coordinates in metres. Mitsuba (the variant chosen by
:mod:`mifacerf.variant`) is imported when the first :class:`MeshScene` is built, not when this
module is imported.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..jitarrays import to_jit
from .boubekeur2008 import to_coarse_device
from ..camera import Camera, stratified_pixel_samples
from ..variant import ensure_variant


@dataclass
class Hits:
    """Ray hits: ``valid`` (N,) bool; ``tri`` (N,) int64 (−1 if none); ``bary`` (N, 3); ``t`` (N,) distance (inf if none)."""

    valid: np.ndarray
    tri: np.ndarray
    bary: np.ndarray
    t: np.ndarray
    sub: np.ndarray | None = None   #: (N,) the traced primitive where it is not ``tri`` (CurvedMeshScene's sub-faces)

    def take(self, rows: np.ndarray, other: "Hits") -> None:
        """Rows ``rows`` replaced by ``other``'s (its rows in that order); ``t`` as given."""
        self.valid[rows], self.tri[rows], self.bary[rows], self.t[rows] = other.valid, other.tri, other.bary, other.t
        if self.sub is not None:
            self.sub[rows] = other.sub


class MeshScene:
    """``vertices`` (V, 3) world, ``faces`` (F, 3) int."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        import drjit as dr

        mi = ensure_variant()
        self._mi, self._dr = mi, dr
        self.faces = np.asarray(faces, np.int64).reshape(-1, 3)
        vertices = np.asarray(vertices, np.float64)
        if self.faces.size and (self.faces.min() < 0 or self.faces.max() >= len(vertices)):
            raise ValueError("faces index vertices out of range")
        self.mesh = mi.Mesh("mesh", len(vertices), len(self.faces))
        self._params = mi.traverse(self.mesh)
        self._params["faces"] = dr.ravel(mi.Vector3u(np.ascontiguousarray(self.faces.T, dtype=np.uint32)))
        self._pending = False
        self._in_scene = None         # the vertices Mitsuba's scene holds (an unchanged update is skipped)
        self.set_vertices(vertices, update=False)
        self._params.update()
        # not in parallel: a plugin (facerf, facerf_bsdf) builds these while Mitsuba loads its scene on the
        # thread pool, and a parallel load inside that one is a nested load (one full-suite run hung there once)
        self._scene = mi.load_dict({"type": "scene", "mesh": self.mesh}, parallel=False)
        self._scene_params = mi.traverse(self._scene)

    @property
    def scene(self):
        """The Mitsuba scene, its vertices up to date (a lazy :meth:`set_vertices` is applied first)."""
        self.commit()
        return self._scene

    def set_vertices(self, vertices: np.ndarray, update: bool = True, lazy: bool = False) -> None:
        """Move the mesh to ``vertices`` (V, 3). ``lazy``: the Mitsuba scene (whose acceleration structure
        Mitsuba rebuilds on every update) is updated only when next used (:attr:`scene`, :meth:`trace`,
        :meth:`occluded`); :meth:`camera_hits` rasterises without it."""
        v = np.asarray(vertices, np.float64)
        if v.shape != (self.mesh.vertex_count(), 3):
            raise ValueError(f"expected ({self.mesh.vertex_count()}, 3) vertices, got {v.shape}")
        if not np.isfinite(v).all():
            bad = np.flatnonzero(~np.isfinite(v).all(1))
            raise ValueError(f"{len(bad)} vertex position(s) are NaN/Inf (first: vertex {bad[0]})")
        self.vertices = v
        self._pending = bool(update and lazy)
        if self._pending:
            return
        if update and self._in_scene is not None and np.array_equal(v, self._in_scene):
            return      # unchanged (a turntable, a relit or re-viewed expression): no rebuild of the BVH
        flat = self._dr.ravel(to_jit(self._mi.Point3f, v.T))
        self._in_scene = v.copy()
        if update:
            self._scene_params["mesh.vertex_positions"] = flat
            self._scene_params.update()
        else:
            self._params["vertex_positions"] = flat

    def commit(self) -> None:
        """Apply a lazy :meth:`set_vertices` to the Mitsuba scene (nothing when none is pending)."""
        if self._pending:
            self.set_vertices(self.vertices)

    def camera_hits(self, camera: Camera, samples, directions: np.ndarray) -> Hits:
        """The culled hits of a camera's samples (as :meth:`trace` from the camera's centre with
        ``cull_back``): rasterised (:func:`.raster.camera_hits`, no acceleration structure) on the CPU
        variants where Numba is there, ray-cast otherwise (the CUDA variants: OptiX on the device) or where a
        triangle reaches behind the camera. ``samples`` the samples' :class:`.raster.SampleGrid`,
        ``directions`` (N, 3) their unit rays in the world (the ray cast's)."""
        from . import raster

        if samples is not None and raster.available() and self._mi.variant().startswith("llvm"):
            tess = self._tessellation()
            found = raster.camera_hits(self._raster_vertices(), self._raster_faces(), camera.centre, camera.R,
                                       samples, cull_back=True, tessellation=tess)
            if found is not None:
                tri, sub, bary, t = found
                return Hits(tri >= 0, tri, bary, t, sub=None if tess is None else sub)
        return self.trace(camera.centre, directions, cull_back=True)

    def _raster_vertices(self) -> np.ndarray:
        return self.vertices

    def _raster_faces(self) -> np.ndarray:
        return self.faces

    def _tessellation(self):
        return None

    def face_normals(self) -> np.ndarray:
        """(F, 3) unit normals of the triangles (right-hand rule on ``faces`` order)."""
        v = self.vertices[self.faces]
        n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
        return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)

    def trace(self, origins: np.ndarray, directions: np.ndarray, cull_back: bool = False,
              max_layers: int = 4, through: np.ndarray | None = None) -> Hits:
        """Closest hits of rays (origins (N, 3) or (3,), unit directions (N, 3)), world frame.

        ``cull_back``: back-facing triangles (seen from behind, e.g. the inside of the template
        through the eye or mouth opening) are passed through: the ray continues to the next
        surface (up to ``max_layers`` such surfaces; a ray still on one after that: no hit).
        ``through`` (F,) bool: triangles passed through whichever way they face (the eyes and teeth of a
        combined scene, when the skin behind them is wanted).
        """
        d = np.asarray(directions, np.float64).reshape(-1, 3)
        o = np.asarray(origins, np.float64)
        if o.shape != (3,):     # one origin (a camera's centre) is broadcast on the device, not copied N times
            o = np.broadcast_to(o, d.shape)
        hits = self._trace_once(o, d)
        if not cull_back and through is None:
            return hits
        normals = self._cull_normals() if cull_back else None
        offset = np.zeros(len(d))
        todo = np.arange(len(d))
        for _ in range(max_layers):
            back = self._passed(hits, todo, d, normals, through)
            if not back.any():
                break
            todo = todo[back]
            offset[todo] += hits.t[todo] + 1e-5
            again = self._trace_once((o if o.ndim == 1 else o[todo]) + offset[todo, None] * d[todo], d[todo])
            again.t = np.where(again.valid, again.t + offset[todo], np.inf)
            hits.take(todo, again)
        else:  # still behind back faces after max_layers: no hit
            bad = todo[self._passed(hits, todo, d, normals, through)]
            hits.valid[bad], hits.tri[bad], hits.bary[bad], hits.t[bad] = False, -1, 0.0, np.inf
        return hits

    def _passed(self, hits: Hits, rows: np.ndarray, d: np.ndarray, normals: np.ndarray | None,
                through: np.ndarray | None) -> np.ndarray:
        """(len(rows),) True where hit ``rows`` of rays ``d`` (N, 3) are passed through: met a face of
        ``normals`` (:meth:`_cull_normals`; None: no culling) from behind, or a triangle ``through`` marks."""
        v = np.flatnonzero(hits.valid[rows])
        out = np.zeros(len(rows), bool)
        if normals is not None:
            face = hits.tri if hits.sub is None else hits.sub
            out[v] = np.einsum("nd,nd->n", normals[face[rows[v]]], d[rows[v]]) > 0
        if through is not None:
            out[v] |= np.asarray(through, bool)[hits.tri[rows[v]]]
        return out

    def _cull_normals(self) -> np.ndarray:
        """The unit normals back faces are judged by, one per traced primitive (``Hits.sub`` where set)."""
        return self.face_normals()

    def _trace_once(self, o: np.ndarray, d: np.ndarray) -> Hits:
        """Closest hits of rays from ``o`` ((N, 3), or (3,): one origin for all) along ``d`` (N, 3)."""
        mi, dr = self._mi, self._dr
        if len(d) == 0:
            return Hits(np.zeros(0, bool), np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0))
        pi = self.scene.ray_intersect_preliminary(self._rays(o, d))
        return self._read_hits(pi.t, pi.prim_uv[0], pi.prim_uv[1], pi.prim_index)

    def _rays(self, o: np.ndarray, d: np.ndarray):
        """Dr.Jit rays from ``o`` ((N, 3), or (3,): one origin for all) along ``d`` (N, 3)."""
        mi, dr = self._mi, self._dr
        if o.ndim == 1:   # opaque, not a literal: a new camera position must not compile a new kernel
            origin = mi.Point3f(*[dr.opaque(mi.Float, float(x), len(d)) for x in o])
        else:
            origin = to_jit(mi.Point3f, o.T)
        return mi.Ray3f(origin, to_jit(mi.Vector3f, d.T))

    def _read_hits(self, t, u, v, prim, *also) -> Hits:
        """:class:`Hits` read back from Dr.Jit arrays of a preliminary intersection: distance ``t`` (inf: no
        hit), barycentrics ``u``, ``v`` of corners 1 and 2, triangle ``prim``; ``also``: more arrays of the same
        rays the caller reads, evaluated in the same kernel."""
        # one kernel for every output: read back one by one (is_valid included), each re-ran the ray cast
        self._dr.eval(t, u, v, prim, *also)
        t_hit = np.asarray(t)
        valid = t_hit < np.inf           # PreliminaryIntersection.is_valid(): t is inf where nothing was hit
        u, v = np.asarray(u), np.asarray(v)
        tri = np.where(valid, np.asarray(prim).astype(np.int64), -1)
        # (b0, b1, b2) = (1 - u - v, u, v) in float32, as the hit reports them, stored as float64; rows
        # without a hit (whose u, v are undefined) are zero
        bary = np.empty((len(t_hit), 3))
        with np.errstate(over="ignore", invalid="ignore"):   # the rows without a hit hold anything
            bary[:, 0] = 1 - u - v
        bary[:, 1] = u
        bary[:, 2] = v
        bary[~valid] = 0.0
        t = np.where(valid, t_hit, np.inf).astype(np.float64)
        return Hits(valid, tri, bary, t)

    def occluded(self, points: np.ndarray, targets: np.ndarray, eps: float = 1e-4) -> np.ndarray:
        """(N,) True where the segment from each point (N, 3) to its target ((N, 3) or (3,)) hits the mesh.

        The segment is shortened by ``eps`` metres at both ends (self-intersection).
        """
        mi = self._mi
        p = np.asarray(points, np.float64).reshape(-1, 3)
        q = np.broadcast_to(np.asarray(targets, np.float64), p.shape)
        d = q - p
        dist = np.linalg.norm(d, axis=1)
        d = d / np.maximum(dist, 1e-12)[:, None]
        o = p + eps * d
        ray = mi.Ray3f(to_jit(mi.Point3f, o.T), to_jit(mi.Vector3f, d.T))
        ray.maxt = to_jit(mi.Float, np.maximum(dist - 2 * eps, 0))
        return np.asarray(self.scene.ray_test(ray)).astype(bool)

    def render_hits(self, camera: Camera, spp: int = 1, seed: int = 0,
                    cull_back: bool = True) -> tuple[Hits, np.ndarray]:
        """Hits of a camera's pixel samples: (hits of H*W*spp samples, sample pixel positions (N, 2)).

        ``spp = 1`` traces exactly through pixel centres; more samples are stratified. Back-facing
        hits (the template's inside, seen through its openings) are culled by default.
        """
        if spp == 1:
            jj, ii = np.meshgrid(np.arange(camera.width), np.arange(camera.height))
            uv = np.stack([jj, ii], -1).reshape(-1, 2).astype(np.float64)
        else:
            uv = stratified_pixel_samples(camera.width, camera.height, spp, seed)
        o, d = camera.pixel_rays(uv)
        return self.trace(o, d, cull_back), uv

    def visible_from(self, points: np.ndarray, camera: Camera, tol: float = 0.003) -> np.ndarray:
        """(N,) visibility of surface points (N, 3) from a camera: in front of it, inside its image, and
        not hidden: the ray from the camera centre towards the point first meets the mesh no nearer
        than ``tol`` metres before the point (a depth-map test, robust for points on silhouettes,
        where a ray *from* the point grazes its own neighbouring triangles)."""
        points = np.asarray(points, np.float64).reshape(-1, 3)
        uv, z = camera.project(points)
        inside = (z > 0) & np.all(np.isfinite(uv), axis=1)
        inside &= (uv[:, 0] >= -0.5) & (uv[:, 0] <= camera.width - 0.5)
        inside &= (uv[:, 1] >= -0.5) & (uv[:, 1] <= camera.height - 0.5)
        vis = np.zeros(len(points), bool)
        if inside.any():
            d = points[inside] - camera.centre
            dist = np.linalg.norm(d, axis=1)
            hits = self.trace(camera.centre, d / dist[:, None])
            vis[inside] = ~hits.valid | (hits.t >= dist - tol)
        return vis


class CurvedMeshScene(MeshScene):
    """A :class:`MeshScene` whose rays meet the Phong-tessellated surface of its coarse mesh
    (:class:`~mifacerf.geometry.boubekeur2008.PhongTessellation`, ``level`` splits per edge; ``only`` (F,)
    bool: the faces to curve, the others traced flat; ``normals_from`` (F,) bool: the faces whose normals
    bend it, default ``only``) instead of its flat triangles. Everything it
    reports is on the coarse mesh — ``vertices`` (V, 3), ``faces`` (F, 3), :meth:`face_normals` (flat, per
    coarse face), and hits as (coarse triangle, barycentrics there) — so a caller swaps it for a
    :class:`MeshScene` unchanged; the distances ``t`` are to the curved surface. Back faces are culled by
    the sub-triangles' own orientation. ``level = 1`` traces the coarse mesh."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, level: int = 3, only=None, normals_from=None):
        from .boubekeur2008 import PhongTessellation

        vertices = np.asarray(vertices, np.float64)
        faces = np.asarray(faces, np.int64).reshape(-1, 3)
        self.tessellation = PhongTessellation(faces, len(vertices), level, only=only, normals_from=normals_from)
        self._curved = MeshScene(self.tessellation.positions(vertices), self.tessellation.faces)
        self._mi, self._dr = self._curved._mi, self._curved._dr
        self.mesh = self._curved.mesh
        self.faces = faces
        self.vertices = vertices
        self._maps = None

    def set_vertices(self, vertices: np.ndarray, update: bool = True, lazy: bool = False) -> None:
        v = np.asarray(vertices, np.float64)
        if v.shape != (self.tessellation.n_vertices, 3):
            raise ValueError(f"expected ({self.tessellation.n_vertices}, 3) vertices, got {v.shape}")
        if not np.isfinite(v).all():
            bad = np.flatnonzero(~np.isfinite(v).all(1))
            raise ValueError(f"{len(bad)} vertex position(s) are NaN/Inf (first: vertex {bad[0]})")
        self.vertices = v
        self._curved.set_vertices(self.tessellation.positions(v), update, lazy)

    @property
    def scene(self):
        return self._curved.scene

    def commit(self) -> None:
        self._curved.commit()

    def _raster_vertices(self) -> np.ndarray:
        return self._curved.vertices

    def _raster_faces(self) -> np.ndarray:
        return self.tessellation.faces

    def _tessellation(self):
        return self.tessellation

    def _trace_once(self, o: np.ndarray, d: np.ndarray) -> Hits:
        # the sub-face → coarse-face map applied on the device, in the ray cast's kernel (in NumPy it took
        # 11 ms for a 256² × 4 frame's hits): coarse barycentrics = Σ_k b_k × the sub-face corner k's
        mi, dr = self._mi, self._dr
        if len(d) == 0:
            hits = self._curved._trace_once(o, d)
            hits.sub = hits.tri.copy()
            return hits
        if self._maps is None:
            self._maps = self.tessellation.device_map(mi)
        pi = self._curved.scene.ray_intersect_preliminary(self._rays(o, d))
        ok = pi.t < dr.inf
        sub = pi.prim_index
        u, v = pi.prim_uv[0], pi.prim_uv[1]
        tri, coarse = to_coarse_device(mi, self._maps, sub, (1.0 - u - v, u, v), ok)
        hits = self._read_hits(pi.t, coarse[1], coarse[2], tri, sub)
        hits.sub = np.where(hits.valid, np.asarray(sub).astype(np.int64), -1)
        return hits

    def _cull_normals(self) -> np.ndarray:
        # culled by the sub-faces' own orientation (the class docstring), not the coarse face's
        return self._curved.face_normals()

    def occluded(self, points: np.ndarray, targets: np.ndarray, eps: float = 1e-4) -> np.ndarray:
        return self._curved.occluded(points, targets, eps)
