"""Blend weights for arbitrary deformations and coherent expression culling (paper §5, §5.1).

Public API (NumPy in, NumPy out; shapes in the docstrings)::

    from mifacerf.blending import BlendModel, local_rotations
    model = BlendModel.fit(sources, neutral_index, triangles, fiducial_mask=None, regions=None,
                           residual_threshold=5e-5, similarity_threshold=5e-4, max_dim=3)
    w = model.weights(targets)          # SparseWeights: indices/weights (T, V, 4)
    W = model.dense_weights(targets)    # (T, V, n_src)
    model.save("model.npz"); BlendModel.load("model.npz")
    R = local_rotations(target, source, model.nbhd)   # (V, 3, 3), paper §6.1

Horn's (1987) absolute orientation lives on the ground floor (:mod:`mifacerf.geometry.horn1987`).
Modules, one concept each: :mod:`.neighbourhoods`,
:mod:`.deformation`, :mod:`.local_space` (PCA + dimensionality), :mod:`.delaunay`
(m-D triangulation, barycentrics, out-of-hull rule), :mod:`.weights` (Dr.Jit
evaluator), :mod:`.culling` (regions, similarity graph, minimum-degree greedy
MIS), :mod:`.reference` (per-vertex NumPy/SciPy), :mod:`.model` (``BlendModel``),
:mod:`.toy` (analytic test meshes), :mod:`.benchmark` (timing). The measurement against the
synthetic subject's true deformations is :mod:`mifacerf.evaluation.blending`.
Documentation: ``docs/blending.md``.
"""
from .culling import REGION_NAMES, load_regions, save_regions
from .deformation import align_neighbourhoods, local_rotations, region_deformations
from .model import BlendModel, SparseWeights
from .neighbourhoods import Neighbourhoods, neighbourhoods

__all__ = [
    "BlendModel",
    "SparseWeights",
    "local_rotations",
    "align_neighbourhoods",
    "region_deformations",
    "Neighbourhoods",
    "neighbourhoods",
    "REGION_NAMES",
    "load_regions",
    "save_regions",
]
