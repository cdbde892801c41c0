"""The straightforward dense reference renderer: a NumPy weighted sum over all lights and all fields.

It evaluates the same model as :class:`mifacerf.rendering.renderer.Renderer`'s exact path
— per sample, for *every* (source expression, capture camera) field (no render chunks,
no skipping of zero weights): the sample's surface point in the source geometry projected
into the camera, the field read bilinearly (occlusion-aware, the same depth test), the
per-vertex rotated lighting interpolated with the chunk weights, summed over every light
— in plain NumPy. It is the speed baseline of ``mifacerf bench`` and an independent check
of the optimised kernels (the two must agree to rounding).
"""
from __future__ import annotations

import numpy as np

from ..rendering.chunks import plan_frame
from ..rendering.frame import (MIN_VIEW_COS, OBLIQUE_RATIO, OUTLINE_WEIGHT, facing_weights, grazing_tolerance_np,
                               outline_texels, resolve_pixels, view_cosine_np)


def dense_render(renderer, target, weights, camera, env, spp: int = 1, seed: int = 0) -> np.ndarray:
    """(H, W, 4) RGBA of the skin (no eyes/teeth pass), computed densely."""
    model = renderer.model
    traced = renderer._traced(target)     # the renderer's traced target (rendering.frame.ChordOffset)
    plan = plan_frame(model, target, facing_weights(weights, traced, model.triangles, camera.centre), camera)
    basis = renderer.light_basis(env)
    T, S, C = model.n_vertices, len(model.expressions), len(model.cameras)
    # per-vertex rotated lighting for every source (identity where the weight is 0): the dense way
    lighting = np.zeros((S, T, model.n_lights, 3))
    for s in range(S):
        R = plan.rotations.get(s, np.broadcast_to(np.eye(3), (T, 3, 3)))
        lighting[s] = basis.rotated(R)
    # per-vertex chunk weights for every (s, c) in both tiers, zero where the plan has no chunk
    a = np.zeros((S, C, T))
    fb = np.zeros((S, C, T))
    for ch in plan.chunks:
        a[ch.s, ch.c] = ch.weights
        fb[ch.s, ch.c] = ch.fallback
    renderer._scene.set_vertices(traced)
    hits, _ = renderer._scene.render_hits(camera, spp, seed)
    idx = np.flatnonzero(hits.valid)
    tri, bary = hits.tri[idx], hits.bary[idx]
    tv = model.triangles[tri]
    cos_r = view_cosine_np(camera, np.einsum("nk,nkd->nd", bary, plan.target[tv]), plan.target[tv])
    # accumulated colour and weight: primary tier seen, fallback tier seen, fallback without the
    # depth test (the documented last resort)
    acc = {k: np.zeros((len(idx), 3)) for k in ("primary", "fallback", "any")}
    wsum = {k: np.zeros(len(idx)) for k in acc}
    tol = renderer.depth_tolerance
    for s in range(S):
        for c in range(C):
            if not model.has_field(s, c):
                continue
            f = model.field(s, c)
            cam = model.cameras[c]
            h, w = f.shape
            dense = np.zeros((h, w, model.n_lights, 3), np.float32)  # the full field, every light
            dense[f.pixels[:, 0], f.pixels[:, 1]] = np.asarray(f.rf, np.float32)
            have = np.zeros((h, w), bool)
            have[f.pixels[:, 0], f.pixels[:, 1]] = True
            depth = f.depth_map()
            inner = have & ~outline_texels(depth)   # texels off the subject's outline: preferred where any
            p_s = np.einsum("nk,nkd->nd", bary, model.vertices[s][tv])
            uv, _ = cam.project(p_s)
            dist = np.linalg.norm(p_s - cam.centre, axis=1)
            cos_v = view_cosine_np(cam, p_s, model.vertices[s][tv])
            tol_p = grazing_tolerance_np(cos_v, dist, cam, tol)   # the renderer's oblique allowance
            a_p = (bary * a[s, c][tv]).sum(1)  # the chunk's weight at the sample, primary tier
            f_p = (bary * fb[s, c][tv]).sum(1)  # and fallback tier
            aw = bary * (a[s, c] + fb[s, c])[tv]  # lighting interpolated over either tier's vertices
            lam = np.einsum("nk,nklc->nlc", aw / np.maximum(aw.sum(1), 1e-300)[:, None], lighting[s][tv])
            x0 = np.floor(uv[:, 0]).astype(np.int64)
            y0 = np.floor(uv[:, 1]).astype(np.int64)
            fx, fy = uv[:, 0] - x0, uv[:, 1] - y0
            sums = {}   # (depth-tested?, off the outline only?) -> [colour, coverage]
            for key in ((True, False), (True, True), (False, False), (False, True)):
                sums[key] = [np.zeros((len(idx), 3)), np.zeros(len(idx))]
            for dy in (0, 1):
                for dx in (0, 1):
                    xx, yy = x0 + dx, y0 + dy
                    ok = (xx >= 0) & (yy >= 0) & (xx < w) & (yy < h) & np.isfinite(uv).all(1) & (a_p + f_p > 0) & ((cos_v >= MIN_VIEW_COS) | (cos_v >= OBLIQUE_RATIO * cos_r))
                    xs, ys = np.where(ok, xx, 0), np.where(ok, yy, 0)
                    ok &= have[ys, xs]
                    wt_any = np.where(ok, (fx if dx else 1 - fx) * (fy if dy else 1 - fy), 0.0)
                    wt = np.where(np.abs(depth[ys, xs] - dist) <= tol_p, wt_any, 0.0)
                    lit = np.einsum("nlc,nlc->nc", dense[ys, xs], lam)  # Σ over every light
                    for tested, weight_tap in ((True, wt), (False, wt_any)):
                        for off, wtap in ((False, weight_tap), (True, weight_tap * inner[ys, xs])):
                            sums[tested, off][0] += wtap[:, None] * lit
                            sums[tested, off][1] += wtap
            # the texels off the outline where the chunk has any for the point, else every texel
            merged = {}
            for tested in (True, False):
                (c_all, v_all), (c_in, v_in) = sums[tested, False], sums[tested, True]
                use_in = v_in > 1e-3
                merged[tested] = (np.where(use_in[:, None], c_in / np.maximum(v_in, 1e-300)[:, None] * v_all[:, None],
                                           c_all), v_all, np.where(use_in, 1.0, OUTLINE_WEIGHT))
            col, cov, k_d = merged[True]
            col_any, cov_any, k_a = merged[False]
            for tier, weight, cl, cv in (("primary", a_p * k_d, col, cov), ("fallback", f_p * k_d, col, cov),
                                         ("any", f_p * k_a, col_any, cov_any)):
                seen = cv > 1e-3
                acc[tier][seen] += weight[seen, None] * cl[seen] / cv[seen, None]
                wsum[tier][seen] += weight[seen]
    tier = np.where(wsum["primary"] > 1e-9, 0, np.where(wsum["fallback"] > 1e-9, 1, 2))
    acc_p = np.choose(tier[:, None], [acc["primary"], acc["fallback"], acc["any"]])
    wsum_p = np.choose(tier, [wsum["primary"], wsum["fallback"], wsum["any"]])
    covered = wsum_p > 1e-9
    colour = np.where(covered[:, None], acc_p / np.maximum(wsum_p, 1e-300)[:, None], 0.0)
    rgba, _ = resolve_pixels(idx // spp, colour, covered, camera.height, camera.width, spp)  # the renderer's alpha rule
    return rgba
