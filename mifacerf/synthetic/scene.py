"""One Mitsuba scene holding every shape of a subject, updated in place per pose.

::

    scene = SubjectScene(subj, extra={"env": {"type": "envmap", ...}})   # no sensor needed
    scene.set_pose(subj.pose(p))        # vertex positions / normals and textures via mi.traverse
    si = scene.scene.ray_intersect(rays)
    part_id, in_face = scene.classify(si)

Shapes (ids): ``skin``, ``eye_left``, ``eye_right``, ``teeth_upper``, ``teeth_lower``,
``mouth_interior``. Materials are all non-delta (the light stage is direct lighting with shadows):

* skin: ``normalmap`` over ``principled`` (albedo texture as ``base_color``, roughness texture,
  ``specular`` 0.5), normal map per :mod:`.textures`;
* eyes: ``principled`` with the iris / sclera texture and a low-roughness (glossy, not smooth) cornea;
* teeth: off-white ``principled``, roughness 0.3;
* mouth interior: ``twosided`` ``diffuse`` with dark-red per-vertex colours.

**Per-hit classification.** :meth:`SubjectScene.classify` maps a ``SurfaceInteraction3f`` to a part
id (:data:`PART_IDS`; 0 = no subject shape, e.g. a miss or an ``extra`` shape) and ``in_face``: True
where the hit is on a skin triangle inside the area the registration template covers
(``subj.skin_face_region``), which includes the lips and eyelids. Eyes and teeth are separate part
ids (a face mask for evaluation may add them).
"""
from __future__ import annotations

import numpy as np

from ..variant import ensure_variant

PART_IDS = {"skin": 1, "eye_left": 2, "eye_right": 3, "teeth_upper": 4, "teeth_lower": 5,
            "mouth_interior": 6}
TEETH_COLOUR = (0.78, 0.74, 0.64)


def _mesh(mi, name, n_v, n_f, bsdf, uv=False, colours=False):
    import drjit as dr  # noqa: F401

    props = mi.Properties()
    props["bsdf"] = bsdf
    return mi.Mesh(name, n_v, n_f, props=props, has_vertex_normals=True, has_vertex_texcoords=uv)


def _bitmap(mi, arr, raw=True):
    arr = np.ascontiguousarray(arr, np.float32)
    if arr.ndim == 2:
        arr = arr[..., None]
    return {"type": "bitmap", "data": mi.TensorXf(arr), "raw": raw, "filter_type": "bilinear",
            "wrap_mode": "clamp"}


class SubjectScene:
    """A Mitsuba scene of a subject (procedural or mesh subject); see the module docstring."""

    def __init__(self, subject, extra: dict | None = None, pose=None):
        mi = ensure_variant()
        import drjit as dr

        self.mi, self.dr = mi, dr
        self.subject = subject
        pose = pose if pose is not None else subject.neutral
        shapes = {}
        tex = pose.textures
        skin_bsdf = mi.load_dict({
            "type": "normalmap",
            "normalmap": _bitmap(mi, tex.normal_map),
            "bsdf": {"type": "principled", "base_color": _bitmap(mi, tex.albedo),
                     "roughness": _bitmap(mi, tex.roughness), "specular": 0.5},
        })
        Vs, Ns, UV, Fs = subject.split_skin(pose)
        shapes["skin"] = self._new_mesh("skin", Vs, Fs, Ns, UV, skin_bsdf)
        for name, part in pose.parts.items():
            if name.startswith("eye"):
                bsdf = mi.load_dict({"type": "principled", "base_color": _bitmap(mi, subject.eye_albedo),
                                     "roughness": _bitmap(mi, subject.eye_roughness), "specular": 0.5})
            elif name.startswith("teeth"):
                bsdf = mi.load_dict({"type": "principled", "base_color": {"type": "rgb", "value": TEETH_COLOUR},
                                     "roughness": 0.3, "specular": 0.5})
            elif name == "mouth_interior":
                bsdf = mi.load_dict({"type": "twosided", "bsdf": {
                    "type": "diffuse", "reflectance": {"type": "mesh_attribute", "name": "vertex_color"}}})
            else:
                bsdf = mi.load_dict({"type": "diffuse"})
            m = self._new_mesh(name, part.vertices, part.faces, part.normals, part.uv, bsdf)
            if part.vertex_colors is not None:
                m.add_attribute("vertex_color", 3, dr.ravel(mi.Color3f(np.asarray(part.vertex_colors, np.float32).T)))
            shapes[name] = m
        d = {"type": "scene"}
        d.update(shapes)
        if extra:
            d.update(extra)
        self.scene = mi.load_dict(d)
        self.shapes = {s.id(): s for s in self.scene.shapes() if s.id() in PART_IDS}
        self.params = mi.traverse(self.scene)
        keys = list(self.params.keys())

        def find(suffix, prefix="skin."):
            for k in keys:
                if k.startswith(prefix) and k.endswith(suffix):
                    return k
            raise KeyError(f"no scene parameter {prefix}*{suffix}")

        self._k_albedo = find("base_color.data")
        self._k_rough = find("roughness.data")
        self._k_normal = find("normalmap.data")
        flags = np.zeros(len(subject.skin_faces), bool) if getattr(subject, "skin_face_region", None) is None \
            else np.asarray(subject.skin_face_region, bool)
        self._face_flags = mi.Bool(flags)
        self._has_region = bool(flags.any())
        self.pose = None
        self.set_pose(pose)

    # ------------------------------------------------------------------------------------------
    def _new_mesh(self, name, V, F, N, UV, bsdf):
        mi, dr = self.mi, self.dr
        m = _mesh(mi, name, len(V), len(F), bsdf, uv=UV is not None)
        p = mi.traverse(m)
        p["vertex_positions"] = dr.ravel(mi.Point3f(np.asarray(V, np.float32).T))
        p["faces"] = dr.ravel(mi.Vector3u(np.asarray(F, np.uint32).T))
        p["vertex_normals"] = dr.ravel(mi.Normal3f(np.asarray(N, np.float32).T))
        if UV is not None:
            p["vertex_texcoords"] = dr.ravel(mi.Point2f(np.asarray(UV, np.float32).T))
        p.update()
        return m

    def set_pose(self, pose) -> None:
        """Move every shape to ``pose`` and upload its textures (in place; no scene reload)."""
        mi, dr = self.mi, self.dr
        p = self.params
        Vs, Ns, _, _ = self.subject.split_skin(pose)
        p["skin.vertex_positions"] = dr.ravel(mi.Point3f(np.asarray(Vs, np.float32).T))
        p["skin.vertex_normals"] = dr.ravel(mi.Normal3f(np.asarray(Ns, np.float32).T))
        for name, part in pose.parts.items():
            p[f"{name}.vertex_positions"] = dr.ravel(mi.Point3f(np.asarray(part.vertices, np.float32).T))
            p[f"{name}.vertex_normals"] = dr.ravel(mi.Normal3f(np.asarray(part.normals, np.float32).T))
        tex = pose.textures
        if tex is not None and (self.pose is None or self.pose.textures is None
                                or tex.albedo is not self.pose.textures.albedo):
            p[self._k_albedo] = mi.TensorXf(np.ascontiguousarray(tex.albedo, np.float32))
        if tex is not None and (self.pose is None or self.pose.textures is None
                                or tex.normal_map is not self.pose.textures.normal_map):
            p[self._k_normal] = mi.TensorXf(np.ascontiguousarray(tex.normal_map, np.float32))
        if tex is not None and self.pose is None:
            p[self._k_rough] = mi.TensorXf(np.ascontiguousarray(tex.roughness, np.float32)[..., None])
        p.update()
        self.pose = pose

    # ------------------------------------------------------------------------------------------
    def part_of(self, shape) -> str | None:
        """Part name of a Mitsuba shape of this scene ('skin', 'eye_left', ...), or None."""
        try:
            sid = shape.id()
        except AttributeError:
            return None
        return sid if sid in PART_IDS else None

    def classify(self, si):
        """(part id per lane as ``mi.UInt32`` (see :data:`PART_IDS`, 0 = none), in-face ``mi.Bool``)."""
        mi, dr = self.mi, self.dr
        pid = dr.zeros(mi.UInt32, dr.width(si.t))
        valid = si.is_valid()
        is_skin = mi.Bool(False)
        for name, shape in self.shapes.items():
            hit = valid & (si.shape == mi.ShapePtr(shape))
            pid = dr.select(hit, PART_IDS[name], pid)
            if name == "skin":
                is_skin = hit
        face = dr.gather(mi.Bool, self._face_flags, si.prim_index, is_skin) & is_skin
        return pid, face
