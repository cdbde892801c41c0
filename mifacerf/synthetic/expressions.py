"""Expression controls of the procedural head and the deformation they drive.

An expression is a parameter vector over :data:`CONTROLS` (named, documented, blendshape-like
controls). :class:`SkinRig` turns a vector into skin vertex positions and the rigid transforms of
the eyes, the teeth and the head, in four stages:

1. **local fields** (linear, like blendshapes): every facial control owns a smooth displacement
   field over the rest skin; the fields of the active controls are summed;
2. **eyelids**: vertices round each eye turn about the eyeball centre (upper lid up, lower lid
   down) by an angle that is largest on the lid margin, vanishes at the eye corners and fades
   smoothly upwards into the brow / downwards into the cheek (the rest shape has the lids shut; the
   neutral expression opens them); the margins curl in onto the eyeball as they open;
3. **jaw**: the lower face turns about the hinge axis (X through :data:`~.head.JAW_HINGE`) and about
   a vertical axis (sideways), weighted by a jaw-membership field that is 1 on the lower lip and chin,
   0 on the upper lip (the mouth slit separates them) and fades smoothly over the cheeks and the neck;
   the lip margins then curl inwards in proportion to how far the lips are apart;
4. **head pose**: yaw / pitch / roll about :data:`~.head.NECK_PIVOT`, applied fully to the head and
   blended down the neck (the neck base never moves).

Every field is smooth, bounded in gradient and zero at the slit corners where it would tear, so any
vector inside the ranges (and somewhat beyond) gives a fold-free mesh (tested).

Sign conventions (head frame = world at the neutral head pose, ``docs/conventions.md``): ``_L`` is
the subject's left (+X). ``head_yaw > 0`` turns the face towards +X, ``head_pitch > 0`` tilts the face
up, ``head_roll > 0`` tilts the crown towards +X. ``gaze_yaw > 0`` looks towards +X, ``gaze_pitch > 0``
looks up. ``jaw_sideways > 0`` moves the chin towards +X. Angles in radians.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from ..geometry.rigid import apply
from . import head as H


class Control(NamedTuple):
    name: str
    lo: float
    hi: float
    default: float
    description: str


CONTROLS: tuple[Control, ...] = (
    Control("brow_raise_L", 0.0, 1.0, 0.0, "raise the left brow (~7 mm); compresses the forehead"),
    Control("brow_raise_R", 0.0, 1.0, 0.0, "raise the right brow (~7 mm); compresses the forehead"),
    Control("brow_lower_L", 0.0, 1.0, 0.0, "lower the left brow (~3 mm) towards the eye"),
    Control("brow_lower_R", 0.0, 1.0, 0.0, "lower the right brow (~3 mm) towards the eye"),
    Control("frown", 0.0, 1.0, 0.0, "pull the inner brows together and down (corrugator): glabella lines"),
    Control("smile_L", 0.0, 1.0, 0.0, "pull the left mouth corner up and back, raise the cheek"),
    Control("smile_R", 0.0, 1.0, 0.0, "pull the right mouth corner up and back, raise the cheek"),
    Control("lip_corner_down", 0.0, 1.0, 0.0, "pull both mouth corners down (sad / disgust)"),
    Control("upper_lip_raise", 0.0, 1.0, 0.0, "raise the upper lip, baring the upper teeth"),
    Control("lower_lip_down", 0.0, 1.0, 0.0, "pull the lower lip down, baring the lower teeth"),
    Control("pucker", 0.0, 1.0, 0.0, "push the lips forwards and narrow the mouth (kiss, /w/, /oo/)"),
    Control("funnel", 0.0, 1.0, 0.0, "flare and round the lips outwards, slightly open (/sh/, /oo/)"),
    Control("lips_press", 0.0, 1.0, 0.0, "press the lips together and thin them (/p,b,m/)"),
    Control("lips_roll_in", 0.0, 1.0, 0.0, "roll both lips inwards over the teeth"),
    Control("lower_lip_tuck", 0.0, 1.0, 0.0, "tuck the lower lip up and back under the upper teeth (/f,v/)"),
    Control("mouth_stretch", 0.0, 1.0, 0.0, "stretch the mouth corners sideways and down (fear, /ee/)"),
    Control("cheek_raise_L", 0.0, 1.0, 0.0, "raise the left cheek and squint the lower lid (crow's feet)"),
    Control("cheek_raise_R", 0.0, 1.0, 0.0, "raise the right cheek and squint the lower lid (crow's feet)"),
    Control("nose_wrinkle", 0.0, 1.0, 0.0, "wrinkle the nose: raise the alae, bunch the bridge skin"),
    Control("jaw_open", 0.0, 0.36, 0.0, "open the jaw: rotation about the hinge axis near the ears (rad)"),
    Control("jaw_sideways", -0.08, 0.08, 0.0, "slide the jaw sideways: rotation about a vertical axis (rad, + = chin to +X)"),
    Control("blink_L", 0.0, 1.0, 0.0, "close the left eyelids (1 = shut)"),
    Control("blink_R", 0.0, 1.0, 0.0, "close the right eyelids (1 = shut)"),
    Control("eyes_wide", 0.0, 1.0, 0.0, "open both eyes wide (sclera above the iris)"),
    Control("gaze_yaw", -0.45, 0.45, 0.0, "turn both eyeballs about the vertical (rad, + = look to +X)"),
    Control("gaze_pitch", -0.35, 0.35, 0.0, "turn both eyeballs up / down (rad, + = look up); the lids follow"),
    Control("head_yaw", -0.60, 0.60, 0.0, "turn the head about the neck (rad, + = face towards +X)"),
    Control("head_pitch", -0.35, 0.35, 0.0, "nod the head about the neck (rad, + = face up)"),
    Control("head_roll", -0.30, 0.30, 0.0, "tilt the head about the neck (rad, + = crown towards +X)"),
)
CONTROL_NAMES = tuple(c.name for c in CONTROLS)
CONTROL_INDEX = {c.name: i for i, c in enumerate(CONTROLS)}

#: controls realised as linear displacement fields (stage 1)
LINEAR_CONTROLS = (
    "brow_raise_L", "brow_raise_R", "brow_lower_L", "brow_lower_R", "frown", "smile_L", "smile_R",
    "lip_corner_down", "upper_lip_raise", "lower_lip_down", "pucker", "funnel", "lips_press",
    "lips_roll_in", "lower_lip_tuck", "mouth_stretch", "cheek_raise_L", "cheek_raise_R",
    "nose_wrinkle", "eyes_wide",
)

# lid opening angles (rad) at the middle of the margin for the neutral face
LID_UP_NEUTRAL = 0.41
LID_LO_NEUTRAL = 0.28


def default_params() -> np.ndarray:
    return np.array([c.default for c in CONTROLS], float)


# --------------------------------------------------------------------------------------------
# small helpers
# --------------------------------------------------------------------------------------------
def gauss(u):
    return np.exp(-0.5 * u * u)


def smoothstep(e0, e1, x):
    t = np.clip((x - e0) / (e1 - e0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def soft_ramp(u):
    """1 at u <= 0 falling to 0 at u >= 1, nearly linear in between (max slope ~1.1)."""
    u = np.clip(u, 0.0, 1.0)
    # linear with quadratic blends over the first and last 10 %
    a = 0.1
    k = 1.0 / (1.0 - a)
    v = np.where(u < a, 1.0 - k * u * u / (2 * a),
                 np.where(u > 1 - a, k * (1 - u) ** 2 / (2 * a), 1.0 - k * (u - a / 2)))
    return np.clip(v, 0.0, 1.0)


def rodrigues(axis, angle):
    """Rotation matrices (..., 3, 3) about unit ``axis`` (..., 3) by ``angle`` (...)."""
    axis = np.asarray(axis, float)
    angle = np.asarray(angle, float)
    k = axis
    c = np.cos(angle)[..., None, None]
    s = np.sin(angle)[..., None, None]
    K = np.zeros(k.shape[:-1] + (3, 3))
    K[..., 0, 1] = -k[..., 2]
    K[..., 0, 2] = k[..., 1]
    K[..., 1, 0] = k[..., 2]
    K[..., 1, 2] = -k[..., 0]
    K[..., 2, 0] = -k[..., 1]
    K[..., 2, 1] = k[..., 0]
    I = np.eye(3)
    return I + s * K + (1 - c) * (K @ K)


def euler_head(yaw, pitch, roll):
    """Head rotation: R = R_y(yaw) · R_x(−pitch) · R_z(−roll) (see the module's sign conventions)."""
    return H.rot_y(yaw) @ H.rot_x(-pitch) @ H.rot_z(-roll)


def affine(R, pivot):
    """4x4 transform rotating by R about ``pivot``."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = pivot - R @ pivot
    return T


# --------------------------------------------------------------------------------------------
# rig
# --------------------------------------------------------------------------------------------
@dataclass
class RigState:
    """Output of :meth:`SkinRig.deform`."""
    vertices: np.ndarray            # (V, 3) skin, world
    head: np.ndarray                # (4, 4) head frame -> world
    jaw: np.ndarray                 # (4, 4) rest lower-jaw frame -> world (includes the head)
    eyes: dict                      # 'eye_left' / 'eye_right' -> (4, 4) eyeball rest -> world
    lid_angles: dict                # 'eye_left' -> (upper, lower) margin angles (rad)
    mouth_opening: np.ndarray       # (n_slit,) distance between the lip margins (m)
    head_frame_vertices: np.ndarray  # (V, 3) skin before the head pose (head frame)


class SkinRig:
    """Precomputed deformation model over a :class:`~.head.SkinGrid`."""

    def __init__(self, grid: H.SkinGrid):
        self.grid = grid
        V0 = grid.vertices
        self.rest = V0
        n = len(V0)
        rc = grid.vertex_rc
        x, y, z = V0[:, 0], V0[:, 1], V0[:, 2]
        ax = np.abs(x)

        # ---- mouth sides -------------------------------------------------------------------
        ms = grid.slits["mouth"]
        self.mouth = ms
        row = rc[:, 0]
        side = np.where(row < ms.row, 1.0, np.where(row > ms.row, -1.0, 0.0))
        side[ms.upper] = 1.0
        side[ms.lower] = -1.0
        hw = 0.5 * (abs(V0[ms.corners[0], 0]) + abs(V0[ms.corners[1], 0]))
        self.mouth_half_width = hw
        eta = y - H.Y_MOUTH
        on_row = row == ms.row
        Pm = np.clip(1.0 - (x / hw) ** 2, 0.0, None) ** 0.6
        w1 = 0.003 + 0.02 * smoothstep(hw, 2.2 * hw, ax)
        M = 1.0 - (1.0 - Pm) * np.clip(1.0 - np.abs(eta) / (3.0 * w1), 0.0, 1.0) ** 2   # compact
        M = np.where(on_row & (side == 0), 0.0, M)
        self.S_up = 0.5 + 0.5 * side * M
        self.S_lo = 1.0 - self.S_up
        self.eta_m = eta

        # ---- linear fields -----------------------------------------------------------------
        B = {}
        front = smoothstep(-0.005, 0.035, z)
        corner_L = np.array([hw, H.Y_MOUTH, float(V0[ms.corners[1], 2])])

        def brow_region(sgn):
            return gauss((x - sgn * 0.030) / 0.020) * smoothstep(-0.004, 0.010, sgn * x) * front

        for sgn, sfx in ((1.0, "L"), (-1.0, "R")):
            reg = brow_region(sgn)
            # raise: rises from the upper lid to the brow, fades over the forehead
            h = smoothstep(0.011, 0.023, y) * (1.0 - 0.75 * smoothstep(0.030, 0.080, y))
            d = np.zeros((n, 3))
            d[:, 1] = 0.0070 * reg * h
            d[:, 2] = 0.0010 * reg * h
            B[f"brow_raise_{sfx}"] = d
            # lower: peaks at the brow, fades to the slit and up the forehead
            # (starts above the shut-lid sphere: the lid itself is moved by the lid rotation)
            h2 = smoothstep(0.015, 0.030, y) * (1.0 - smoothstep(0.034, 0.070, y))
            d = np.zeros((n, 3))
            d[:, 1] = -0.0040 * reg * h2
            d[:, 0] = -sgn * 0.0012 * reg * h2
            d[:, 2] = 0.0008 * reg * h2
            B[f"brow_lower_{sfx}"] = d

        # frown: inner brows together and down
        fy = gauss((y - 0.020) / 0.011) * front
        d = np.zeros((n, 3))
        s_ = 0.014
        d[:, 0] = -0.0030 * (x / s_) * np.exp(0.5 * (1.0 - (x / s_) ** 2)) * fy
        d[:, 1] = -0.0020 * gauss(x / 0.018) * fy * smoothstep(H.Y_EYE, 0.015, y)
        B["frown"] = d

        # smiles
        for sgn, sfx in ((1.0, "L"), (-1.0, "R")):
            c = corner_L * np.array([sgn, 1, 1])
            r = V0 - c
            # anisotropic falloff: longer towards the cheek (up and out)
            u = np.sqrt((r[:, 0] * sgn / 0.018) ** 2 + (r[:, 1] / 0.017) ** 2 + (r[:, 2] / 0.02) ** 2)
            g = gauss(u) * front
            d = np.zeros((n, 3))
            d[:, 0] = sgn * 0.0055 * g
            d[:, 1] = 0.0065 * g
            d[:, 2] = -0.0035 * g
            # cheek bulge (lateral to the nasolabial fold)
            cc = np.array([sgn * 0.036, -0.030, 0.0])
            gc = gauss(np.sqrt(((x - cc[0]) / 0.016) ** 2 + ((y - cc[1]) / 0.016) ** 2)) * front
            d[:, 1] += 0.0035 * gc
            d[:, 2] += 0.0025 * gc
            B[f"smile_{sfx}"] = d

        d = np.zeros((n, 3))
        for sgn in (1.0, -1.0):
            c = corner_L * np.array([sgn, 1, 1])
            u = np.linalg.norm((V0 - c) / np.array([0.015, 0.014, 0.02]), axis=1)
            g = gauss(u) * front
            d[:, 0] += sgn * 0.0010 * g
            d[:, 1] += -0.0050 * g
            d[:, 2] += -0.0010 * g
        B["lip_corner_down"] = d

        lipx = gauss(x / 0.017) * front
        # side-dependent (opening) fields vanish towards the mouth corners
        taper = smoothstep(1.05 * hw, 0.55 * hw, ax)
        lipo = lipx * taper
        h_up = np.where(eta > 0.0, soft_ramp((eta - 0.006) / 0.016), 1.0)
        d = np.zeros((n, 3))
        d[:, 1] = 0.0045 * self.S_up * lipo * h_up
        d[:, 2] = 0.0012 * self.S_up * lipo * h_up
        # alae lift a little
        al = gauss(np.sqrt(((ax - 0.013) / 0.008) ** 2 + ((y + 0.040) / 0.008) ** 2)) * front
        d[:, 1] += 0.0012 * al
        B["upper_lip_raise"] = d

        h_lo = np.where(eta < 0.0, soft_ramp((-eta - 0.008) / 0.022), 1.0)
        d = np.zeros((n, 3))
        d[:, 1] = -0.0050 * self.S_lo * lipo * h_lo
        d[:, 2] = 0.0015 * self.S_lo * lipo * h_lo
        B["lower_lip_down"] = d

        L = gauss(x / 0.026) * gauss(eta / 0.013) * front
        Lc = gauss(x / 0.020) * gauss(eta / 0.007) * front
        d = np.zeros((n, 3))
        d[:, 0] = -0.33 * x * L
        d[:, 2] = 0.0045 * L + 0.0020 * Lc
        B["pucker"] = d

        d = np.zeros((n, 3))
        d[:, 0] = -0.15 * x * L
        d[:, 2] = 0.0040 * L
        op = gauss(x / 0.015) * gauss(eta / 0.008) * front * taper
        d[:, 1] += (0.0030 * self.S_up - 0.0035 * self.S_lo) * op
        d[:, 2] += 0.0015 * op
        B["funnel"] = d

        d = np.zeros((n, 3))
        lp = gauss(x / 0.020) * gauss(eta / 0.008) * front
        d[:, 1] = -0.35 * eta * lp
        d[:, 2] = -0.0025 * lp
        B["lips_press"] = d

        d = np.zeros((n, 3))
        lr = gauss(x / 0.020) * np.exp(-(eta / 0.006) ** 2) * front
        d[:, 1] = -0.30 * eta * lr
        d[:, 2] = -0.0045 * lr
        B["lips_roll_in"] = d

        d = np.zeros((n, 3))
        tx = gauss(x / 0.018) * front * taper
        tl = self.S_lo * tx * np.where(eta < 0, soft_ramp((-eta - 0.004) / 0.020), 1.0)
        d[:, 1] = 0.0025 * tl
        d[:, 2] = -0.0055 * tl
        tu = self.S_up * tx * np.where(eta > 0, soft_ramp((eta - 0.003) / 0.012), 1.0)
        d[:, 1] += 0.0015 * tu
        B["lower_lip_tuck"] = d

        d = np.zeros((n, 3))
        for sgn in (1.0, -1.0):
            c = corner_L * np.array([sgn, 1, 1])
            g = gauss(np.linalg.norm((V0 - c) / np.array([0.017, 0.016, 0.02]), axis=1)) * front
            d[:, 0] += sgn * 0.0050 * g
            d[:, 1] += -0.0025 * g
            d[:, 2] += -0.0020 * g
        d[:, 1] += -0.0015 * self.S_lo * lipo * h_lo
        B["mouth_stretch"] = d

        for sgn, sfx in ((1.0, "L"), (-1.0, "R")):
            d = np.zeros((n, 3))
            g = gauss(np.sqrt(((x - sgn * 0.040) / 0.016) ** 2 + ((y + 0.014) / 0.015) ** 2)) * front
            # the lower lid itself rises by the lid rotation (see lid_angles); fade the push below it
            ce_ = H.EYE_CENTRE * np.array([sgn, 1, 1])
            g = g * smoothstep(H.LID_RADIUS + 0.001, H.LID_RADIUS + 0.009, np.linalg.norm(V0 - ce_, axis=1))
            d[:, 1] = 0.0036 * g
            d[:, 2] = 0.0012 * g
            # circumferential squeeze lateral to the eye (orbicularis): crow's feet
            lat = smoothstep(0.040, 0.050, sgn * x) * gauss((sgn * x - 0.056) / 0.012)
            d[:, 1] += -0.25 * (y - H.Y_EYE) * lat * gauss((y - H.Y_EYE) / 0.013)
            B[f"cheek_raise_{sfx}"] = d

        d = np.zeros((n, 3))
        nose = gauss(x / 0.012) * front
        d[:, 1] = 0.0030 * nose * smoothstep(0.014, -0.012, y) * smoothstep(-0.050, -0.035, y)
        al = gauss(np.sqrt(((ax - 0.012) / 0.009) ** 2 + ((y + 0.038) / 0.009) ** 2)) * front
        d[:, 1] += 0.0022 * al
        d[:, 1] += 0.0012 * self.S_up * lipo * h_up
        B["nose_wrinkle"] = d

        d = np.zeros((n, 3))
        for sgn in (1.0, -1.0):
            d[:, 1] += 0.0020 * brow_region(sgn) * smoothstep(0.011, 0.023, y) * (
                1.0 - 0.75 * smoothstep(0.030, 0.080, y))
        B["eyes_wide"] = d

        self.linear_names = LINEAR_CONTROLS
        self.linear_index = np.array([CONTROL_INDEX[k] for k in LINEAR_CONTROLS])
        self.basis = np.stack([B[k] for k in LINEAR_CONTROLS], 0)  # (K, V, 3)
        # only vertices that any field moves are updated (speed)
        self.basis_support = np.nonzero(np.abs(self.basis).max(axis=(0, 2)) > 1e-9)[0]
        self.basis_sub = np.ascontiguousarray(self.basis[:, self.basis_support].reshape(len(B), -1))

        # ---- eyelids -----------------------------------------------------------------------
        self.eye = {}
        for name, sgn in (("eye_left", 1.0), ("eye_right", -1.0)):
            es = grid.slits[name]
            ce = H.EYE_CENTRE * np.array([sgn, 1, 1])
            rel = V0 - ce
            # position along the slit from the grid column (0 at the medial corner, 1 lateral):
            # columns, not eye-centred angles, so the nose side never joins the lid motion
            col = rc[:, 1]
            t = (col - es.c0) / (es.c1 - es.c0)
            if sgn < 0:   # the right eye's medial corner is its larger column
                t = 1.0 - t
            inside = (t > 0.0) & (t < 1.0) & (rel[:, 2] > -0.004) & (rc[:, 0] >= 0)
            t = np.clip(t, 0.0, 1.0)
            P_up = np.where(inside, np.sin(np.pi * t ** 0.87), 0.0)
            P_lo = np.where(inside, np.sin(np.pi * t ** 1.15), 0.0)
            row = rc[:, 0]
            eside = np.where(row < es.row, 1.0, np.where(row > es.row, -1.0, 0.0))
            eside[es.upper] = 1.0
            eside[es.lower] = -1.0
            eta_e = y - H.Y_EYE
            g_up = soft_ramp(eta_e / 0.020) * (eside > 0)
            g_lo = soft_ramp(-eta_e / 0.014) * (eside < 0)
            # keep the motion on the front of the face, near this eye
            near = smoothstep(0.040, 0.030, np.linalg.norm(rel, axis=1))
            w_up = P_up * g_up * near
            w_lo = P_lo * g_lo * near
            curl = np.exp(-(eta_e / 0.0010) ** 2) * near * (eside != 0)
            idx = np.nonzero((w_up > 1e-6) | (w_lo > 1e-6) | (curl * np.maximum(P_up, P_lo) > 1e-6))[0]
            # skin lying on the lid sphere is kept outside it when other fields push it inwards
            rho = np.linalg.norm(rel, axis=1)
            w_col = smoothstep(H.LID_RADIUS + 0.006, H.LID_RADIUS + 0.0015, rho) * (rel[:, 2] > -0.004)
            cidx = np.nonzero(w_col > 1e-6)[0]
            self.eye[name] = dict(centre=ce, idx=idx, w_up=w_up[idx], w_lo=w_lo[idx],
                                  curl=curl[idx], P_up=P_up[idx], P_lo=P_lo[idx], side=eside[idx],
                                  sgn=sgn, slit=es, col_idx=cidx, col_w=w_col[cidx])

        # ---- jaw -----------------------------------------------------------------------------
        q = y + 0.46 * (z - 0.06) + 0.12          # > 0 above the line under the jaw
        J = smoothstep(-0.065, 0.002, q) * smoothstep(-0.050, 0.020, z)
        self.w_jaw = self.S_lo * J
        self.jaw_idx = np.nonzero(self.w_jaw > 1e-6)[0]
        # lip-margin curl: where and how much
        self.curl_idx = np.nonzero((np.abs(eta) < 0.006) & (ax < hw + 0.004) & (z > 0.04))[0]
        self.curl_w = np.exp(-(eta[self.curl_idx] / 0.0016) ** 2)
        self.slit_x_up = V0[ms.upper, 0]

        # ---- head pose -----------------------------------------------------------------------
        self.w_head = smoothstep(-0.105, -0.012, q) * smoothstep(H.NECK_BASE_Y + 0.002, H.NECK_BASE_Y + 0.04, y)
        self.w_head[grid.cap_centre] = 0.0

    # ------------------------------------------------------------------------------------------
    def lid_angles(self, p: np.ndarray, side: str):
        g = lambda k: p[CONTROL_INDEX[k]]
        s = "L" if side == "eye_left" else "R"
        blink = np.clip(g(f"blink_{s}"), 0.0, 1.0)
        wide = g("eyes_wide")
        sq = g(f"cheek_raise_{s}")
        gp = g("gaze_pitch")
        up = max(0.0, LID_UP_NEUTRAL + 0.25 * wide - 0.06 * sq + 0.55 * gp) * (1.0 - blink)
        lo = max(0.0, LID_LO_NEUTRAL + 0.08 * wide - 0.17 * sq - 0.35 * gp) * (1.0 - blink)
        return up, lo

    def deform(self, params: np.ndarray) -> RigState:
        p = np.asarray(params, float)
        V = self.rest.copy()
        # 1. linear fields
        w = p[self.linear_index]
        if np.any(w != 0):
            D = np.zeros_like(V)
            D[self.basis_support] = (w @ self.basis_sub).reshape(-1, 3)
            # skin on the lid spheres slides over them: drop the inward radial part
            for e in self.eye.values():
                ci = e["col_idx"]
                r = self.rest[ci] - e["centre"]
                r /= np.linalg.norm(r, axis=1, keepdims=True)
                dr = np.einsum("ij,ij->i", D[ci], r)
                D[ci] -= (e["col_w"] * np.minimum(dr, 0.0))[:, None] * r
            V += D

        # 2. eyelids (first keep the lid skin outside the lid sphere: a soft collision)
        lid = {}
        for name, e in self.eye.items():
            ci = e["col_idx"]
            Q = V[ci] - e["centre"]
            r = np.linalg.norm(Q, axis=1)
            k = 0.0003
            push = k * np.logaddexp(0.0, (H.LID_RADIUS - r) / k) - k * np.log(2.0)
            push = np.maximum(push, 0.0) * e["col_w"]
            V[ci] = e["centre"] + Q * ((r + push) / np.maximum(r, 1e-12))[:, None]
        for name, e in self.eye.items():
            up, lo = self.lid_angles(p, name)
            lid[name] = (up, lo)
            idx = e["idx"]
            Q = V[idx] - e["centre"]
            dang = up * e["w_up"] - lo * e["w_lo"]
            # rotate towards / away from +Y about the axis perpendicular to the radial direction
            horiz = Q.copy()
            horiz[:, 1] = 0.0
            axis = np.cross(horiz, np.array([0.0, 1.0, 0.0]))
            nrm = np.linalg.norm(axis, axis=1, keepdims=True)
            axis = axis / np.maximum(nrm, 1e-12)
            Rm = rodrigues(axis, dang)
            Q = np.einsum("nij,nj->ni", Rm, Q)
            # margin curl onto the eyeball as the lid opens
            opening = np.where(e["side"] > 0, up * e["P_up"], lo * e["P_lo"])
            inset = (H.LID_RADIUS - H.EYE_RADIUS + 0.0004) * smoothstep(0.0, 0.12, opening) * e["curl"]
            r = np.linalg.norm(Q, axis=1, keepdims=True)
            Q = Q * (1.0 - inset[:, None] / np.maximum(r, 1e-9))
            V[idx] = Q + e["centre"]

        # 3. jaw
        jaw_open = p[CONTROL_INDEX["jaw_open"]]
        jaw_side = p[CONTROL_INDEX["jaw_sideways"]]
        T_jaw = affine(H.rot_x(jaw_open), H.JAW_HINGE) @ affine(H.rot_y(jaw_side), H.JAW_HINGE)
        if jaw_open != 0 or jaw_side != 0:
            idx = self.jaw_idx
            wj = self.w_jaw[idx]
            Q = V[idx] - H.JAW_HINGE
            Ry = rodrigues(np.tile([0.0, 1.0, 0.0], (len(idx), 1)), wj * jaw_side)
            Rx = rodrigues(np.tile([1.0, 0.0, 0.0], (len(idx), 1)), wj * jaw_open)
            Q = np.einsum("nij,nj->ni", Rx, np.einsum("nij,nj->ni", Ry, Q))
            V[idx] = Q + H.JAW_HINGE
        # lip margins curl inwards in proportion to the opening
        ms = self.mouth
        gap = np.linalg.norm(V[ms.upper] - V[ms.lower], axis=1)
        if np.any(gap > 1e-7):
            xs = np.concatenate([[-self.mouth_half_width], self.slit_x_up, [self.mouth_half_width]])
            gs = np.concatenate([[0.0], gap, [0.0]])
            order = np.argsort(xs)
            ci = self.curl_idx
            o = np.interp(self.rest[ci, 0], xs[order], gs[order])
            depth = 0.55 * np.minimum(o, 0.008) * self.curl_w
            # inwards = back, in the jaw-rotated frame for the lower lip
            V[ci, 2] -= depth
            V[ci, 1] += 0.2 * depth * (self.S_up[ci] - self.S_lo[ci])
        # 4. head pose
        R_head = euler_head(p[CONTROL_INDEX["head_yaw"]], p[CONTROL_INDEX["head_pitch"]],
                            p[CONTROL_INDEX["head_roll"]])
        T_head = affine(R_head, H.NECK_PIVOT)
        Vh = V.copy()
        if not np.allclose(R_head, np.eye(3)):
            yaw, pitch, roll = (p[CONTROL_INDEX[k]] for k in ("head_yaw", "head_pitch", "head_roll"))
            wh = self.w_head
            full = wh >= 1.0 - 1e-12
            part = (~full) & (wh > 1e-12)
            V[full] = apply(T_head, V[full])
            ip = np.nonzero(part)[0]
            whp = wh[ip]
            Rp = np.einsum("nij,njk->nik",
                           rodrigues(np.tile([0.0, 1.0, 0.0], (len(ip), 1)), whp * yaw),
                           np.einsum("nij,njk->nik",
                                     rodrigues(np.tile([1.0, 0.0, 0.0], (len(ip), 1)), -whp * pitch),
                                     rodrigues(np.tile([0.0, 0.0, 1.0], (len(ip), 1)), -whp * roll)))
            V[ip] = np.einsum("nij,nj->ni", Rp, V[ip] - H.NECK_PIVOT) + H.NECK_PIVOT
        # eye transforms: gaze about the eyeball centre, then the head
        gy = p[CONTROL_INDEX["gaze_yaw"]]
        gpch = p[CONTROL_INDEX["gaze_pitch"]]
        eyes = {}
        for name, sgn in (("eye_left", 1.0), ("eye_right", -1.0)):
            ce = H.EYE_CENTRE * np.array([sgn, 1, 1])
            eyes[name] = T_head @ affine(H.rot_y(gy) @ H.rot_x(-gpch), ce)
        return RigState(V, T_head, T_head @ T_jaw, eyes, lid, gap, Vh)


# --------------------------------------------------------------------------------------------
# validity checks (used by the tests)
# --------------------------------------------------------------------------------------------
def triangle_normals(V, F):
    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    a = np.linalg.norm(n, axis=1)
    return n / np.maximum(a, 1e-30)[:, None], 0.5 * a


def interior_edges(F):
    """Pairs of faces sharing an edge: (E, 2) face indices."""
    e = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    fid = np.tile(np.arange(len(F)), 3)
    key = np.sort(e, axis=1)
    order = np.lexsort((key[:, 1], key[:, 0]))
    k = key[order]
    same = np.all(k[1:] == k[:-1], axis=1)
    i = np.nonzero(same)[0]
    return np.stack([fid[order][i], fid[order][i + 1]], 1)


def fold_report(V_ref, V_def, F, pairs=None):
    """Compare a deformed mesh with a reference of the same topology.

    Returns ``(min_area_ratio, n_folded_edges)``: the smallest triangle-area ratio deformed /
    reference, and the number of edges whose two triangles were nearly coplanar in the reference
    (normals within 60°) but face more than 120° apart in the deformed mesh (a fold)."""
    if pairs is None:
        pairs = interior_edges(F)
    n0, a0 = triangle_normals(V_ref, F)
    n1, a1 = triangle_normals(V_def, F)
    ratio = a1 / np.maximum(a0, 1e-30)
    c0 = np.einsum("ij,ij->i", n0[pairs[:, 0]], n0[pairs[:, 1]])
    c1 = np.einsum("ij,ij->i", n1[pairs[:, 0]], n1[pairs[:, 1]])
    folded = int(np.sum((c0 > 0.5) & (c1 < -0.5)))
    return float(ratio[a0 > 1e-12].min()), folded
