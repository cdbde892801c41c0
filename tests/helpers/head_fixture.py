"""A small production-style head the tests build themselves (nothing shipped): one OBJ in centimetres,
+Y up, looking along +Z, with named groups (``g``), quads and triangles, per-corner UVs with seams,
UDIM tiles (the face in 1001, the back of the head in 1002), eyeballs, teeth, a mouth socket and
eyelashes, plus ARKit-named expression OBJs of the same topology and UDIM albedo tiles.

    folder = write_head(tmp_path)                      # neutral.obj, jawOpen.obj, ..., albedo.1001.png, subject.json

The skin is an ellipsoid (7.5 × 11 × 9 cm half axes) with a mouth slot and two eye openings; the
albedo's face tile is red on the subject's left (+X) and blue on its right, so a test can check
that the user's texture is used as given.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

AXES = np.array([7.5, 11.0, 9.0])          # cm
EYE_X, EYE_Y = 3.1, 1.5
MOUTH_Y = -4.8
EYE_R = 1.2


def _sphere(sub):
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=sub, radius=1.0)
    return np.asarray(m.vertices), np.asarray(m.faces)


def _surface_z(x, y):
    return AXES[2] * np.sqrt(max(1e-9, 1 - (x / AXES[0]) ** 2 - (y / AXES[1]) ** 2))


def head_parts(sub: int = 4):
    """{group: (V (n, 3) cm, polygons list of index lists)} and the vertex array they index."""
    Vs, Fs = _sphere(sub)
    V = Vs * AXES
    C = V[Fs].mean(axis=1)
    front = C[:, 2] > 0
    cut = np.zeros(len(Fs), bool)
    for sx in (1, -1):                                                 # eye openings
        cut |= front & (((C[:, 0] - sx * EYE_X) / 1.25) ** 2 + ((C[:, 1] - EYE_Y) / 0.55) ** 2 < 1)
    cut |= front & (np.abs(C[:, 0]) < 2.3) & (np.abs(C[:, 1] - MOUTH_Y) < 0.35)   # the mouth slot
    neck = C[:, 1] < -10.2                                             # an open neck
    keep = ~cut & ~neck
    groups = {"Face": Fs[keep & front], "Head and Neck": Fs[keep & ~front]}
    verts = [V]
    n = len(V)

    def add(name, P, F):
        nonlocal n
        verts.append(P)
        groups[name] = [list(f) for f in (np.asarray(F) + n)] if not isinstance(F, list) else [
            [i + n for i in f] for f in F]
        n += len(P)

    ev, ef = _sphere(2)
    for name, sx in (("Eyeball left", 1), ("Eyeball right", -1)):
        c = np.array([sx * EYE_X, EYE_Y, _surface_z(sx * EYE_X, EYE_Y) - 0.9 * EYE_R])
        add(name, ev * EYE_R + c, ef)
    # teeth: one box per tooth (quads), an upper and a lower row
    box = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
    quads = [[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]]
    tv, tq = [], []
    for yoff in (0.45, -0.45):
        for k in range(-3, 4):
            c = np.array([0.55 * k, MOUTH_Y + yoff, _surface_z(0.55 * k, MOUTH_Y) - 0.9 - 0.05 * k * k])
            base = len(tv) * 8
            tv.append(box * [0.24, 0.38, 0.3] + c)
            tq += [[base + i for i in q] for q in quads]
    add("Teeth", np.concatenate(tv), tq)
    sv, sf = _sphere(2)
    add("Mouth socket", sv * [2.0, 1.0, 1.6] + [0.0, MOUTH_Y, _surface_z(0, MOUTH_Y) - 2.6], sf)
    lash = np.array([[x, EYE_Y + 0.6, 0.0] for x in np.linspace(-1.0, 1.0, 5)] +
                    [[x, EYE_Y + 0.8, 0.3] for x in np.linspace(-1.0, 1.0, 5)])
    for sx in (1, -1):
        P = lash.copy()
        P[:, 0] = P[:, 0] + sx * EYE_X
        P[:, 2] = _surface_z(sx * EYE_X, EYE_Y + 0.6) + P[:, 2]
        add("Eyelashes " + ("left" if sx > 0 else "right"), P, [[i, i + 1, i + 6, i + 5] for i in range(4)])
    return np.concatenate(verts), {k: [list(map(int, f)) for f in v] for k, v in groups.items()}


def _uv_of(P, group):
    """UV of a position for a skin group: the face in tile 1001 (planar), the head in 1002 (cylindrical)."""
    if group == "Face":
        return np.stack([0.5 + P[:, 0] / 16.0, 0.5 + P[:, 1] / 24.0], 1)
    az = np.arctan2(P[:, 0], P[:, 2])
    az = np.where(az < 0, az + 2 * np.pi, az)
    return np.stack([1.0 + 0.02 + 0.96 * az / (2 * np.pi), 0.02 + 0.96 * (P[:, 1] + 11.0) / 22.0], 1)


def write_obj(path, V, groups, uv: bool = True):
    """One OBJ: ``v`` for every position, then per group ``g`` and faces (skin faces with per-corner
    ``vt``: seams where the face and head groups meet)."""
    lines = ["# mifacerf test head (cm, +Y up, looking along +Z)"]
    lines += [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in V]
    vt_lines, body, vt_of = [], [], {}
    for name, polys in groups.items():
        body.append(f"g {name}")
        skin = name in ("Face", "Head and Neck")
        for f in polys:
            if skin and uv:
                ts = _uv_of(V[f], name)
                idx = []
                for v, t in zip(f, ts):                   # one vt per (position, group): seams between groups
                    if (v, name) not in vt_of:
                        vt_lines.append(f"vt {t[0]:.6f} {t[1]:.6f}")
                        vt_of[(v, name)] = len(vt_lines)
                    idx.append(vt_of[(v, name)])
                body.append("f " + " ".join(f"{v + 1}/{t}" for v, t in zip(f, idx)))
            else:
                body.append("f " + " ".join(str(v + 1) for v in f))
    Path(path).write_text("\n".join(lines + vt_lines + body) + "\n")


def expressions(V, groups, jaw_cm: float = 0.9, jaw_deg: float = 0.0):
    """{name: V'} ARKit-named shapes: jawOpen (chin, lower lip and lower teeth ``jaw_cm`` down, and the chin
    turned ``jaw_deg`` down and back about a hinge behind the mouth), mouthSmile_L,
    eyeLookUp_L (both eyeballs turn up 15 degrees)."""
    out = {}
    face_v = np.unique([i for k in ("Face", "Head and Neck") for f in groups[k] for i in f])
    Vf = V[face_v]
    jaw = V.copy()
    w = np.clip((MOUTH_Y - 0.2 - Vf[:, 1]) / 3.0, 0, 1) * (Vf[:, 2] > -2)
    jaw[face_v, 1] -= jaw_cm * w
    if jaw_deg:
        a = np.radians(jaw_deg) * w * np.clip((Vf[:, 1] + 10.2) / 3.0, 0, 1)     # the neck's end stays
        y, z = Vf[:, 1] - MOUTH_Y, Vf[:, 2] + 2.0
        jaw[face_v, 1] = MOUTH_Y + y * np.cos(a) - z * np.sin(a) - jaw_cm * w
        jaw[face_v, 2] = -2.0 + y * np.sin(a) + z * np.cos(a)
    teeth = np.unique([i for f in groups["Teeth"] for i in f])
    low = teeth[V[teeth, 1] < MOUTH_Y]
    jaw[low, 1] -= jaw_cm
    out["jawOpen"] = jaw
    sm = V.copy()
    g = np.exp(-((Vf[:, 1] - MOUTH_Y) / 1.5) ** 2) * (Vf[:, 0] > 0) * (Vf[:, 2] > 0)
    sm[face_v, 0] += 0.5 * g * Vf[:, 0] / 7.5
    sm[face_v, 1] += 0.3 * g
    out["mouthSmile_L"] = sm
    up = V.copy()
    a = np.radians(15.0)
    R = np.array([[1, 0, 0], [0, np.cos(a), np.sin(a)], [0, -np.sin(a), np.cos(a)]])
    for k in ("Eyeball left", "Eyeball right"):
        ids = np.unique([i for f in groups[k] for i in f])
        c = V[ids].mean(axis=0)
        up[ids] = (V[ids] - c) @ R.T + c
    out["eyeLookUp_L"] = up
    return out


def albedo_tiles(size: int = 64):
    """{1001: red (+X half) / blue, 1002: grey} 8-bit sRGB images (row 0 = top = v 1)."""
    face = np.zeros((size, size, 3), np.uint8)
    face[:, size // 2:, 0] = 200                  # u > 0.5: the subject's left (+X): red
    face[:, : size // 2, 2] = 200                 # blue
    head = np.full((size, size, 3), 120, np.uint8)
    return {1001: face, 1002: head}


def write_head(folder, sub: int = 4, albedo: bool = True, manifest: dict | None = None, jaw_cm: float = 0.9,
               jaw_deg: float = 0.0) -> Path:
    """Write the whole subject folder (``jaw_cm``, ``jaw_deg``: how jawOpen moves the chin); returns it."""
    import imageio.v3 as iio

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    V, groups = head_parts(sub)
    write_obj(folder / "neutral.obj", V, groups)
    for name, Vx in expressions(V, groups, jaw_cm, jaw_deg).items():
        write_obj(folder / f"{name}.obj", Vx, groups)
    if albedo:
        for t, img in albedo_tiles().items():
            iio.imwrite(folder / f"albedo.{t}.png", img)
    man = {"scale": 0.01}
    man.update(manifest or {})
    (folder / "subject.json").write_text(json.dumps(man))
    return folder
