"""How many of the texels a frame relights its shading reads: per chunk (source, capture camera) the texels
the exact path lights (those on triangles facing the view with a weight at a vertex, as
``Renderer.light_frame`` chooses them) against those some hit's 2x2 bilinear taps fall on (the hit mapped
into the source's geometry and projected into the chunk's camera, as ``LitFrame.shade`` reads), summed over
the frame's chunks. A share near 1 leaves nothing to skip by relighting only the texels read::

    python benchmarks/texels_read.py MODEL [--expression neutral=0.5,smile=0.5] [--yaw 20] [--pitch 3] [--size 256]
"""
from __future__ import annotations

import argparse

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("model")
    ap.add_argument("--expression", default=None, help="default: the neutral and the second expression, half each")
    ap.add_argument("--yaw", type=float, default=20.0)
    ap.add_argument("--pitch", type=float, default=3.0)
    ap.add_argument("--size", type=int, default=256)
    a = ap.parse_args()
    import mifacerf as mf
    from mifacerf.rendering.chunks import plan_frame
    from mifacerf.rendering.frame import facing_weights

    face = mf.load_model(a.model)
    m, r = face.model, face.renderer
    other = [e for e in m.expressions if e != m.neutral][0]
    expression = a.expression or f"{m.neutral}=0.5,{other}=0.5"
    cam = face.camera((a.yaw, a.pitch), a.size)
    target, W = face.target(expression)
    traced = r._traced(target)
    plan = plan_frame(m, target, facing_weights(W, traced, m.triangles, cam.centre), cam)
    r._scene.set_vertices(traced)
    _, origin, dirs = r._camera_rays(cam, 4, 0)
    hits = r._scene.trace(origin, dirs, cull_back=True)
    tri, bary = hits.tri[hits.valid], hits.bary[hits.valid]
    lit_total = read_total = 0
    for ch in plan.chunks:
        f = m.field(ch.s, ch.c)
        wv = ch.weights + ch.fallback
        near = np.flatnonzero((wv[m.triangles] > 0).any(axis=1)[f.tri])
        lit = near[(f.bary[near] * wv[m.triangles[f.tri[near]]]).sum(1) > 0]
        use = (wv[m.triangles[tri]] > 0).any(1)
        P = np.einsum("nk,nkd->nd", bary[use], m.vertices[ch.s][m.triangles[tri[use]]])
        uv, _ = m.cameras[ch.c].project(P)
        x0, y0 = np.floor(uv[:, 0] - 0.5).astype(int), np.floor(uv[:, 1] - 0.5).astype(int)
        H, Wd = f.depth_map().shape
        index = np.full(H * Wd, -1)
        index[f.pixels[:, 0] * Wd + f.pixels[:, 1]] = np.arange(len(f))
        taps = []
        for dy in (0, 1):
            for dx in (0, 1):
                yy, xx = y0 + dy, x0 + dx
                inside = (yy >= 0) & (yy < H) & (xx >= 0) & (xx < Wd)
                t = index[yy[inside] * Wd + xx[inside]]
                taps.append(t[t >= 0])
        lit_total += len(lit)
        read_total += len(np.intersect1d(np.unique(np.concatenate(taps)), lit))
    print(f"{expression} at yaw {a.yaw}°, pitch {a.pitch}°, {a.size}²: {len(plan.chunks)} chunks, {lit_total} texels "
          f"lit, {read_total} of them read by some hit's taps ({read_total / max(lit_total, 1):.2f})")


if __name__ == "__main__":
    main()
