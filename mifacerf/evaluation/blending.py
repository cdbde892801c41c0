"""Blending on a subject against its true deformations: reconstruction error of the local deformation, culling.

    mifacerf evaluate blending [--subject synthetic|toy] [--out docs/img] [--json FILE]

For held-out targets — random blends of the sources' parameters and out-of-set parameter vectors —
the weights of every fiducial vertex reconstruct the local deformation as ``Σ_i w_i D_i(v)`` (the
sources' aligned neighbourhoods); its error against the target's own ``D_T(v)`` is reported per vertex
(RMS over the neighbourhood, metres), without and with coherent culling, next to two baselines: the
neutral alone, and the single nearest source (in the same metric).  Also: the kept expressions per
region, the histogram of the chosen dimensionality ``m``, and two pictures (``m`` per template vertex,
kept counts per region).
"""
from __future__ import annotations

import os
import time

import numpy as np

from ..blending.model import BlendModel


def local_error(model: BlendModel, D_src, D_tgt, W) -> np.ndarray:
    """Per (target, fiducial) RMS error (m) of ``Σ_i W_i D_src_i`` against ``D_tgt``.

    ``D_src`` ``(n, F, K, 3)``, ``D_tgt`` ``(T, F, K, 3)``, ``W`` dense ``(T, F, n)``.
    """
    rec = np.einsum("tfn,nfkc->tfkc", W, D_src)
    cnt = model.nbhd.count[model.fiducials]
    return np.sqrt(np.sum((rec - D_tgt) ** 2, axis=(2, 3)) / cnt[None, :])


def nearest_source_error(model, D_src, D_tgt) -> np.ndarray:
    cnt = model.nbhd.count[model.fiducials]
    d = np.sum((D_src[None] - D_tgt[:, None]) ** 2, axis=(3, 4)) / cnt[None, None, :]   # (T, n, F)
    return np.sqrt(d.min(axis=1))


def summarise(e: np.ndarray) -> dict:
    return {"mean_mm": float(e.mean() * 1e3), "median_mm": float(np.median(e) * 1e3),
            "p95_mm": float(np.percentile(e, 95) * 1e3), "max_mm": float(e.max() * 1e3)}


def toy_problem(seed: int = 0):
    """The toy sheet (:mod:`.toy`): 40 sources, 12 blendshapes, regions from the toy."""
    from ..blending.toy import random_sources, toy_subject

    sub = toy_subject(nx=24, ny=20, n_shapes=12, seed=seed + 3)
    S, params = random_sources(sub, 40, seed=seed + 1, max_active=4)
    rng = np.random.default_rng(seed + 9)

    def pose(P):
        return sub.pose(P, rng.normal(size=(len(P), 3)) * 0.1, rng.normal(size=(len(P), 3)) * 0.01)

    out_of_set = rng.uniform(0, 1, size=(60, params.shape[1])) * (rng.random((60, params.shape[1])) < 0.35)
    return dict(name="toy sheet", sources=S, params=params, neutral_index=0, triangles=sub.triangles,
                regions=sub.regions, vertices=sub.neutral, pose=pose, out_of_set=out_of_set)


def synthetic_problem(seed: int = 0, n_sources: int = 60, texture_resolution: int = 256):
    """The synthetic subject (:mod:`mifacerf.synthetic`): its ``n_sources`` captured-expression presets.

    Template meshes (``pose(params).template_vertices``), triangles and regions come from the subject's
    registration template.  Out-of-set targets: every control drawn uniformly in its range with
    probability 0.3 (else at its default), head pose included.
    """
    from ..synthetic.subject import default_subject

    subject = default_subject(texture_resolution)
    tpl = subject.template
    presets = subject.presets(n_sources)
    src_params = np.stack([e.params for e in presets])
    neutral_index = next(i for i, e in enumerate(presets) if e.category == "neutral")

    def pose(P):
        return np.stack([subject.pose(p, textures=False).template_vertices for p in P])

    S = pose(src_params)
    rng = np.random.default_rng(seed + 9)
    lo = np.array([c.lo for c in subject.controls])
    hi = np.array([c.hi for c in subject.controls])
    dflt = np.array([c.default for c in subject.controls])
    k = 60
    draw = lo + (hi - lo) * rng.random((k, lo.size))
    out_of_set = np.where(rng.random((k, lo.size)) < 0.3, draw, dflt)
    return dict(name="synthetic subject", sources=S, params=src_params, neutral_index=neutral_index,
                triangles=np.asarray(tpl.triangles), regions={k: np.asarray(v) for k, v in tpl.regions.items()},
                vertices=S[neutral_index], pose=pose, out_of_set=out_of_set,
                source_names=[e.name for e in presets])


def run(problem: dict, residual_threshold=None, similarity_threshold=None, n_blends: int = 60,
        out_dir: str | None = None, seed: int = 0, precision: str = "float64") -> dict:
    from ..blending.model import DEFAULT_RESIDUAL_THRESHOLD, DEFAULT_SIMILARITY_THRESHOLD

    rt = DEFAULT_RESIDUAL_THRESHOLD if residual_threshold is None else residual_threshold
    st = DEFAULT_SIMILARITY_THRESHOLD if similarity_threshold is None else similarity_threshold
    S, params = problem["sources"], problem["params"]
    n = len(S)
    rng = np.random.default_rng(seed)
    blend = rng.dirichlet(np.ones(n) * 0.3, size=n_blends) @ params
    targets = {"random blends": problem["pose"](blend), "out-of-set": problem["pose"](problem["out_of_set"])}
    t0 = time.perf_counter()
    plain = BlendModel.fit(S, problem["neutral_index"], problem["triangles"], residual_threshold=rt)
    culled = BlendModel.fit(S, problem["neutral_index"], problem["triangles"], regions=problem["regions"],
                            residual_threshold=rt, similarity_threshold=st)
    t_fit = time.perf_counter() - t0
    D_src = plain.local_deformations(S)
    out = dict(subject=problem["name"], n_sources=n, n_vertices=int(S.shape[1]), residual_threshold=rt,
               similarity_threshold=st, fit_s=t_fit, dims=np.bincount(plain.dims, minlength=4).tolist(),
               dims_culled=np.bincount(culled.dims, minlength=4).tolist(),
               kept={k: int(len(v)) for k, v in culled.kept.items()},
               region_sizes={k: int(len(v)) for k, v in problem["regions"].items()}, errors={})
    for name, X in targets.items():
        D_t = plain.local_deformations(X)
        e_plain = local_error(plain, D_src, D_t, plain.dense_weights(X, precision=precision))
        e_cull = local_error(culled, D_src, D_t, culled.dense_weights(X, precision=precision))
        W0 = np.zeros((len(X), plain.fiducials.size, n))
        W0[..., problem["neutral_index"]] = 1
        e_neutral = local_error(plain, D_src, D_t, W0)
        e_near = nearest_source_error(plain, D_src, D_t)
        out["errors"][name] = {"blend (no culling)": summarise(e_plain), "blend (culled)": summarise(e_cull),
                               "neutral only": summarise(e_neutral), "nearest source": summarise(e_near),
                               "targets": int(len(X))}
        if out_dir and name == "random blends":
            os.makedirs(out_dir, exist_ok=True)
            _error_picture(problem, plain, e_plain.mean(0), e_cull.mean(0), os.path.join(out_dir, "blending_error.png"))
    if out_dir:
        _pictures(problem, plain, culled, out_dir)
    return out


def _pictures(problem, plain, culled, out_dir):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    os.makedirs(out_dir, exist_ok=True)
    P = problem["vertices"]
    fig, axes = plt.subplots(1, 2, figsize=(11, 5), gridspec_kw={"width_ratios": [1.2, 1]})
    vd = plain.vertex_dims()
    cmap = matplotlib.colors.ListedColormap(["#444444", "#3b7dd8", "#f2a33a", "#d6322f"])
    order = np.argsort(P[:, 2])
    sc = axes[0].scatter(P[order, 0] * 100, P[order, 1] * 100, c=vd[order], cmap=cmap, vmin=-0.5, vmax=3.5, s=6)
    axes[0].set_aspect("equal")
    axes[0].set_title(f"chosen dimensionality m per vertex ({problem['name']}, front view)")
    axes[0].set_xlabel("x (cm)")
    axes[0].set_ylabel("y (cm)")
    cb = fig.colorbar(sc, ax=axes[0], ticks=[0, 1, 2, 3])
    cb.set_label("m")
    names = list(culled.kept)
    kept = [len(culled.kept[k]) for k in names]
    axes[1].barh(names, kept, color="#3b7dd8")
    axes[1].axvline(plain.n_sources, color="k", ls="--", lw=1)
    axes[1].text(plain.n_sources, len(names) - 0.5, f" all {plain.n_sources}", va="center")
    axes[1].set_xlabel("source expressions kept")
    axes[1].set_title("coherent culling (§5.1): kept per region")
    fig.tight_layout()
    fig.savefig(os.path.join(out_dir, "blending_dims_culling.png"), dpi=110)
    plt.close(fig)


def dims_picture(problem, thresholds, path):
    """``m`` per template vertex for several residual thresholds (like the paper's Fig. 5b)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    P = problem["vertices"]
    order = np.argsort(P[:, 2])
    cmap = matplotlib.colors.ListedColormap(["#444444", "#3b7dd8", "#f2a33a", "#d6322f"])
    fig, axes = plt.subplots(1, len(thresholds), figsize=(4.2 * len(thresholds) + 1, 5.2))
    for ax, thr in zip(np.atleast_1d(axes), thresholds):
        model = BlendModel.fit(problem["sources"], problem["neutral_index"], problem["triangles"],
                               residual_threshold=thr)
        vd = model.vertex_dims()
        sc = ax.scatter(P[order, 0] * 100, P[order, 1] * 100, c=vd[order], cmap=cmap, vmin=-0.5, vmax=3.5, s=7)
        h = np.bincount(model.dims, minlength=4)
        ax.set_title(f"threshold {thr * 1e3:g} mm\nm=0..3: {h.tolist()}")
        ax.set_aspect("equal")
        ax.set_xlabel("x (cm)")
    np.atleast_1d(axes)[0].set_ylabel("y (cm)")
    fig.colorbar(sc, ax=list(np.atleast_1d(axes)), ticks=[0, 1, 2, 3], fraction=0.025).set_label("m")
    fig.suptitle(f"chosen dimensionality m per vertex ({problem['name']})", y=0.99)
    fig.subplots_adjust(top=0.80, right=0.86)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _error_picture(problem, model, e_plain, e_cull, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    P = problem["vertices"][model.fiducials]
    order = np.argsort(P[:, 2])
    vmax = float(np.percentile(np.r_[e_plain, e_cull], 99) * 1e3)
    fig, axes = plt.subplots(1, 2, figsize=(11, 5))
    for ax, e, title in ((axes[0], e_plain, "no culling"), (axes[1], e_cull, "with culling")):
        sc = ax.scatter(P[order, 0] * 100, P[order, 1] * 100, c=e[order] * 1e3, s=6, vmin=0, vmax=vmax,
                        cmap="magma")
        ax.set_aspect("equal")
        ax.set_title(f"mean local-deformation error, random blends ({title})")
        fig.colorbar(sc, ax=ax).set_label("RMS error (mm)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
