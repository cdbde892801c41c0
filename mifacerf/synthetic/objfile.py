"""Wavefront OBJ reading for a user's own head: positions in file order, per-corner texture
coordinates, named groups, UDIM tiles.

trimesh's OBJ loader (even with ``process=False, maintain_order=True``) splits vertices wherever a
position has several texture coordinates, so a seamed production head comes back with ten times its
vertices, most of them unused, and blendshape files no longer line up with the neutral. This reader
keeps the two topologies apart, as the file does:

* ``positions`` (V, 3): every ``v`` line in file order (the blendshape index space);
* ``faces`` (F, 3): triangles over ``positions`` (polygons fanned from their first corner; the
  ``polygon`` (F,) array names each triangle's source polygon);
* ``uvs`` (T, 2) and ``face_uvs`` (F, 3): every ``vt`` line and, per triangle corner, its ``vt``
  index (−1 where the corner has none); ``None`` when the file has no ``vt``;
* ``groups`` (names) and ``face_group`` (F,): the sub-mesh of each triangle. A file with several
  ``g`` / ``o`` names is split by them (``g`` wins over ``o``); a file with a single group but several
  ``usemtl`` materials is split by material (ICT FaceKit-style heads).

Negative (relative) indices, ``v/vt/vn``, ``v//vn`` and ``\\`` line continuations are read; ``vn``,
``s``, ``mtllib`` and the rest are ignored. Errors name the file and the line.

**UDIM.** Texture coordinates beyond [0, 1] are UDIM tiles: tile ``1001 + floor(u) + 10 floor(v)``.
:func:`udim_tiles` lists the tiles a set of triangles uses and :func:`pack_udim` maps them into one
[0, 1]² atlas (a grid of tiles, each with a small inset so bilinear look-ups do not bleed across
tiles) and assembles the matching texture from per-tile images.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import MifacerfError


class ObjError(MifacerfError, ValueError):
    """An OBJ file that cannot be read as a mesh (the message names the file and the line)."""


@dataclass
class ObjMesh:
    path: Path
    positions: np.ndarray            # (V, 3) float64, file order
    faces: np.ndarray                # (F, 3) int64 into positions
    polygon: np.ndarray              # (F,) int64 source polygon of each triangle
    uvs: np.ndarray | None           # (T, 2) float64
    face_uvs: np.ndarray | None      # (F, 3) int64 into uvs, -1 where missing
    groups: list                     # group names
    face_group: np.ndarray           # (F,) int64 into groups
    n_polygons: int = 0
    n_quads: int = 0

    def group_faces(self, name: str) -> np.ndarray:
        """Triangle ids of the group ``name``."""
        return np.nonzero(self.face_group == self.groups.index(name))[0]


def _fix(idx: int, n: int, path, lineno, what) -> int:
    if idx < 0:
        idx = n + idx
    else:
        idx = idx - 1
    if not (0 <= idx < n):
        raise ObjError(f"{path}: line {lineno}: {what} index out of range (the file has {n} so far)")
    return idx


def read_obj(path, positions_only: bool = False) -> ObjMesh:
    """Read an OBJ file (see the module docstring). ``positions_only`` still reads the faces'
    position indices (needed to check a blendshape's topology) but skips texture coordinates."""
    path = Path(path)
    try:
        text = path.read_text(errors="replace")
    except OSError as exc:
        raise ObjError(f"{path}: cannot read ({exc.strerror or exc})") from exc
    if "\\\n" in text:
        text = text.replace("\\\n", " ")
    V, VT = [], []
    fpos, fuv, fgrp = [], [], []
    tri_poly = []
    g_names, o_names, m_names = {}, {}, {}
    cur_g = cur_o = cur_m = None
    face_keys = []           # per polygon: (g, o, m)
    n_poly = n_quad = 0
    for lineno, line in enumerate(text.splitlines(), 1):
        if not line or line[0] == "#":
            continue
        c0 = line[0]
        if c0 == "v":
            c1 = line[1:2]
            if c1 == " " or c1 == "\t":
                p = line.split()
                try:
                    V.append((float(p[1]), float(p[2]), float(p[3])))
                except (IndexError, ValueError):
                    raise ObjError(f"{path}: line {lineno}: a 'v' line needs three numbers: {line.strip()[:60]!r}") from None
            elif c1 == "t" and not positions_only:
                p = line.split()
                try:
                    VT.append((float(p[1]), float(p[2]) if len(p) > 2 else 0.0))
                except (IndexError, ValueError):
                    raise ObjError(f"{path}: line {lineno}: a 'vt' line needs two numbers: {line.strip()[:60]!r}") from None
            continue
        if c0 == "f" and line[1:2] in (" ", "\t"):
            toks = line.split()[1:]
            if len(toks) < 3:
                raise ObjError(f"{path}: line {lineno}: a face needs at least three corners")
            nv, nt = len(V), len(VT)
            pi, ti = [], []
            try:
                for t in toks:
                    s = t.split("/")
                    pi.append(_fix(int(s[0]), nv, path, lineno, "vertex"))
                    if not positions_only:
                        ti.append(_fix(int(s[1]), nt, path, lineno, "texture coordinate")
                                  if len(s) > 1 and s[1] else -1)
            except ValueError as exc:
                if isinstance(exc, ObjError):
                    raise
                raise ObjError(f"{path}: line {lineno}: cannot read the face {line.strip()[:60]!r}") from None
            n_poly += 1
            n_quad += len(pi) == 4
            key = (cur_g, cur_o, cur_m)
            for k in range(1, len(pi) - 1):
                fpos.append((pi[0], pi[k], pi[k + 1]))
                if not positions_only:
                    fuv.append((ti[0], ti[k], ti[k + 1]))
                tri_poly.append(n_poly - 1)
                face_keys.append(key)
            continue
        if c0 in "gou":
            p = line.split(None, 1)
            name = p[1].strip() if len(p) > 1 else ""
            if p[0] == "g":
                cur_g = name or "default"
                g_names.setdefault(cur_g, None)
            elif p[0] == "o":
                cur_o = name or "default"
                o_names.setdefault(cur_o, None)
            elif p[0] == "usemtl":
                cur_m = name or "default"
                m_names.setdefault(cur_m, None)
    if not V or not fpos:
        raise ObjError(f"{path}: not a mesh ({len(V)} vertices, {len(fpos)} faces)")
    faces = np.asarray(fpos, np.int64)
    # which naming splits the file: g, else o, else usemtl
    keys = np.array([0] * len(face_keys))
    groups = ["mesh"]
    for slot, names in ((0, g_names), (1, o_names), (2, m_names)):
        used = {k[slot] for k in face_keys}
        if len(used) > 1:
            order = [n for n in names if n in used] + ([None] if None in used else [])
            index = {n: i for i, n in enumerate(order)}
            keys = np.array([index[k[slot]] for k in face_keys])
            groups = [n if n is not None else "default" for n in order]
            break
        if len(used) == 1 and None not in used:
            groups = [next(iter(used))]
    uvs = face_uvs = None
    if not positions_only and VT:
        uvs = np.asarray(VT, np.float64)
        face_uvs = np.asarray(fuv, np.int64)
    return ObjMesh(path, np.asarray(V, np.float64), faces, np.asarray(tri_poly, np.int64), uvs, face_uvs,
                   groups, keys.astype(np.int64), n_poly, n_quad)


# --------------------------------------------------------------------------------------------- UDIM
def udim_tiles(uv: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F,) UDIM tile number of each triangle (from its uv centroid): ``1001 + floor(u) + 10 floor(v)``."""
    c = uv[faces].mean(axis=1)
    iu = np.floor(c[:, 0]).astype(np.int64)
    iv = np.floor(c[:, 1]).astype(np.int64)
    return 1001 + iu + 10 * iv


def pack_udim(uv: np.ndarray, faces: np.ndarray, inset: float = 0.004):
    """Map the UDIM tiles used by ``faces`` (triangles of uv indices) into one [0, 1]² atlas.

    Returns ``(uv_packed (T, 2), layout)``: ``layout`` maps each tile number to its grid cell
    ``(column, row)`` in a ``g × g`` grid (``layout["grid"] = g``). A triangle's corners are mapped with
    the tile of its centroid, so a corner on a tile's edge (u = 1.0 exactly) stays in its tile.
    Single-tile layouts (every u, v in [0, 1]) come back unchanged with ``g = 1``.
    """
    tiles = udim_tiles(uv, faces)
    used = sorted(set(tiles.tolist()))
    g = int(np.ceil(np.sqrt(len(used))))
    layout = {"grid": g}
    for i, t in enumerate(used):
        layout[int(t)] = (i % g, i // g)
    if used == [1001]:
        return np.clip(uv, 0.0, 1.0), layout
    out = uv.copy()
    span = (1.0 - 2 * inset)
    for t in used:
        col, row = layout[int(t)]
        iu, iv = (t - 1001) % 10, (t - 1001) // 10
        tri = faces[tiles == t]
        idx = np.unique(tri)
        local = np.clip(uv[idx] - [iu, iv], 0.0, 1.0)
        out[idx] = (np.array([col, row]) + inset + span * local) / g
    return out, layout


def assemble_udim(layout: dict, images: dict, res: int, fill) -> np.ndarray:
    """One (res, res, 3) texture (the texel convention of :mod:`.textures`: row 0 is v ≈ 0) from
    per-tile images (``images[tile]`` (H, W, 3) linear, as image files store them: row 0 at the top,
    v = 1) laid out as :func:`pack_udim` placed their tiles; tiles without an image get ``fill`` (3,)."""
    g = layout["grid"]
    out = np.tile(np.asarray(fill, np.float32), (res, res, 1))
    inset = 0.004
    for t, (col, row) in ((k, v) for k, v in layout.items() if k != "grid"):
        img = images.get(t)
        if img is None:
            continue
        H0, W0 = img.shape[:2]
        # texel (r, c) of the atlas -> uv in the atlas -> local uv in the tile -> image pixel
        c0 = int(np.floor(col / g * res))
        c1 = int(np.ceil((col + 1) / g * res))
        r0 = int(np.floor(row / g * res))
        r1 = int(np.ceil((row + 1) / g * res))
        cc = np.arange(c0, min(c1, res))
        rr = np.arange(r0, min(r1, res))
        u = (cc + 0.5) / res * g - col          # texel row r is centred at v = (r + 1/2) / res
        v = (rr + 0.5) / res * g - row
        lu = np.clip((u - inset) / (1 - 2 * inset), 0.0, 1.0)
        lv = np.clip((v - inset) / (1 - 2 * inset), 0.0, 1.0)
        px = np.minimum((lu * W0).astype(int), W0 - 1)
        py = np.minimum(((1.0 - lv) * H0).astype(int), H0 - 1)   # image files: row 0 is v = 1
        out[rr[:, None], cc[None, :]] = img[py[:, None], px[None, :], :3]
    return out


def read_positions(path):
    """``(positions (V, 3), digest of the face lines)`` of an OBJ file, fast (for blendshape files,
    whose faces must equal the neutral's: equal digests mean equal faces; on a mismatch, compare
    :func:`read_obj` ``(path, positions_only=True).faces``)."""
    import hashlib

    path = Path(path)
    try:
        text = path.read_text(errors="replace")
    except OSError as exc:
        raise ObjError(f"{path}: cannot read ({exc.strerror or exc})") from exc
    lines = text.splitlines()
    vl = [ln[2:] for ln in lines if ln.startswith("v ")]
    try:
        P = np.array(" ".join(vl).split(), np.float64)
        P = P.reshape(len(vl), -1)[:, :3]
    except ValueError:
        return read_obj(path, positions_only=True).positions, None
    h = hashlib.sha1("\n".join(ln.strip() for ln in lines if ln.startswith("f ")).encode()).hexdigest()
    return P, h


def face_digest(path) -> str:
    return read_positions(path)[1]
