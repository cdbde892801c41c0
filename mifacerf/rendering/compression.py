"""Compressed reflectance fields (the paper's future work, §8): few coefficients per texel.

The ways a renderer can store and light a field are chosen by name from
:data:`COMPRESSION_METHODS` (:func:`compression_method`; the pattern of :mod:`mifacerf.methods`):
``exact`` (the default: the stored field itself, L terms per texel, :mod:`.relight`), ``pca`` (below) and
``sh`` (spherical harmonics of a chosen order, lit in the SH domain with the per-vertex rotation applied
band by band: :mod:`.sh_fields`, :mod:`.ivanic1996`).
Adding one is a :class:`CompressionMethod` (how to compress, load and light a field) plus one
registry line; ``mifacerf compress --method``, ``Renderer(method=...)``, ``mifacerf bench`` (its
``<method><rank>`` configurations) and the demo take it by that name.

Method ``pca`` (per field): every texel's reflectance function, the 3L-vector
``F(x)[l, c]``, is approximated by a mean plus ``rank`` principal components of that
field (an SVD of the N × 3L texel matrix)::

    F(x)[l, c] ≈ μ[l, c] + Σ_k C[x, k] B[k, l, c]

Lighting is projected into the same basis: for a vertex's rotated light-stage weights
L_v (L, 3) (rotated in the light domain, :mod:`.lighting`), ``m_v[c] = Σ_l μ[l,c] L_v[l,c]``
and ``β_v[k, c] = Σ_l B[k,l,c] L_v[l,c]``; a texel's lit colour is then
``Σ_i ĉ_i (m_{v_i} + Σ_k C[x,k] β_{v_i}[k])`` — ``rank`` terms per texel instead of L.
The knob ``rank`` trades size and time for error (measured by ``mifacerf bench``).

Storage: ``fields/<expr>/<cam>.<method><rank>.npz`` (:func:`compressed_path`), for ``pca``
with ``coeff`` (N, rank) float16, ``basis`` (rank, L, 3) and ``mean`` (L, 3) float32, next to the
exact field; ``model.json`` lists the ranks written per method (``"compressed": {"pca": [8]}``).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from ..execution import Executor, worker_cached
from ..formats.files import save_npz_atomic
from ..formats.model import update_model
from ..jitarrays import to_jit
from ..variant import ensure_variant
from .sh_fields import compress_sh, lighting_sh, lit_sh, load_sh

#: the method :func:`compress_model` and ``mifacerf compress`` write unless told (see :data:`COMPRESSION_METHODS`)
DEFAULT_COMPRESS_METHOD = "pca"


def compress_field(rf: np.ndarray, rank: int) -> dict:
    """PCA of one field: rf (N, L, 3) → {coeff (N, K) f16, basis (K, L, 3), mean (L, 3)}; K = min(rank, N, 3L)."""
    return compress_field_ranks(rf, [rank])[rank]


def compress_field_ranks(rf: np.ndarray, ranks) -> dict:
    """:func:`compress_field` for several ranks from one eigen-decomposition: {rank: compressed field}."""
    rf = np.asarray(rf, np.float32)
    n, L = rf.shape[:2]
    X = rf.reshape(n, L * 3).astype(np.float64)
    mean = X.mean(axis=0) if n else np.zeros(L * 3)
    Xc = X - mean
    # eigen-decomposition of the 3L x 3L covariance: cheap for N >> 3L, exact up to rounding
    evecs = np.linalg.eigh(Xc.T @ Xc)[1][:, ::-1] if n else np.zeros((L * 3, 0))
    out = {}
    for rank in ranks:
        k = int(min(rank, n, L * 3))
        basis = evecs[:, :k].T  # (K, 3L), orthonormal rows
        coeff = Xc @ basis.T
        if np.abs(coeff).max(initial=0.0) > 65000:
            raise ValueError("PCA coefficients overflow float16")
        out[rank] = {"coeff": coeff.astype(np.float16), "basis": basis.reshape(k, L, 3).astype(np.float32),
                     "mean": mean.reshape(L, 3).astype(np.float32)}
    return out


def reconstruct(comp: dict, light_directions: np.ndarray | None = None) -> np.ndarray:
    """(N, L, 3) reflectance functions back from a compressed field: ``pca``'s arrays, or ``sh``'s
    coefficients given the model's ``light_directions`` (L, 3) (each light's cell average,
    :func:`.sh_fields.reconstruct_sh`)."""
    if "basis" not in comp:
        from .sh_fields import reconstruct_sh

        if light_directions is None:
            raise ValueError("an sh field is reconstructed per light: give the model's light directions")
        return reconstruct_sh(comp["coeff"], light_directions)
    c = np.asarray(comp["coeff"], np.float32)
    B = comp["basis"].reshape(len(comp["basis"]), -1)
    return (comp["mean"].reshape(1, -1) + c @ B).reshape(len(c), *comp["mean"].shape)


def compressed_path(model_root, expression: str, camera: str, rank: int, method: str) -> Path:
    """Where the ``<method><rank>`` version of field (expression, camera) lives in a model folder."""
    return Path(model_root) / "fields" / expression / f"{camera}.{method}{rank}.npz"


class CompressContext:
    """What every field unit of :func:`compress_model` shares: the model, the method, the ranks. Pickled (sent
    to a worker) it keeps the model's folder; a worker opens it once (:func:`mifacerf.execution.worker_cached`)."""

    def __init__(self, model, method: str, ranks: list[int]):
        self._model, self.root, self.method, self.ranks = model, str(model.root), method, ranks

    def __getstate__(self):
        return {**self.__dict__, "_model": None}

    def model(self):
        if self._model is None:
            import os

            from .model import Model

            stamp = os.stat(Path(self.root) / "model.json").st_mtime_ns
            self._model = worker_cached(("model folder", self.root, stamp), lambda: Model(self.root))
        return self._model


def compress_field_unit(context: CompressContext, unit: tuple) -> tuple[str, str, dict]:
    """One field ``(s, c)`` compressed → (expression, camera, {rank: compressed arrays})."""
    model = context.model()
    f = model.field(*unit)
    return f.expression, f.camera, compression_method(context.method).compress(np.asarray(f.rf), context.ranks,
                                                                                model.light_directions)


def compress_model(model, rank, progress: bool = True, method: str = DEFAULT_COMPRESS_METHOD,
                   executor: Executor | None = None) -> dict:
    """Write the ``<method><rank>`` version of every field of a model (``rank``: an int or several, computed
    from one decomposition per field; ``method``: a :data:`COMPRESSION_METHODS` name that compresses;
    ``progress``: a bar over the fields); returns {"bytes": {rank: ...}, "fields": n}.

    ``executor`` (:mod:`mifacerf.execution`; default: this process) compresses each field as one unit
    (:func:`compress_field_unit`); this process writes the results, in the fields' order, in one transaction."""
    compress = compression_method(method).compress
    if compress is None:
        raise ValueError(f"the {method!r} method renders the stored field itself; there is nothing to compress "
                         f"(choose one of {', '.join(compressing_methods())})")
    ranks = [int(rank)] if np.isscalar(rank) else [int(r) for r in rank]
    jobs = [(s, c) for s in range(len(model.expressions)) for c in range(len(model.cameras)) if model.has_field(s, c)]
    total = {r: 0 for r in ranks}

    def add_ranks(meta):     # under the model's lock, on model.json as it is on disk
        done = sorted(set(meta.get("compressed", {}).get(method, [])) | set(ranks))
        meta["compressed"] = {**meta.get("compressed", {}), method: done}

    # one transaction: the files appear, listed in model.json, all at once (a kill leaves the model as it was)
    with update_model(model, what="compress") as update:
        done = (executor or Executor()).imap(compress_field_unit, jobs, CompressContext(model, method, ranks),
                                             desc=f"compress {method}", unit="field", progress=progress)
        for expression, camera, comps in done:
            for r, comp in comps.items():
                path = compressed_path(update.root, expression, camera, r, method)
                save_npz_atomic(path, compressed=False, **comp)
                update.add(path)
                total[r] += path.stat().st_size
        update.update(add_ranks)
    return {"bytes": total if len(ranks) > 1 else total[ranks[0]], "fields": len(jobs)}


def lit_texels_pca(coeff_device, rank: int, texels: np.ndarray, vertex_ids: np.ndarray, coef: np.ndarray,
                   m_v: np.ndarray, beta_v: np.ndarray) -> np.ndarray:
    """Lit colour (N, 3) of ``texels`` from PCA coefficients (Dr.Jit; ``rank`` terms per texel).

    ``coeff_device``: flat Float16 (rows, rank); ``m_v`` (V, 3) and ``beta_v`` (V, rank, 3) the
    per-vertex lighting projected on the field's mean and basis; ``coef`` (N, 3) the normalised
    vertex weights ĉ.
    """
    import drjit as dr

    mi = ensure_variant()
    n = len(texels)
    if n == 0:
        return np.zeros((0, 3), np.float32)
    Float, UInt32 = mi.Float, mi.UInt32
    F16 = type(coeff_device)
    row = to_jit(UInt32, np.asarray(texels, np.uint32) * np.uint32(max(rank, 1)))
    vid = [to_jit(UInt32, np.asarray(vertex_ids[:, k], np.uint32)) for k in range(3)]
    cf = [to_jit(Float, coef[:, k]) for k in range(3)]
    mv = to_jit(Float, np.asarray(m_v).reshape(-1))
    bv = to_jit(Float, np.asarray(beta_v).reshape(-1))
    out = []
    for ch in range(3):
        acc = Float(0)
        for k in range(3):
            acc += cf[k] * dr.gather(Float, mv, vid[k] * 3 + ch)
        out.append(acc)
    stride = rank * 3
    for j in range(rank):
        c = Float(dr.gather(F16, coeff_device, row + j))
        for ch in range(3):
            b = (cf[0] * dr.gather(Float, bv, vid[0] * stride + j * 3 + ch)
                 + cf[1] * dr.gather(Float, bv, vid[1] * stride + j * 3 + ch)
                 + cf[2] * dr.gather(Float, bv, vid[2] * stride + j * 3 + ch))
            out[ch] = dr.fma(c, b, out[ch])
    dr.eval(*out)
    return np.stack([np.asarray(o) for o in out], axis=1)


# ------------------------------------------------------------------ the methods by name
def _load_exact(model, s: int, c: int, rank: int, lights):
    from .relight import to_device_words

    rf = np.asarray(model.field(s, c).rf)
    return to_device_words(rf if lights is None else rf[:, lights])


def _lit_exact(data, n_lights: int, texels, vertex_ids, coef, lighting, keep):
    from .relight import lit_texels

    return lit_texels(data, n_lights, texels, vertex_ids, coef, lighting, keep, later=True)


class PcaField:
    """A ``pca`` field ready to light: ``comp`` its arrays (:func:`compress_field`); ``device`` the
    coefficients on the device (flat Float16, what :func:`lit_texels_pca` reads); ``halves`` (N, (K+1)·3)
    float16 the same coefficients laid out as the exact kernel's rows (:func:`_rows_pca`). The two forms
    are made on first use: a renderer reads one of them."""

    def __init__(self, comp: dict):
        self.comp = comp
        self._device = self._halves = None

    @property
    def rank(self) -> int:
        return int(self.comp["basis"].shape[0])

    @property
    def device(self):
        if self._device is None:
            from .relight import to_device_f16

            self._device = to_device_f16(self.comp["coeff"])
        return self._device

    @property
    def halves(self) -> np.ndarray:
        if self._halves is None:
            c = np.asarray(self.comp["coeff"], np.float16)
            rows = np.empty((len(c), self.rank + 1, 3), np.float16)
            rows[:, 0] = 1.0                      # the mean's term (1 is exact in float16)
            rows[:, 1:] = c[:, :, None]            # each coefficient once per colour
            rows.flags.writeable = False
            self._halves = rows.reshape(len(c), -1)
        return self._halves

    def projected(self, lighting, keep) -> tuple[np.ndarray, np.ndarray]:
        """``m_v`` (V, 3) and ``β_v`` (V, K, 3): the per-vertex lighting (V, L, 3) (of the lights ``keep``,
        None for all) projected on the field's mean and basis."""
        lighting = np.asarray(lighting, np.float32)
        mean, basis = self.comp["mean"], self.comp["basis"]
        if keep is not None:
            mean, basis = mean[keep], basis[:, keep]
        # per colour, (V, L) @ (L, K + 1): one BLAS product (einsum's loops took 8 ms a field, 140 ms a frame)
        mb = np.concatenate([mean[None], basis], axis=0).astype(np.float32)       # (K + 1, L, 3)
        out = np.matmul(lighting.transpose(2, 0, 1), mb.transpose(2, 1, 0))       # (3, V, K + 1)
        out = out.transpose(1, 2, 0)                                                # (V, K + 1, 3)
        return out[:, 0], out[:, 1:]


def _load_pca(model, s: int, c: int, rank: int, lights):
    return PcaField(model.compressed_field(s, c, rank, "pca"))


def _lit_pca(data, n_lights: int, texels, vertex_ids, coef, lighting, keep):
    m_v, beta_v = data.projected(lighting, keep)
    return lit_texels_pca(data.device, data.rank, texels, vertex_ids, coef, m_v, beta_v)


def _rows_halves(data, lighting, keep):
    """A field of :class:`.relight.HalfWords` (``exact``: L lights; ``sh``: J coefficients) as the CPU
    kernel's rows, against the per-vertex lighting's rows."""
    return data.halves, lighting.rows, keep


def _rows_pca(data, lighting, keep):
    """A ``pca`` field as the exact kernel's rows: the texel's row (1, C_1 … C_K), each once per colour,
    against the vertex's (m_v, β_v) — ``Σ_i ĉ_i (m_{v_i} + Σ_k C[x, k] β_{v_i}[k])``, the same sum."""
    m_v, beta_v = data.projected(lighting, keep)
    light = np.concatenate([m_v[:, None], beta_v], axis=1).astype(np.float32)
    return data.halves, np.ascontiguousarray(light.reshape(len(light), -1)), None


def _compress_pca(rf, ranks, light_directions):
    return compress_field_ranks(rf, ranks)


@dataclass(frozen=True)
class CompressionMethod:
    """One way of storing and lighting a reflectance field (an entry of :data:`COMPRESSION_METHODS`).

    * ``compress(rf (N, L, 3), ranks, light_directions (L, 3)) -> {rank: {name: array}}``: the arrays
      written to :func:`compressed_path` by :func:`compress_model`; None for the stored field itself;
    * ``load(model, s, c, rank, lights) -> data``: field (source ``s``, camera ``c``) ready to light
      (device arrays; ``lights`` a light subset or None);
    * ``lit(data, n_lights, texels (N,), vertex_ids (N, 3), coef (N, 3), lighting (V, L, 3), keep) -> (N, 3)``:
      the lit colour of ``texels`` under the per-vertex light-stage weights ``lighting`` (``keep``: the
      lights kept, None for all), or a function returning it (a launched kernel, read back when called: the
      renderer launches every chunk's kernel before it reads the first);
    * ``light_subsets``: whether ``load`` accepts a light subset;
    * ``lighting(renderer, env, rotations (P, 3, 3)) -> (P, K, 3)``: the per-(vertex, source) lighting
      ``lit`` takes, when it is not the light stage's rotated basis (:mod:`.lighting`, None): ``sh``
      rotates the environment's coefficients (:mod:`.sh_fields`). Negligible lights are skipped only in
      the light stage's basis;
    * ``rows(data, lighting (DeviceLighting), keep) -> (field (N, J) float16, light (V, J) float32, ids)``:
      the same sum as ``lit`` laid out for the CPU kernel (:func:`.relight_cpu.lit_images`: a texel's
      row of J halves against its vertices' rows of J floats, ``ids`` the J/3 lights kept or None), used
      on the CPU variants where Numba is importable (:func:`.relight.cpu_kernel`); None: ``lit`` only.
    """

    compress: Callable | None
    load: Callable
    lit: Callable
    light_subsets: bool = False
    lighting: Callable | None = None
    rows: Callable | None = None


#: how a renderer stores and lights a field: name → :class:`CompressionMethod`; the first is the default
COMPRESSION_METHODS = {
    "exact": CompressionMethod(None, _load_exact, _lit_exact, light_subsets=True, rows=_rows_halves),
    "pca": CompressionMethod(_compress_pca, _load_pca, _lit_pca, rows=_rows_pca),
    "sh": CompressionMethod(compress_sh, load_sh, lit_sh, lighting=lighting_sh, rows=_rows_halves),
}
DEFAULT_COMPRESSION_METHOD = "exact"


def compression_method(method: str = DEFAULT_COMPRESSION_METHOD) -> CompressionMethod:
    """The :data:`COMPRESSION_METHODS` entry named ``method`` (ValueError listing the choices otherwise)."""
    from ..methods import lookup

    return lookup(COMPRESSION_METHODS, method, "compression")


def compressing_methods() -> list[str]:
    """The names of the methods that write a compressed copy (``mifacerf compress --method``)."""
    return [name for name, m in COMPRESSION_METHODS.items() if m.compress is not None]
