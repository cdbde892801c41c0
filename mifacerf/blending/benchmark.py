"""Benchmark: blend weights of 300 vertices × 60 sources × 10,000 target frames.

    mifacerf evaluate blending-speed [--vertices 300] [--sources 60] [--frames 10000] [--json FILE]

Times, in the same run and on the same targets:

* the Dr.Jit evaluator (:mod:`mifacerf.blending.weights`, float32 and float64): one kernel per
  dimensionality over all (frame × vertex) lanes — Horn alignment, projection, walk, barycentrics,
  nearest-hull fall-back;
* the straightforward NumPy/SciPy reference (:mod:`mifacerf.blending.reference`): a Python loop over
  vertices, vectorised over frames — Horn (batched ``eigh``), projection, ``Delaunay.find_simplex`` +
  ``transform``, nearest hull facet for the outside targets.  Its two halves are timed separately.

The subject is a toy sheet (:mod:`mifacerf.blending.toy`) with 12 localised blendshapes; sources
activate 1-4 of them under random head poses; targets are random blends of the sources' parameters
(a third of them scaled by 2.5, mostly outside the sources' hull) under random head poses.  Not a timed test: numbers go to
``docs/blending.md``.
"""
from __future__ import annotations

import os
import platform
import time

import numpy as np


def _dense_max_diff(i1, w1, i2, w2, n, chunk=500):
    worst = 0.0
    for t0 in range(0, i1.shape[0], chunk):
        s = slice(t0, t0 + chunk)
        a = np.zeros(i1[s].shape[:2] + (n,))
        b = np.zeros_like(a)
        t, f = np.meshgrid(np.arange(a.shape[0]), np.arange(a.shape[1]), indexing="ij")
        for k in range(i1.shape[2]):
            np.add.at(a, (t, f, i1[s][..., k]), w1[s][..., k])
            np.add.at(b, (t, f, i2[s][..., k]), w2[s][..., k])
        worst = max(worst, float(np.abs(a - b).max()))
    return worst


def make_problem(n_vertices=300, n_sources=60, n_frames=10000, seed=0):
    from .toy import random_sources, toy_subject

    nx = int(round(np.sqrt(n_vertices * 4 / 3)))
    ny = max(2, n_vertices // nx)
    sub = toy_subject(nx=nx, ny=ny, n_shapes=12, seed=seed + 3)
    S, params = random_sources(sub, n_sources, seed=seed + 1, max_active=4)
    rng = np.random.default_rng(seed + 5)
    a = rng.dirichlet(np.ones(n_sources) * 0.3, size=n_frames)
    p = a @ params
    p[: n_frames // 3] *= 2.5
    X = sub.pose(p, rng.normal(size=(n_frames, 3)) * 0.1, rng.normal(size=(n_frames, 3)) * 0.01)
    return sub, S, X


def run(n_vertices=300, n_sources=60, n_frames=10000, residual_threshold=2e-5, seed=0, quiet=False,
        threads=None, repeats=3):
    from ..blas import single_threaded_blas
    from .model import BlendModel
    from .reference import vertex_coords, vertex_weights
    from .weights import backend

    say = (lambda *a: None) if quiet else (lambda *a: print(*a, flush=True))
    sub, S, X = make_problem(n_vertices, n_sources, n_frames, seed)
    V = S.shape[1]
    t0 = time.perf_counter()
    model = BlendModel.fit(S, 0, sub.triangles, residual_threshold=residual_threshold)
    t_fit = time.perf_counter() - t0
    dims = np.bincount(model.dims, minlength=4)
    nsimp = np.array([t.n_simplices for t in model.triangulations])
    say(f"problem: {V} vertices x {n_sources} sources x {n_frames} frames; fit {t_fit:.2f} s; "
        f"m histogram {dims.tolist()}; simplices per vertex mean {nsimp.mean():.0f} max {nsimp.max()}")

    B = backend()
    import drjit as dr

    if threads:
        dr.set_thread_count(int(threads))
    out = dict(vertices=V, sources=n_sources, frames=n_frames, fit_s=t_fit, dims=dims.tolist(),
               ghost_simplices=int(sum(t.ghost.sum() for t in model.triangulations)),
               simplices_mean=float(nsimp.mean()), simplices_max=int(nsimp.max()),
               variant=None, cpu_count=os.cpu_count(), drjit_threads=dr.thread_count(),
               machine=platform.processor() or platform.machine(), load_before=os.getloadavg()[0])
    from mifacerf.variant import ensure_variant

    out["variant"] = ensure_variant().variant()
    res = {}
    for precision in ("float32", "float64"):
        model.fiducial_weights(X[:64], precision=precision)            # compile (cached afterwards)
        t0 = time.perf_counter()
        model.fiducial_weights(X[:64], precision=precision)
        t_small = time.perf_counter() - t0
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            res[precision] = model.fiducial_weights(X, precision=precision)
            times.append(time.perf_counter() - t0)
        out[f"drjit_{precision}_s"] = min(times)
        say(f"Dr.Jit {precision} ({dr.thread_count()} threads): {min(times):.3f} s (best of {repeats}; "
            f"a 64-frame call takes {t_small * 1e3:.0f} ms)")

    # reference, per vertex; timed in its two halves.  Single-threaded BLAS: its LAPACK calls are tiny
    # (4x4 eigh, scipy's per-simplex transforms) and a threaded OpenBLAS only slows them down.
    blas = single_threaded_blas()
    blas.__enter__()
    Tn, F = X.shape[0], model.fiducials.size
    t0 = time.perf_counter()
    coords = [vertex_coords(model, f, X) if model.triangulations[f].m else None for f in range(F)]
    t_align = time.perf_counter() - t0
    ids = np.zeros((Tn, F, 4), dtype=np.int32)
    w = np.zeros((Tn, F, 4))
    t0 = time.perf_counter()
    for f in range(F):
        tri = model.triangulations[f]
        z = coords[f] if coords[f] is not None else np.zeros((Tn, 0))
        i, ww = vertex_weights(tri, z)
        k = i.shape[1]
        ids[:, f, :k], ids[:, f, k:], w[:, f, :k] = i, i[:, :1], ww
    t_locate = time.perf_counter() - t0
    blas.__exit__(None, None, None)
    out.update(reference_align_project_s=t_align, reference_locate_s=t_locate,
               reference_s=t_align + t_locate)
    say(f"reference (per-vertex NumPy/SciPy): {t_align + t_locate:.2f} s "
        f"(Horn + projection {t_align:.2f} s, find_simplex + transform + hull {t_locate:.2f} s)")
    for precision in ("float32", "float64"):
        r = out["reference_s"] / out[f"drjit_{precision}_s"]
        out[f"ratio_{precision}"] = r
        di = _dense_max_diff(ids, w, *res[precision], n_sources)
        out[f"max_dense_diff_{precision}"] = di
        say(f"ratio reference / Dr.Jit {precision}: {r:.1f}x; max |dense weight difference| {di:.2e}")
    outside = []
    for f in range(F):
        tri = model.triangulations[f]
        if tri.m >= 2 and tri.qhull is not None:
            outside.append(np.mean(tri.qhull.find_simplex(coords[f][:2000]) < 0))
    out["outside_fraction"] = float(np.mean(outside)) if outside else 0.0
    say(f"fraction of (frame, vertex) targets outside the sources' hull: {out['outside_fraction']:.2f}")
    out["load_after"] = os.getloadavg()[0]
    say(f"load average before / after: {out['load_before']:.1f} / {out['load_after']:.1f} on {os.cpu_count()} cores")
    return out
