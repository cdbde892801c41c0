"""Scene files (``scenes/*.xml``) that place a face model, a camera and an environment.

A scene file is ordinary Mitsuba XML using mifacerf's plugins; mifacerf only adds the
target mesh: :func:`render_scene_file` reads the scene's ``model``, ``expression`` and
``target`` defaults (overridable with ``-D``), writes the target mesh (the template's
topology, in vertex order, no texture coordinates) to a PLY, and loads the scene with
``face_mesh`` set to it. In the scene, the face is::

    <shape type="ply" id="face"><string name="filename" value="$face_mesh"/></shape>

and its eyes, teeth and mouth interior are shapes with those ids (``eye_left``,
``eye_right``, ``teeth_upper``, ``teeth_lower``, ``mouth_interior``) from ``$eye_left_mesh`` …
"""
from __future__ import annotations

import os
import tempfile
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from ..imageio import write_exr, write_png
from ..variant import ensure_plugins


def write_target_mesh(path, vertices: np.ndarray, triangles: np.ndarray) -> Path:
    """A binary little-endian PLY with exactly these vertices (in order) and triangles."""
    import trimesh

    mesh = trimesh.Trimesh(np.asarray(vertices, np.float64), np.asarray(triangles, np.int64), process=False)
    data = trimesh.exchange.ply.export_ply(mesh, encoding="binary", vertex_normal=False, include_attributes=False)
    Path(path).write_bytes(data)
    return Path(path)


def read_target_mesh(path) -> np.ndarray:
    """Vertices (T, 3) of a target mesh file: .npy (T, 3) or a mesh file (.ply/.obj, vertex order kept)."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such target mesh")
    if path.suffix == ".npy":
        v = np.load(path)
    else:
        import trimesh

        v = np.asarray(trimesh.load(path, process=False, force="mesh").vertices)
    v = np.asarray(v, np.float64)
    if v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"{path}: expected (T, 3) vertices, got {v.shape}")
    return v


def scene_defaults(xml_path) -> dict:
    """The ``<default name=... value=...>`` entries of a Mitsuba scene file."""
    root = ET.parse(xml_path).getroot()
    return {d.get("name"): d.get("value") for d in root.iter("default")}


def load_scene_file(xml_path, params: dict | None = None):
    """Load a scene file with its target mesh written; returns (scene, parameters used)."""
    from .api import load_model

    mi = ensure_plugins()  # the scene names the facerf plugins
    xml_path = Path(xml_path)
    values = {**scene_defaults(xml_path), **(params or {})}
    if "model" not in values:
        raise KeyError(f"{xml_path}: needs a 'model' parameter (a <default> or -D model=...)")
    face = load_model(Path(values["model"]).resolve())
    target = values.get("target") or ""
    if target:
        vertices, _ = face.target(mesh=read_target_mesh(target))  # validates topology and values
    else:
        vertices, _ = face.target(values.get("expression") or face.model.neutral)
    folder = Path(tempfile.mkdtemp(prefix="mifacerf-scene-"))
    write_target_mesh(folder / "face.ply", vertices, face.model.triangles)
    values["face_mesh"] = str(folder / "face.ply")
    # eyes, teeth, mouth interior, posed for the target (a part the model lacks: a speck far away)
    from ..geometry.rigid import apply
    from .parts import PARTS, part_meshes

    parts = face.parts(mesh=vertices) if target else face.parts(values.get("expression") or face.model.neutral)
    meshes = part_meshes(face.model.template)
    for p in PARTS:
        path = folder / f"{p}.ply"
        if p in meshes and p in parts:
            write_target_mesh(path, apply(parts[p], meshes[p][0]), meshes[p][1])
        else:
            write_target_mesh(path, np.array([[1e3, 1e3, 1e3], [1e3 + 1e-6, 1e3, 1e3], [1e3, 1e3 + 1e-6, 1e3]]),
                              np.array([[0, 1, 2]]))
        values[f"{p}_mesh"] = str(path)
    if "envmap" in values:
        from ..environment import GENERATORS, cache_dir, generated

        if values["envmap"] in GENERATORS:  # a generated environment: its cached EXR
            generated(values["envmap"])
            values["envmap"] = str(cache_dir() / "environments" / f"{values['envmap']}-128.exr")
        else:
            values["envmap"] = str(Path(values["envmap"]).resolve())
    for key in ("model", "target"):
        if values.get(key):
            values[key] = str(Path(values[key]).resolve())
    here = os.getcwd()
    try:
        os.chdir(xml_path.parent)  # relative paths in the scene are relative to the file
        scene = mi.load_file(str(xml_path.name), **{k: str(v) for k, v in values.items()})
    finally:
        os.chdir(here)
    return scene, values


def render_scene_file(xml_path, output, params: dict | None = None, spp: int | None = None) -> Path:
    """Render a scene file to ``output`` (.exr, plus a .png beside it)."""
    mi = ensure_plugins()
    scene, _ = load_scene_file(xml_path, params)
    img = np.asarray(mi.render(scene, spp=spp or 0), np.float32)
    output = Path(output)
    output.parent.mkdir(parents=True, exist_ok=True)
    write_exr(output, img if img.shape[2] in (3, 4) else img[..., :4])
    write_png(output.with_suffix(".png"), img[..., :4] if img.shape[2] >= 4 else img)
    return output
