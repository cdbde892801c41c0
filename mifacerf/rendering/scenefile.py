"""Scene files (``scenes/*.xml``): plain Mitsuba XML naming mifacerf's plugins.

A scene names the model folder only; the ``facerf_face`` shape builds the face, eyes, teeth and
mouth-interior meshes from it (:mod:`.scene_assets`), so after ``import mitsuba as mi;
mi.set_variant(...); import mifacerf`` a scene loads with ``mi.load_file(path, model=MODEL)``.
:func:`load_scene_file` / :func:`render_scene_file` (``mifacerf render``) add the command line's
conveniences: ``-D`` values, a generated environment by name (``-D envmap=sky``), paths given on
the command line taken relative to the working directory (a scene's own defaults are relative to
the scene file, as Mitsuba resolves them), and the thread count.

:func:`write_target_mesh` / :func:`read_target_mesh`: target meshes in the template's topology
(the shape's ``target`` parameter reads .ply/.obj/.npy).
"""
from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from ..errors import MifacerfError
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


class SceneError(MifacerfError, ValueError):
    """A scene file that cannot be loaded or rendered; the message names the file (and the plugin's own error)."""


def _plugin_error(exc: RuntimeError, xml_path) -> SceneError | None:
    """Mitsuba reports an exception raised inside a Python plugin as a RuntimeError whose text holds the
    Python traceback; the plugin's own error (its last line, ``ModelError: <file>: ...``) is what the user
    needs: a SceneError with that message and where in the scene it came from (None: not such an error)."""
    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
    if len(lines) < 2 or "Traceback (most recent call last)" not in lines[0]:
        return None
    last = lines[-1]
    name, sep, message = last.partition(": ")
    if not sep or not name.replace("_", "").isalnum():
        return None
    where = lines[0].split("Traceback (most recent call last)")[0].rstrip(": ")
    where = where.split("] ", 1)[-1]
    return SceneError(f"{message} ({name}, {where})" if where else f"{message} ({name} in {xml_path})")


def scene_defaults(xml_path) -> dict:
    """The ``<default name=... value=...>`` entries of a Mitsuba scene file."""
    try:
        root = ET.parse(xml_path).getroot()
    except ET.ParseError as exc:
        # Mitsuba's own parser accepts what strict XML refuses inside comments (a "--", as in "--spp 16"):
        # so does this, with the comments taken out; anything else is named
        import re

        try:   # each comment replaced by its line breaks, so that an error elsewhere is named at its own line
            text = Path(xml_path).read_text(encoding="utf-8", errors="replace")
            root = ET.fromstring(re.sub(r"<!--.*?-->", lambda m: "\n" * m.group().count("\n"), text, flags=re.S))
        except ET.ParseError as inner:
            raise SceneError(f"{xml_path}: not a well-formed scene file ({inner})") from exc
    return {d.get("name"): d.get("value") for d in root.iter("default")}


def load_scene_file(xml_path, params: dict | None = None):
    """Load a scene file with ``params`` (``-D`` values) over its defaults; returns (scene, parameters used)."""
    mi = ensure_plugins()  # the scene names the facerf plugins
    xml_path = Path(xml_path)
    if not xml_path.exists():
        raise FileNotFoundError(f"{xml_path}: no such scene file")
    defaults = scene_defaults(xml_path)
    given = dict(params or {})
    unknown = [k for k in given if k not in defaults]
    if unknown:
        raise KeyError(f"{xml_path}: no parameter {', '.join(map(repr, unknown))}; it has "
                       f"{', '.join(defaults) or 'none'}")
    if "envmap" in given:
        from ..environment import GENERATORS, cache_dir, generated

        if given["envmap"] in GENERATORS:  # a generated environment: its cached EXR
            generated(given["envmap"])
            given["envmap"] = str(cache_dir() / "environments" / f"{given['envmap']}-128.exr")
    for key in ("model", "target", "envmap"):   # paths on the command line: relative to the working directory
        if given.get(key):
            given[key] = str(Path(given[key]).expanduser().resolve())
    if given.get("model") and not (Path(given["model"]) / "model.json").exists():
        raise FileNotFoundError(f"parameter 'model': {given['model']} is not a model folder (no model.json)")
    if given.get("envmap"):   # the API's checks (a 2:1 lat-long, finite, >= 0): Mitsuba's envmap stretches any image
        from ..environment import Environment

        Environment.load(given["envmap"])
    values = {**defaults, **given}
    try:
        scene = mi.load_file(str(xml_path), **{k: str(v) for k, v in given.items()})
    except RuntimeError as exc:
        raise (_plugin_error(exc, xml_path) or exc) from exc
    return scene, values


def render_scene_file(xml_path, output, params: dict | None = None, spp: int | None = None,
                      threads: int | None = None) -> Path:
    """Render a scene file to ``output`` (.exr, plus a .png beside it); ``spp`` overrides the sampler's
    count, ``threads`` the number of CPU threads (LLVM variants)."""
    mi = ensure_plugins()
    if threads:
        import drjit as dr

        dr.set_thread_count(int(threads))
    scene, _ = load_scene_file(xml_path, params)
    try:
        img = np.asarray(mi.render(scene, spp=spp or 0), np.float32)
    except RuntimeError as exc:
        cause = exc.__cause__
        if isinstance(cause, (ValueError, MifacerfError)):   # a plugin's own error inside mi.render's custom op
            raise SceneError(f"{xml_path}: {cause}") from exc
        raise (_plugin_error(exc, xml_path) or exc) from exc
    output = Path(output)
    output.parent.mkdir(parents=True, exist_ok=True)
    write_exr(output, img if img.shape[2] in (3, 4) else img[..., :4])
    write_png(output.with_suffix(".png"), img[..., :4] if img.shape[2] >= 4 else img)
    return output
