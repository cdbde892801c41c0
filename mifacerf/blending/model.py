"""``BlendModel``: per-vertex blend weights for arbitrary target deformations (paper §5, §5.1).

Fitting (offline, NumPy/SciPy, a loop over fiducial vertices):

1. neighbourhoods (graph distance <= ``rings`` = 2 on the template's triangles);
2. coherent culling per region (optional, :mod:`~mifacerf.blending.culling`) → the
   sources each fiducial may use;
3. per fiducial: local deformation vectors of its allowed sources (Horn onto the
   neutral), PCA with the residual-threshold dimensionality ``m <= max_dim``
   (:mod:`~mifacerf.blending.local_space`), m-D triangulation with its robustness
   rules (:mod:`~mifacerf.blending.delaunay`).

Evaluation (:meth:`BlendModel.weights`): the Dr.Jit kernel
(:mod:`~mifacerf.blending.weights`) over all (frame × fiducial) pairs, or the
per-vertex NumPy/SciPy reference (``method="reference"``).

**Non-fiducial vertices** (``fiducial_mask`` False) get an inverse-distance blend
of the weights of their (up to) 3 nearest fiducials in the neutral mesh, chosen
among the fiducials with exactly the same set of regions when there is at least
one such fiducial (so culling is respected), otherwise among all fiducials.  The
union of their sources is cut to the 4 largest weights and renormalised (the cut
mass is usually zero; when it is not, the weights of that vertex are slightly
discontinuous).

**Sparse output**: K = 4 slots per (frame, vertex), sorted by decreasing weight;
unused slots have weight 0 and repeat the id of slot 0 (always a valid source id).
"""
from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ..blas import single_threaded_blas
from .culling import CullingResult, allowed_sources, cull_regions, load_regions
from .deformation import align_neighbourhoods
from .delaunay import DUP_TOL, LocalTriangulation, triangulate
from .local_space import LocalSpace, fit_local_space
from .neighbourhoods import Neighbourhoods, neighbourhoods
from .weights import GroupTables

__all__ = ["BlendModel", "SparseWeights", "K_MAX", "DEFAULT_RESIDUAL_THRESHOLD", "DEFAULT_SIMILARITY_THRESHOLD",
           "DEFAULT_DUP_TOL"]

#: slots per (frame, vertex) in SparseWeights
K_MAX = 4
#: default RMS PCA residual (metres) below which a dimension is dropped
DEFAULT_RESIDUAL_THRESHOLD = 5e-5
#: default RMS distance (metres) under which two sources count as duplicates at a vertex
DEFAULT_DUP_TOL = 1e-6
#: default RMS distance (metres) under which two expressions count as similar in a region
DEFAULT_SIMILARITY_THRESHOLD = 5e-4
FORMAT_VERSION = 1


@dataclass
class SparseWeights:
    """Blend weights of ``T`` frames × ``V`` vertices.

    Attributes
    ----------
    indices : ndarray ``(T, V, K)`` int32   source ids (always valid ids, also in unused slots)
    weights : ndarray ``(T, V, K)`` float32 non-negative, summing to 1 over K, sorted decreasing
    """

    indices: np.ndarray
    weights: np.ndarray

    def dense(self, n_sources: int) -> np.ndarray:
        """``(T, V, n_sources)`` float32."""
        T, V, K = self.indices.shape
        out = np.zeros((T, V, n_sources), dtype=np.float32)
        t, v = np.meshgrid(np.arange(T), np.arange(V), indexing="ij")
        for k in range(K):
            np.add.at(out, (t, v, self.indices[:, :, k]), self.weights[:, :, k])
        return out


def _as_meshes(x, name, V=None):
    a = np.asarray(x)
    if a.ndim != 3 or a.shape[2] != 3 or (V is not None and a.shape[1] != V):
        want = "(n, V, 3)" if V is None else f"(n, {V}, 3)"
        raise ValueError(f"{name} must have shape {want}; got {a.shape}")
    a = a.astype(np.float64, copy=False)
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} {a.shape} contain non-finite values")
    return a


def _sort_slots(ids, w):
    order = np.argsort(-w, axis=-1, kind="stable")
    ids = np.take_along_axis(ids, order, axis=-1)
    w = np.take_along_axis(w, order, axis=-1)
    ids = np.where(w > 0, ids, ids[..., :1])
    return ids, w


def _topk_merge(ids, w, k):
    """Merge duplicate ids along the last axis (sum their weights), keep the k largest, renormalise."""
    same = ids[..., :, None] == ids[..., None, :]
    total = np.einsum("...ij,...j->...i", same.astype(w.dtype), w)
    first = np.argmax(same, axis=-1) == np.arange(ids.shape[-1])
    total = np.where(first, total, 0.0)
    order = np.argsort(-total, axis=-1, kind="stable")[..., :k]
    ids = np.take_along_axis(ids, order, axis=-1)
    tw = np.take_along_axis(total, order, axis=-1)
    s = tw.sum(axis=-1, keepdims=True)
    tw = tw / np.where(s > 0, s, 1.0)
    return _sort_slots(ids, tw)


class BlendModel:
    """Per-vertex blend weights (paper §5, §5.1).  Build with :meth:`fit` or :meth:`load`.

    Main attributes (NumPy):

    ``n_sources``, ``n_vertices``, ``neutral_index``; ``neutral`` ``(V, 3)``; ``triangles`` ``(F_t, 3)``;
    ``nbhd`` (:class:`Neighbourhoods`); ``fiducials`` ``(F,)`` vertex ids; ``dims`` ``(F,)`` the chosen
    ``m``; ``spaces`` / ``triangulations``: one :class:`LocalSpace` / :class:`LocalTriangulation` per
    fiducial; ``culling`` (:class:`CullingResult` or None) with ``kept`` per region; ``allowed``: the
    source ids each fiducial may use.
    """

    def __init__(self, *, neutral, triangles, neutral_index, n_sources, nbhd, fiducials, spaces,
                 triangulations, allowed, culling, params):
        self.neutral = np.asarray(neutral, dtype=np.float64)
        self.triangles = np.asarray(triangles, dtype=np.int64)
        self.neutral_index = int(neutral_index)
        self.n_sources = int(n_sources)
        self.nbhd = nbhd
        self.fiducials = np.asarray(fiducials, dtype=np.int64)
        self.spaces = list(spaces)
        self.triangulations = list(triangulations)
        self.allowed = [np.asarray(a, dtype=np.int64) for a in allowed]
        self.culling = culling
        self.params = dict(params)
        self._groups = None
        self._build_interpolation()

    # ------------------------------------------------------------------------------------ properties
    @property
    def n_vertices(self) -> int:
        return int(self.neutral.shape[0])

    @property
    def dims(self) -> np.ndarray:
        return np.array([t.m for t in self.triangulations], dtype=np.int64)

    @property
    def kept(self) -> dict:
        """Kept source ids per region (empty without culling)."""
        return {} if self.culling is None else dict(self.culling.kept)

    def vertex_dims(self) -> np.ndarray:
        """``(V,)`` chosen ``m`` per template vertex (-1 for non-fiducial vertices)."""
        out = np.full(self.n_vertices, -1, dtype=np.int64)
        out[self.fiducials] = self.dims
        return out

    # ------------------------------------------------------------------------------------------ fit
    @classmethod
    def fit(cls, sources, neutral_index: int, triangles, fiducial_mask=None, regions=None,
            residual_threshold: float = DEFAULT_RESIDUAL_THRESHOLD,
            similarity_threshold: float = DEFAULT_SIMILARITY_THRESHOLD, max_dim: int = 3,
            rings: int = 2, dup_tol: float = DEFAULT_DUP_TOL) -> "BlendModel":
        """Fit the model.

        Parameters
        ----------
        sources : array_like ``(n_src, V, 3)``
            Source expressions (template vertices, world metres) in correspondence.
        neutral_index : int
            Which source is the neutral expression.
        triangles : array_like ``(F_t, 3)``
            Template triangles (the graph of the neighbourhoods).
        fiducial_mask : array_like ``(V,)`` bool, optional
            Vertices whose weights are computed (default all); the others are interpolated (module doc).
        regions : dict[str, array of vertex ids] or path of a region JSON file, optional
            Culling regions (:mod:`~mifacerf.blending.culling`); None: no culling.
        residual_threshold : float
            RMS PCA residual in metres (:mod:`~mifacerf.blending.local_space`).
        similarity_threshold : float
            RMS region distance in metres (:mod:`~mifacerf.blending.culling`).
        max_dim : int
            Largest ``m`` (0..3).
        rings : int
            Neighbourhood radius in edges (paper: 2).
        dup_tol : float
            Sources whose projected local deformations differ by at most this RMS distance per
            neighbourhood vertex (metres) are merged (:mod:`~mifacerf.blending.delaunay`, rule 1).
        """
        S = _as_meshes(sources, "sources")
        n, V = S.shape[:2]
        if not 0 <= int(neutral_index) < n:
            raise ValueError(f"neutral_index {neutral_index} out of range for {n} sources")
        if not 0 <= max_dim <= 3:
            raise ValueError(f"max_dim must be in 0..3; got {max_dim}")
        if residual_threshold < 0 or similarity_threshold < 0:
            raise ValueError("thresholds must be non-negative")
        neutral_index = int(neutral_index)
        nb = neighbourhoods(triangles, V, rings)
        if fiducial_mask is None:
            fid = np.arange(V)
        else:
            fm = np.asarray(fiducial_mask, dtype=bool)
            if fm.shape != (V,):
                raise ValueError(f"fiducial_mask must have shape ({V},); got {fm.shape}")
            fid = np.nonzero(fm)[0]
            if fid.size == 0:
                raise ValueError("fiducial_mask selects no vertex")
        if isinstance(regions, (str, os.PathLike)):
            regions = load_regions(regions)
        culling = cull_regions(S, neutral_index, regions, similarity_threshold) if regions else None
        allowed = allowed_sources(culling, n, fid)
        neutral = S[neutral_index]
        chunk = max(1, int(2e7 // max(n * nb.index.shape[1] * 3, 1)))
        with single_threaded_blas():
            spaces, tris = cls._fit_vertices(S, nb, fid, allowed, neutral_index, residual_threshold, max_dim,
                                             dup_tol, chunk)
        params = dict(residual_threshold=float(residual_threshold),
                      similarity_threshold=float(similarity_threshold), max_dim=int(max_dim),
                      rings=int(rings), dup_tol=float(dup_tol))
        return cls(neutral=neutral, triangles=triangles, neutral_index=neutral_index, n_sources=n, nbhd=nb,
                   fiducials=fid, spaces=spaces, triangulations=tris, allowed=allowed, culling=culling,
                   params=params)

    @staticmethod
    def _fit_vertices(S, nb, fid, allowed, neutral_index, residual_threshold, max_dim, dup_tol, chunk):
        """PCA + triangulation of every fiducial (a loop; fitting is offline)."""
        spaces, tris = [], []
        neutral = S[neutral_index]
        for c0 in range(0, fid.size, chunk):
            rows = fid[c0:c0 + chunk]
            aligned, _ = align_neighbourhoods(S, neutral, nb, rows=rows)       # (n, c, K, 3)
            mask = nb.mask[rows]
            for i in range(rows.size):
                a = allowed[c0 + i]
                sp = fit_local_space(aligned[a, i], mask[i], residual_threshold, max_dim)
                # metres RMS per neighbourhood vertex → PCA units (a floor catches exact duplicates)
                tol = max(dup_tol * np.sqrt(mask[i].sum()) / sp.scale, DUP_TOL)
                tri = triangulate(sp.coords, ids=a, preferred=neutral_index, dup_tol=tol)
                if tri.m < sp.m:
                    sp = LocalSpace(mean=sp.mean, basis=sp.basis[: tri.m], scale=sp.scale,
                                    coords=sp.coords[:, : tri.m], residuals=sp.residuals, m=tri.m)
                spaces.append(sp)
                tris.append(tri)
        return spaces, tris

    # --------------------------------------------------------------------------- non-fiducial vertices
    def _region_key(self):
        if self.culling is None:
            return np.zeros(self.n_vertices, dtype=np.int64)
        _, key = np.unique(self.culling.membership, axis=0, return_inverse=True)
        return key.ravel()

    def _build_interpolation(self):
        V = self.n_vertices
        is_fid = np.zeros(V, dtype=bool)
        is_fid[self.fiducials] = True
        others = np.nonzero(~is_fid)[0]
        self.fiducial_row = np.full(V, -1, dtype=np.int64)
        self.fiducial_row[self.fiducials] = np.arange(self.fiducials.size)
        self.interp_vertices = others
        self.interp_index = np.zeros((others.size, 3), dtype=np.int64)
        self.interp_weight = np.zeros((others.size, 3))
        if others.size == 0:
            return
        key = self._region_key()
        P = self.neutral
        k = min(3, self.fiducials.size)
        for kv in np.unique(key[others]):
            sel = others[key[others] == kv]
            cand = np.nonzero(key[self.fiducials] == kv)[0]
            if cand.size == 0:
                cand = np.arange(self.fiducials.size)
            kk = min(k, cand.size)
            d, j = cKDTree(P[self.fiducials[cand]]).query(P[sel], k=kk)
            d = d.reshape(sel.size, kk)
            j = cand[j.reshape(sel.size, kk)]
            w = 1.0 / np.maximum(d, 1e-12)
            w /= w.sum(axis=1, keepdims=True)
            rows = np.searchsorted(others, sel)
            self.interp_index[rows, :kk] = j
            self.interp_index[rows, kk:] = j[:, :1]
            self.interp_weight[rows, :kk] = w

    # ------------------------------------------------------------------------------------ evaluation
    def group_tables(self) -> dict:
        """``{m: GroupTables}`` for m in 1..3 (built once, cached)."""
        if self._groups is not None:
            return self._groups
        groups = {}
        dims = self.dims
        Kw = self.nbhd.index.shape[1]
        for m in (1, 2, 3):
            rows = np.nonzero(dims == m)[0]
            if rows.size == 0:
                continue
            G = rows.size
            vid = self.fiducials[rows]
            nb_idx = self.nbhd.index[vid]
            nb_w = self.nbhd.mask[vid].astype(np.float64)
            q = self.neutral[nb_idx]
            cq = np.einsum("gk,gkc->gc", nb_w, q) / nb_w.sum(axis=1, keepdims=True)
            ref = (q - cq[:, None, :]) * nb_w[..., None]
            basis = np.zeros((G, m, Kw, 3))
            z0 = np.zeros((G, m))
            Ts, rs, nbrs, sids, fps, fss, ghosts = [], [], [], [], [], [], []
            s_start = np.zeros(G, np.int64); s_first = np.zeros(G, np.int64); s_count = np.zeros(G, np.int64)
            f_first = np.zeros(G, np.int64); f_count = np.zeros(G, np.int64)
            so = fo = 0
            for i, f in enumerate(rows):
                sp, tri = self.spaces[f], self.triangulations[f]
                basis[i] = sp.basis[:m] / sp.scale
                z0[i] = np.einsum("kc,mkc->m", q[i] - sp.mean, basis[i] * nb_w[i][None, :, None])
                S_ = tri.n_simplices
                Ts.append(tri.transform[:, :m, :])
                rs.append(tri.transform[:, m, :])
                nbrs.append(np.where(tri.neighbors >= 0, tri.neighbors + so, -1))
                sids.append(tri.point_ids[tri.simplices])
                ghosts.append(tri.ghost.astype(np.int32))
                s_start[i], s_first[i], s_count[i] = tri.start + so, so, S_
                fps.append(tri.points[tri.facets])
                fss.append(tri.point_ids[tri.facets])
                f_first[i], f_count[i] = fo, tri.facets.shape[0]
                so += S_
                fo += tri.facets.shape[0]
            g = GroupTables(m=m, nb_idx=nb_idx, nb_w=nb_w, ref=ref, basis=basis, z0=z0,
                            T=np.concatenate(Ts), r=np.concatenate(rs), nbr=np.concatenate(nbrs),
                            sid=np.concatenate(sids), ghost=np.concatenate(ghosts), s_start=s_start, s_first=s_first, s_count=s_count,
                            fpts=np.concatenate(fps), fsid=np.concatenate(fss), f_first=f_first,
                            f_count=f_count)
            g.check(self.n_vertices, self.n_sources)
            groups[m] = (rows, g)
        self._groups = groups
        return groups

    def fiducial_weights(self, targets, method: str = "drjit", precision: str = "float64"):
        """Weights at the fiducials: ``(ids (T, F, 4) int32, w (T, F, 4) float64)`` (slots unsorted).

        ``method``: ``"drjit"`` (vectorised; falls back to the reference on scalar variants) or
        ``"reference"`` (per-vertex NumPy/SciPy).  ``precision`` applies to ``"drjit"``.
        """
        X = _as_meshes(targets, "targets", self.n_vertices)
        if method not in ("drjit", "reference"):
            raise ValueError(f"method must be 'drjit' or 'reference'; got {method!r}")
        B = None
        if method == "drjit":
            from .weights import backend
            B = backend()
        if method == "reference" or B is None:
            from .reference import reference_fiducial_weights
            return reference_fiducial_weights(self, X)
        from .weights import evaluate_group

        Tn, F = X.shape[0], self.fiducials.size
        ids = np.zeros((Tn, F, K_MAX), dtype=np.int32)
        w = np.zeros((Tn, F, K_MAX), dtype=np.float64)
        zero = np.nonzero(self.dims == 0)[0]
        if zero.size:
            rep = np.array([self.triangulations[f].point_ids[0] for f in zero], dtype=np.int32)
            ids[:, zero, :] = rep[None, :, None]
            w[:, zero, 0] = 1.0
        groups = self.group_tables()
        if groups:
            Xvt = np.ascontiguousarray(np.transpose(X - self.neutral, (1, 0, 2)))
            for m, (rows, g) in groups.items():
                gi, gw = evaluate_group(g, Xvt, precision=precision, B=B)
                ids[:, rows, : m + 1] = np.transpose(gi, (1, 0, 2))
                ids[:, rows, m + 1:] = np.transpose(gi[:, :, :1], (1, 0, 2))
                w[:, rows, : m + 1] = np.transpose(gw, (1, 0, 2))
        return ids, w

    def weights(self, targets, method: str = "drjit", precision: str = "float64") -> SparseWeights:
        """Blend weights of target meshes.

        Parameters
        ----------
        targets : array_like ``(T, V, 3)``
            Target expressions (template vertices, world metres; any rigid pose).
        method : "drjit" | "reference"
        precision : "float32" | "float64"   working precision of the Dr.Jit kernel

        Returns
        -------
        SparseWeights with ``indices`` ``(T, V, 4)`` int32 and ``weights`` ``(T, V, 4)`` float32.
        """
        fi, fw = self.fiducial_weights(targets, method=method, precision=precision)
        Tn, V = fi.shape[0], self.n_vertices
        ids = np.zeros((Tn, V, K_MAX), dtype=np.int32)
        w = np.zeros((Tn, V, K_MAX), dtype=np.float64)
        fi, fw = _sort_slots(fi, fw)
        ids[:, self.fiducials] = fi
        w[:, self.fiducials] = fw
        U = self.interp_vertices.size
        if U:
            step = max(1, int(4e6 // max(U * 12, 1)))
            for t0 in range(0, Tn, step):
                ci = fi[t0:t0 + step][:, self.interp_index]                  # (t, U, 3, 4)
                cw = fw[t0:t0 + step][:, self.interp_index] * self.interp_weight[None, :, :, None]
                ci = ci.reshape(ci.shape[0], U, 12)
                cw = cw.reshape(cw.shape[0], U, 12)
                mi, mw = _topk_merge(ci, cw, K_MAX)
                ids[t0:t0 + step, self.interp_vertices] = mi
                w[t0:t0 + step, self.interp_vertices] = mw
        return SparseWeights(indices=ids, weights=w.astype(np.float32))

    def dense_weights(self, targets, method: str = "drjit", precision: str = "float64") -> np.ndarray:
        """``(T, V, n_src)`` float32 dense weights (convenience; see :meth:`weights`)."""
        return self.weights(targets, method=method, precision=precision).dense(self.n_sources)

    # ---------------------------------------------------------------------------------- diagnostics
    def weight_lipschitz(self) -> np.ndarray:
        """``(F,)`` per fiducial: the largest rate of change of any weight per metre of local deformation.

        ``max_s,j |∇ b_j|`` over the vertex's non-ghost simplices, divided by the PCA scale (0 for
        ``m = 0``).  A weight changes by at most this much times the change of the deformation vector
        (Euclidean norm of the ``3|V|``-vector, metres).  Thin simplices make it large: float32 evaluation
        (about 1e-8 m of rounding in the deformation) agrees with float64 only to ``1e-8 × this``.
        """
        out = np.zeros(self.fiducials.size)
        for f, (sp, tri) in enumerate(zip(self.spaces, self.triangulations)):
            if tri.m == 0:
                continue
            T = tri.transform[~tri.ghost, : tri.m, :]
            g = np.concatenate([T, -T.sum(axis=1, keepdims=True)], axis=1)
            out[f] = np.linalg.norm(g, axis=2).max() / sp.scale
        return out

    def local_deformations(self, meshes) -> np.ndarray:
        """Local deformation vectors at the fiducials: ``(N, F, K, 3)`` for meshes ``(N, V, 3)``.

        Padding entries are zero.  ``Σ_i w_i D_i`` against ``D_target`` is the reconstruction error of
        the "Measure" paragraph.
        """
        X = _as_meshes(meshes, "meshes", self.n_vertices)
        aligned, _ = align_neighbourhoods(X, self.neutral, self.nbhd, rows=self.fiducials)
        return aligned * self.nbhd.mask[self.fiducials][None, :, :, None]

    def coords(self, targets) -> np.ndarray:
        """PCA coordinates ``(T, F, 3)`` of targets at the fiducials (NaN beyond each vertex's ``m``)."""
        from .reference import vertex_coords

        X = _as_meshes(targets, "targets", self.n_vertices)
        out = np.full((X.shape[0], self.fiducials.size, 3), np.nan)
        for f in range(self.fiducials.size):
            m = self.triangulations[f].m
            if m:
                out[:, f, :m] = vertex_coords(self, f, X)
        return out

    # ---------------------------------------------------------------------------------------- I/O
    def save(self, path) -> None:
        """Write the model to an ``.npz`` (format documented in ``docs/blending.md``)."""
        F = self.fiducials.size
        tris, sps = self.triangulations, self.spaces
        Kw = self.nbhd.index.shape[1]
        off = lambda sizes: np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)

        def pad(a, shape):
            out = np.full(shape, -1 if a.dtype.kind == "i" else 0, dtype=a.dtype)
            out[tuple(slice(0, s) for s in a.shape)] = a
            return out

        basis = np.zeros((F, 3, Kw, 3))
        for f, sp in enumerate(sps):
            basis[f, : sp.m] = sp.basis
        data = dict(
            format_version=np.int64(FORMAT_VERSION),
            n_sources=np.int64(self.n_sources), neutral_index=np.int64(self.neutral_index),
            params_json=np.array(__import__("json").dumps(self.params)),
            neutral=self.neutral, triangles=self.triangles,
            nb_index=self.nbhd.index, nb_count=self.nbhd.count, fiducials=self.fiducials,
            dims=self.dims,
            pca_mean=np.stack([sp.mean for sp in sps]), pca_basis=basis,
            pca_scale=np.array([sp.scale for sp in sps]),
            pca_residuals=np.stack([pad(np.asarray(sp.residuals), (4,)) for sp in sps]),
            allowed=np.stack([np.isin(np.arange(self.n_sources), a) for a in self.allowed]),
            tri_p_off=off([t.points.shape[0] for t in tris]),
            tri_points=np.concatenate([pad(t.points, (t.points.shape[0], 3)) for t in tris]),
            tri_point_ids=np.concatenate([t.point_ids for t in tris]),
            tri_merged=np.stack([pad(t.merged, (self.n_sources,)) for t in tris]),
            tri_s_off=off([t.n_simplices for t in tris]),
            tri_simplices=np.concatenate([pad(t.simplices, (t.n_simplices, 4)) for t in tris]),
            tri_transform=np.concatenate([pad(t.transform, (t.n_simplices, 4, 3)) for t in tris]),
            tri_neighbors=np.concatenate([pad(t.neighbors, (t.n_simplices, 4)) for t in tris]),
            tri_ghost=np.concatenate([t.ghost for t in tris]),
            tri_h_off=off([t.facets.shape[0] for t in tris]),
            tri_facets=np.concatenate([pad(t.facets, (t.facets.shape[0], 3)) for t in tris]),
            tri_start=np.array([t.start for t in tris], dtype=np.int64),
            tri_method=np.array([t.method for t in tris]),
        )
        if self.culling is not None:
            kept = np.zeros((len(self.culling.names), self.n_sources), dtype=bool)
            for k, name in enumerate(self.culling.names):
                kept[k, self.culling.kept[name]] = True
            data.update(region_names=np.array(self.culling.names), region_membership=self.culling.membership,
                        region_kept=kept)
        np.savez_compressed(os.fspath(path), **data)

    @classmethod
    def load(cls, path) -> "BlendModel":
        """Read a model written by :meth:`save`."""
        import json

        with np.load(os.fspath(path), allow_pickle=False) as z:
            d = {k: z[k] for k in z.files}
        if int(d["format_version"]) != FORMAT_VERSION:
            raise ValueError(f"{path}: blend model format {int(d['format_version'])}, expected {FORMAT_VERSION}")
        F = d["fiducials"].size
        n = int(d["n_sources"])
        spaces, tris = [], []
        for f in range(F):
            m = int(d["dims"][f])
            p0, p1 = d["tri_p_off"][f], d["tri_p_off"][f + 1]
            s0, s1 = d["tri_s_off"][f], d["tri_s_off"][f + 1]
            h0, h1 = d["tri_h_off"][f], d["tri_h_off"][f + 1]
            pts = d["tri_points"][p0:p1, :m]
            sp_basis = d["pca_basis"][f, :m]
            tris.append(LocalTriangulation(
                m=m, points=pts, point_ids=d["tri_point_ids"][p0:p1],
                merged=d["tri_merged"][f][d["tri_merged"][f] >= 0],
                simplices=d["tri_simplices"][s0:s1, : m + 1], transform=d["tri_transform"][s0:s1, : m + 1, :m],
                neighbors=d["tri_neighbors"][s0:s1, : m + 1], ghost=d["tri_ghost"][s0:s1].astype(bool),
                facets=d["tri_facets"][h0:h1, :m],
                start=int(d["tri_start"][f]), method=str(d["tri_method"][f])))
            spaces.append(LocalSpace(mean=d["pca_mean"][f], basis=sp_basis, scale=float(d["pca_scale"][f]),
                                     coords=np.zeros((0, m)), residuals=d["pca_residuals"][f], m=m))
        culling = None
        if "region_names" in d:
            names = tuple(str(s) for s in d["region_names"])
            kept = {nm: np.nonzero(d["region_kept"][k])[0] for k, nm in enumerate(names)}
            culling = CullingResult(kept=kept, membership=d["region_membership"], names=names)
        return cls(neutral=d["neutral"], triangles=d["triangles"], neutral_index=int(d["neutral_index"]),
                   n_sources=n, nbhd=Neighbourhoods(d["nb_index"], d["nb_count"]), fiducials=d["fiducials"],
                   spaces=spaces, triangulations=tris, allowed=[np.nonzero(a)[0] for a in d["allowed"]],
                   culling=culling, params=json.loads(str(d["params_json"])))
