"""Eyeballs, teeth and the mouth interior of the procedural head.

* **Eyeballs** (rigid, one per eye): a sphere of radius :data:`~.head.EYE_RADIUS` with a cornea
  cap bulging :data:`~.head.CORNEA_HEIGHT` above it, looking along +Z in its rest frame (centre at
  :data:`~.head.EYE_CENTRE`, mirrored for the right eye). Texture coordinates are an azimuthal
  equidistant map about the optical axis: ``uv = ½ + (β/2π)(sin ψ, cos ψ)`` with ``β`` the angle from
  the axis and ``ψ`` the angle about it (ψ = 0 up), so the iris is a disc in the middle of the texture.
  Material: principled, sclera / iris / pupil texture, a glossy (low roughness, non-delta) cornea.
* **Teeth** (rigid): an upper and a lower arch of 12 rounded-box crowns each (incisors, canines,
  premolars, first molars) along parabolic dental arches; the upper arch is fixed to the skull, the
  lower one moves with the jaw. Their rest frames are the head frame at the neutral head pose.
* **Mouth interior** (deformable): a "sock" whose rim is the lip-margin loop of the skin's mouth
  slit (so it closes the mouth opening exactly, with no gap); it runs back over the gums, the palate
  and the tongue to the throat. Its upper half follows the skull, its lower half the jaw. Diffuse,
  dark red, pinker near the lips (per-vertex colour).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry.rigid import apply
from . import head as H

# --------------------------------------------------------------------------------------------
# eyeball
# --------------------------------------------------------------------------------------------
CORNEA_ANGLE = np.radians(33.0)   #: angular radius of the cornea cap
IRIS_ANGLE = float(np.arcsin(H.IRIS_RADIUS / H.EYE_RADIUS))
PUPIL_ANGLE = float(np.arcsin(H.PUPIL_RADIUS / H.EYE_RADIUS))


def eyeball_radius(beta):
    c = np.where(beta < CORNEA_ANGLE, np.cos(0.5 * np.pi * beta / CORNEA_ANGLE) ** 2, 0.0)
    return H.EYE_RADIUS + H.CORNEA_HEIGHT * c


def eyeball_mesh(n_rings: int = 44, n_seg: int = 56):
    """Eyeball about the origin looking along +Z: vertices (n, 3), faces, uv (n, 2), β per vertex."""
    # rings: dense over the cornea, coarser behind
    t = np.linspace(0.0, 1.0, n_rings + 1)
    beta = np.where(t < 0.45, t / 0.45 * np.radians(40.0),
                    np.radians(40.0) + (t - 0.45) / 0.55 * (np.pi - np.radians(40.0)))
    psi = np.linspace(0.0, 2 * np.pi, n_seg, endpoint=False)
    verts, uvs, betas = [], [], []
    # front pole
    verts.append([0.0, 0.0, eyeball_radius(0.0)])
    uvs.append([0.5, 0.5])
    betas.append(0.0)
    for b in beta[1:-1]:
        r = eyeball_radius(b)
        for ps in psi:
            d = np.array([np.sin(b) * np.sin(ps), np.sin(b) * np.cos(ps), np.cos(b)])
            verts.append(r * d)
            uvs.append([0.5 + b / (2 * np.pi) * np.sin(ps), 0.5 + b / (2 * np.pi) * np.cos(ps)])
            betas.append(b)
    verts.append([0.0, 0.0, -H.EYE_RADIUS])
    uvs.append([0.5, 0.999])
    betas.append(np.pi)
    V = np.array(verts)
    nr = len(beta) - 2
    F = []
    for j in range(n_seg):
        F.append([0, 1 + j, 1 + (j + 1) % n_seg])
    for i in range(nr - 1):
        a = 1 + i * n_seg
        b = a + n_seg
        for j in range(n_seg):
            j2 = (j + 1) % n_seg
            F.append([a + j, b + j, b + j2])
            F.append([a + j, b + j2, a + j2])
    last = len(V) - 1
    a = 1 + (nr - 1) * n_seg
    for j in range(n_seg):
        F.append([a + j, last, a + (j + 1) % n_seg])
    F = np.array(F, np.int32)
    # outward orientation: ψ runs clockwise seen from the front, so fix by signed volume
    vol = np.einsum("ij,ij->i", V[F[:, 0]], np.cross(V[F[:, 1]], V[F[:, 2]])).sum()
    if vol < 0:
        F = F[:, [0, 2, 1]]
    return V, F, np.array(uvs), np.array(betas)


def _hash_noise(n, seed):
    return np.random.default_rng(seed).random(n)


def eye_textures(res: int = 256, iris_colour=(0.16, 0.20, 0.22), seed: int = 7):
    """Albedo (res, res, 3) and roughness (res, res) of the eyeball (linear sRGB)."""
    v, u = np.meshgrid((np.arange(res) + 0.5) / res, (np.arange(res) + 0.5) / res, indexing="ij")
    du, dv = u - 0.5, v - 0.5
    beta = np.hypot(du, dv) * 2 * np.pi
    psi = np.arctan2(du, dv)
    rng = np.random.default_rng(seed)
    # iris fibres: sum of random radial streaks
    fib = np.zeros_like(beta)
    for k, amp in ((37, 0.5), (61, 0.3), (113, 0.2)):
        ph = rng.random(k) * 2 * np.pi
        a = rng.random(k)
        idx = ((psi + np.pi) / (2 * np.pi) * k).astype(int) % k
        fib += amp * (a[idx] * np.cos(psi * k + ph[idx]) * 0.5 + 0.5)
    rel = np.clip((beta - PUPIL_ANGLE) / (IRIS_ANGLE - PUPIL_ANGLE), 0.0, 1.0)
    outer = np.asarray(iris_colour)
    inner = np.array([0.30, 0.19, 0.08])   # a warm collarette round the pupil
    mix = np.clip((rel - 0.18) / 0.25, 0.0, 1.0)[..., None]
    iris = inner * (1 - mix) + outer * mix
    iris = iris * (0.65 + 0.55 * fib[..., None])
    limbal = np.clip((rel - 0.82) / 0.18, 0.0, 1.0)[..., None]
    iris = iris * (1.0 - 0.75 * limbal)
    sclera = np.array([0.80, 0.76, 0.72])
    # pinker, veined towards the corners
    side = np.abs(np.sin(psi)) * np.clip((beta - 0.9) / 0.8, 0.0, 1.0)
    veins = np.zeros_like(beta)
    for _ in range(6):
        p0 = rng.random() * 2 * np.pi
        w = 0.02 + 0.02 * rng.random()
        veins += np.exp(-((np.angle(np.exp(1j * (psi - p0 - 0.3 * np.sin(beta * 7 + p0))))) / w) ** 2)
    sc = sclera * (1.0 - 0.10 * side[..., None]) + np.array([0.06, -0.04, -0.04]) * side[..., None]
    sc = sc - (np.clip(veins, 0, 1) * side)[..., None] * np.array([0.05, 0.25, 0.25])
    albedo = np.where((beta < IRIS_ANGLE)[..., None], iris, sc)
    # soft limbus transition
    lim = np.clip((beta - IRIS_ANGLE) / 0.03, 0.0, 1.0)[..., None]
    albedo = np.where((beta >= IRIS_ANGLE)[..., None], iris * (1 - lim) + sc * lim, albedo)
    pupil = 1.0 - np.clip((beta - PUPIL_ANGLE) / 0.015, 0.0, 1.0)
    albedo = albedo * (1 - pupil[..., None]) + 0.008 * pupil[..., None]
    rough = np.where(beta < CORNEA_ANGLE, 0.10, 0.28).astype(np.float32)
    return np.clip(albedo, 0.0, 1.0).astype(np.float32), rough


# --------------------------------------------------------------------------------------------
# teeth
# --------------------------------------------------------------------------------------------
@dataclass
class ArchSpec:
    z_front: float      # z of the labial face of the central incisors
    k: float            # parabola: z = z_front - k x^2
    edge_y: float       # incisal edge height of the central incisors
    widths: tuple
    heights: tuple
    thick: tuple
    upper: bool


UPPER = ArchSpec(0.0835, 44.0, H.Y_MOUTH - 0.0015,
                 (0.0085, 0.0066, 0.0076, 0.0070, 0.0066, 0.0100),
                 (0.0105, 0.0092, 0.0102, 0.0084, 0.0078, 0.0072),
                 (0.0068, 0.0060, 0.0078, 0.0088, 0.0088, 0.0104), True)
LOWER = ArchSpec(0.0815, 48.0, H.Y_MOUTH + 0.0012,
                 (0.0054, 0.0059, 0.0069, 0.0070, 0.0071, 0.0108),
                 (0.0090, 0.0093, 0.0104, 0.0086, 0.0080, 0.0074),
                 (0.0058, 0.0060, 0.0074, 0.0080, 0.0084, 0.0100), False)
N_FRONT_TEETH = 5   # per side in the template strips (incisors, canine, premolars): 10 per arch


def _arch_point(spec: ArchSpec, s: float):
    """Point at arc length ``s`` (signed, from the midline) along the arch at its labial face, and
    its unit tangent and outward normal (in the x-z plane)."""
    xs = np.linspace(0.0, 0.04, 4001)
    zs = spec.z_front - spec.k * xs ** 2
    arc = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(xs), np.diff(zs)))])
    x = np.interp(abs(s), arc, xs)
    z = spec.z_front - spec.k * x * x
    t = np.array([1.0, 0.0, -2 * spec.k * x])
    t /= np.linalg.norm(t)
    nrm = np.array([t[2], 0.0, -t[0]])
    if nrm[2] < 0:
        nrm = -nrm
    if s < 0:
        x = -x
        t = np.array([t[0], 0.0, -t[2]])
        nrm = np.array([-nrm[0], 0.0, nrm[2]])
    return np.array([x, 0.0, z]), t, nrm


def _tooth_layout(spec: ArchSpec):
    """Per tooth (right to left): arc centre, width, height, thickness, edge height."""
    out = []
    for sgn in (-1.0, 1.0):
        s = 0.0
        for i, (w, h, th) in enumerate(zip(spec.widths, spec.heights, spec.thick)):
            w = 0.94 * w
            c = s + 0.5 * w
            s += w
            # the occlusal plane curves up towards the back (curve of Spee), incisors lowest
            lift = (0.00045 if spec.upper else 0.00034) * i * i
            edge = spec.edge_y + lift
            out.append((sgn * c, w, h, th, edge, i))
    out.sort(key=lambda r: r[0])
    return out


def _rounded_box(n=10):
    """Unit rounded box (superellipsoid, exponents ~0.3) as a UV sphere: vertices, faces."""
    th = np.linspace(0, np.pi, n + 1)
    ph = np.linspace(0, 2 * np.pi, 2 * n, endpoint=False)
    e = 0.35

    def sp(a):
        return np.sign(a) * np.abs(a) ** e

    V = [[0, 1, 0]]
    for t in th[1:-1]:
        for p in ph:
            V.append([sp(np.sin(t)) * sp(np.cos(p)), sp(np.cos(t)), sp(np.sin(t)) * sp(np.sin(p))])
    V.append([0, -1, 0])
    V = np.array(V, float)
    m = 2 * n
    F = []
    for j in range(m):
        F.append([0, 1 + (j + 1) % m, 1 + j])
    for i in range(n - 2):
        a = 1 + i * m
        b = a + m
        for j in range(m):
            j2 = (j + 1) % m
            F.append([a + j, a + j2, b + j2])
            F.append([a + j, b + j2, b + j])
    last = len(V) - 1
    a = 1 + (n - 2) * m
    for j in range(m):
        F.append([a + j, a + (j + 1) % m, last])
    F = np.array(F, np.int32)
    vol = np.einsum("ij,ij->i", V[F[:, 0]], np.cross(V[F[:, 1]], V[F[:, 2]])).sum()
    return V, (F if vol > 0 else F[:, [0, 2, 1]])


def teeth_mesh(spec: ArchSpec):
    """The arch's crowns (each extended ~3 mm into the gum) in the head frame at rest."""
    box_v, box_f = _rounded_box()
    Vs, Fs = [], []
    off = 0
    for (s, w, h, th, edge, i) in _tooth_layout(spec):
        c, t, nrm = _arch_point(spec, s)
        root = 0.003
        hh = 0.5 * (h + root)
        yc = edge + hh if spec.upper else edge - hh
        # local shape: taper the thickness towards the incisal edge (front teeth)
        q = box_v.copy()
        edge_side = -1.0 if spec.upper else 1.0   # local y of the edge
        tnorm = 0.5 * (1.0 + q[:, 1] * edge_side)  # 0 at the gum end, 1 at the edge
        taper = 1.0 - (0.55 if i < 3 else 0.25) * tnorm ** 1.5
        q[:, 2] = q[:, 2] * taper
        if i == 2:  # canine: pointed
            q[:, 1] = q[:, 1] - edge_side * 0.25 * (np.abs(q[:, 0])) * tnorm
        loc = np.stack([q[:, 0] * 0.5 * w, q[:, 1] * hh, (q[:, 2] - 0.6 * (1 - taper)) * 0.5 * th], 1)
        # labial face on the arch: shift inwards by half the thickness
        centre = c - nrm * 0.5 * th + np.array([0.0, yc, 0.0])
        # slight labial inclination of incisors
        R = np.stack([t, [0.0, 1.0, 0.0], nrm], 1)
        P = loc @ R.T + centre
        Vs.append(P)
        Fs.append(box_f + off)
        off += len(P)
    return np.concatenate(Vs), np.concatenate(Fs).astype(np.int32)


def teeth_strip(spec: ArchSpec, n_side: int = N_FRONT_TEETH):
    """The paper's teeth model: a triangle strip along the front ``2 n_side`` teeth, two triangles
    per tooth; vertices alternate incisal edge / gum line at the tooth boundaries (rest frame)."""
    layout = [r for r in _tooth_layout(spec) if r[5] < n_side]
    bounds = [layout[0][0] - 0.5 * layout[0][1]]
    for k, r in enumerate(layout):
        bounds.append(r[0] + 0.5 * r[1])
    V = []
    gum_off = (0.0088 if spec.upper else -0.0085)
    for k, s in enumerate(bounds):
        c, t, nrm = _arch_point(spec, s)
        # edge height at this boundary: the lower of the two neighbouring teeth's edges
        nb = [layout[j] for j in (k - 1, k) if 0 <= j < len(layout)]
        edge = float(np.mean([r[4] for r in nb]))
        V.append(c + np.array([0.0, edge, 0.0]))
        V.append(c + np.array([0.0, edge + gum_off, 0.0]))
    V = np.array(V)
    F = []
    for k in range(len(bounds) - 1):
        e0, g0, e1, g1 = 2 * k, 2 * k + 1, 2 * k + 2, 2 * k + 3
        if spec.upper:
            F += [[e0, e1, g1], [e0, g1, g0]]
        else:
            F += [[e0, g1, e1], [e0, g0, g1]]
    return V, np.array(F, np.int32)


# --------------------------------------------------------------------------------------------
# mouth interior
# --------------------------------------------------------------------------------------------
class MouthSock:
    """The mouth interior, attached to the lip-margin loop of the skin's mouth slit."""

    N_RINGS = 5

    def __init__(self, slit, rest_vertices: np.ndarray):
        # loop: right corner, upper margin (increasing x), left corner, lower margin (decreasing x)
        self.loop = np.concatenate([[slit.corners[0]], slit.upper, [slit.corners[1]], slit.lower[::-1]])
        L = len(self.loop)
        x = rest_vertices[self.loop, 0]
        hw = max(abs(x[0]), abs(x[len(slit.upper) + 1]))
        side = np.concatenate([[0.0], np.ones(len(slit.upper)), [0.0], -np.ones(len(slit.lower))])
        self.side = side
        self.lower_w = np.where(side < 0, 1.0, np.where(side > 0, 0.0, 0.5))
        tau = np.arccos(np.clip(x / hw, -1.0, 1.0))
        tau = np.where(side < 0, -tau, tau)
        self.tau = tau
        c, s = np.cos(tau), np.sin(tau)
        up = s > 0
        ym = H.Y_MOUTH
        rings = []
        # ring 2: gum line, just in front of the teeth
        gx = 0.0215 * c
        gz_up = UPPER.z_front + 0.0012 - UPPER.k * gx ** 2
        gz_lo = LOWER.z_front + 0.0012 - LOWER.k * gx ** 2
        rings.append(np.stack([gx, ym + 0.0098 * s, np.where(up, gz_up, gz_lo)], 1))
        # ring 3: palate above the teeth / tongue behind the lower incisors
        rings.append(np.stack([0.027 * c, np.where(up, ym + 0.0175 * s, ym - 0.0030 + 0.0060 * s),
                               np.where(up, 0.062, 0.071) - 0.004 * c * c], 1))
        # ring 4: back of the mouth
        rings.append(np.stack([0.024 * c, ym + np.where(up, 0.012, 0.010) * s, 0.040 - 0.004 * c * c], 1))
        # ring 5: throat
        rings.append(np.stack([0.010 * c, ym + 0.005 * s, 0.022 + 0.0 * c], 1))
        self.rest_rings = rings
        self.colours = np.array([
            [0.50, 0.16, 0.15],   # ring 0: lip margin (not stored; skin owns it)
            [0.48, 0.15, 0.14],   # ring 1: inner lip
            [0.52, 0.22, 0.20],   # ring 2: gums
            [0.30, 0.07, 0.06],   # ring 3: palate / tongue
            [0.06, 0.015, 0.012],  # ring 4
            [0.03, 0.008, 0.006],  # ring 5
            [0.02, 0.005, 0.004],  # throat pole
        ])
        self.n_loop = L
        # faces: ring k (k = 0 is the skin loop) to ring k+1, then a fan to the throat pole
        F = []
        n_r = 1 + 1 + len(rings)   # loop, ring1, rings 2..5
        for k in range(n_r - 1):
            for i in range(L):
                i2 = (i + 1) % L
                a, b = k * L + i, k * L + i2
                c_, d = (k + 1) * L + i2, (k + 1) * L + i
                F.append([a, b, c_])
                F.append([a, c_, d])
        pole = n_r * L
        for i in range(L):
            F.append([(n_r - 1) * L + i, (n_r - 1) * L + (i + 1) % L, pole])
        self.faces = np.array(F, np.int32)
        cols = [self.colours[min(k, 5)][None].repeat(L, 0) for k in range(n_r)] + [self.colours[6][None]]
        self.vertex_colours = np.concatenate(cols).astype(np.float32)

    def vertices(self, skin_head: np.ndarray, T_jaw_rel: np.ndarray, T_head: np.ndarray):
        """World vertices given the skin in the head frame (before the head pose), the jaw
        transform relative to the head, and the head transform. The loop reuses the skin's margin
        vertices (in world: apply ``T_head`` to the loop too)."""
        L = self.n_loop
        loop = skin_head[self.loop]
        # ring 1: inner lip, follows the margins
        ring1 = loop + np.stack([np.zeros(L), 0.0018 * np.sign(self.side), np.full(L, -0.0045)], 1)
        out = [loop, ring1]
        w = self.lower_w[:, None]
        for R0 in self.rest_rings:
            Rj = apply(T_jaw_rel, R0)
            out.append(R0 * (1 - w) + Rj * w)
        pole = np.array([[0.0, H.Y_MOUTH, 0.016]])
        P = np.concatenate(out + [pole])
        # keep ring 1 from crossing: if the lips are shut, ring 1 of both sides sits inside the lips
        return apply(T_head, P)
