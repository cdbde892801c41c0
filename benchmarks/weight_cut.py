"""Would dropping small blend weights pay? On frames of a tracked performance (the §5 weights of each frame's
mesh, as ``mifacerf drive`` renders them), the weights below each cut are zeroed and the rest renormalised;
per cut: the share of (vertex, source) pairs and of the weight mass removed, the chunks and texels a frame
relights, the median seconds per warm 256² frame, and the PSNR of each frame against the uncut one (alpha-1
pixels)::

    python benchmarks/weight_cut.py MODEL TRACK [--frames 10,40,70,100] [--cuts 0.01,0.02,0.05]
"""
from __future__ import annotations

import argparse
import statistics
import time

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("model")
    ap.add_argument("track")
    ap.add_argument("--frames", default="10,40,70,100")
    ap.add_argument("--cuts", default="0.01,0.02,0.05")
    ap.add_argument("--size", type=int, default=256)
    a = ap.parse_args()
    import mifacerf as mf
    from mifacerf.rendering.parts import part_transforms
    from mifacerf.rendering.renderer import RenderStats
    from mifacerf.tracking.drive import frame_parts
    from mifacerf.tracking.track import Track

    face = mf.load_model(a.model)
    m = face.model
    tr = Track(a.track)
    s0 = m.expression_index(m.neutral)
    base = part_transforms(m.template, m.eye_centres[s0], m.teeth[s0], m.head_pose[s0]) if m.references else {}
    cam, env, r = face.camera(None, a.size), face.environment("sky"), face.renderer
    r.cache_frames = False
    frames = [int(f) for f in a.frames.split(",")]
    Ws = {f: face.target(mesh=tr.vertices[f])[1] for f in frames}
    W = np.concatenate(list(Ws.values()))
    print(f"{len(frames)} frames, {(W > 1e-6).sum(1).mean():.1f} sources per vertex")

    def cut(Wf, eps):
        Wc = np.where(Wf >= eps, Wf, 0.0)
        none = Wc.sum(1) == 0
        Wc[none] = Wf[none]
        return Wc / Wc.sum(1, keepdims=True)

    def psnr(x, ref):
        mask = ref[..., 3] > 0.999
        return 10 * np.log10(ref[..., :3][mask].max() ** 2 / ((x[..., :3] - ref[..., :3])[mask] ** 2).mean())

    uncut = None
    for eps in [0.0] + [float(c) for c in a.cuts.split(",")]:
        ts, imgs, chunks, texels = [], [], [], []
        for f in frames:
            Wf = Ws[f] if eps == 0 else cut(Ws[f], eps)
            parts = frame_parts(face, tr, f, base) if base else None
            r.render(tr.vertices[f], Wf, cam, env, spp=4, parts=parts)   # warm: its fields loaded
            st = RenderStats()
            t0 = time.perf_counter()
            imgs.append(r.render(tr.vertices[f], Wf, cam, env, spp=4, parts=parts, stats=st))
            ts.append(time.perf_counter() - t0)
            chunks.append(st.chunks)
            texels.append(st.texels)
        line = f"cut {eps:g}: "
        if eps:
            removed = (W > 1e-6) & (W < eps)
            line += f"pairs removed {removed.sum() / (W > 1e-6).sum():.1%}, mass {W[removed].sum() / W.sum():.2%}, "
        line += f"{np.mean(chunks):.0f} chunks, {np.mean(texels) / 1e3:.0f}k texels, {statistics.median(ts):.3f} s/frame"
        if uncut is None:
            uncut = imgs
        else:
            line += ", PSNR against uncut " + " / ".join(f"{psnr(x, y):.1f}" for x, y in zip(imgs, uncut))
        print(line, flush=True)


if __name__ == "__main__":
    main()
