"""Face masks of ground-truth renders: which pixels show the parts of the subject the model renders.

A pixel belongs to the **face mask** when every one of its ``spp`` sub-pixel samples hits the
skin inside the area the registration template covers, an eye, or the teeth (the mouth's
interior and everything outside the template — scalp, ears' backs, shoulders — are not
modelled and are excluded). Masks are traced through the same camera model as every render.
"""
from __future__ import annotations

import numpy as np

from ..camera import Camera
from ..synthetic.olat import camera_rays

MODELLED = ("skin_face", "eye_left", "eye_right", "teeth_upper", "teeth_lower")


def classify_pixels(subject_scene, camera: Camera, spp: int = 4, seed: int = 0) -> dict:
    """Per sample: part id (see ``mifacerf.synthetic.scene.PART_IDS``), in-face flag and skin triangle,
    each (H, W, spp)."""
    mi = subject_scene.mi
    ray = camera_rays(camera, spp, seed)
    si = subject_scene.scene.ray_intersect(ray)
    pid, face = subject_scene.classify(si)
    shape = (camera.height, camera.width, spp)
    return {"part": np.asarray(pid).reshape(shape), "face": np.asarray(face).astype(bool).reshape(shape),
            "triangle": np.asarray(si.prim_index).reshape(shape), "valid": np.asarray(si.is_valid()).reshape(shape),
            "mi": mi}


def face_mask(classes: dict) -> np.ndarray:
    """(H, W) bool: all samples on modelled parts (template skin, eyes, teeth)."""
    from ..synthetic.scene import PART_IDS

    part = classes["part"]
    ok = classes["face"] | np.isin(part, [PART_IDS[p] for p in ("eye_left", "eye_right", "teeth_upper",
                                                                "teeth_lower")])
    return ok.all(axis=2)


def triangle_mask(classes: dict, triangle_flags: np.ndarray) -> np.ndarray:
    """(H, W) bool: all samples on skin triangles flagged in ``triangle_flags`` (F,) bool."""
    from ..synthetic.scene import PART_IDS

    skin = classes["part"] == PART_IDS["skin"]
    tri = np.where(skin, classes["triangle"], 0)
    return (skin & np.asarray(triangle_flags, bool)[tri]).all(axis=2)
