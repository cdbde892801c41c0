"""Closest point on a triangle as barycentrics (Ericson, *Real-Time Collision Detection*, 2004, §5.1.5).

One branch-free copy of the Voronoi-region logic, shared by the NumPy reference
(:mod:`mifacerf.blending.delaunay`) and the Dr.Jit kernel (:mod:`mifacerf.blending.weights`): the caller
computes the six dot products of its own array type and passes its element-wise ``select``
(``numpy.where`` or ``drjit.select``), so the same arithmetic runs in both.
"""
from __future__ import annotations


def region_barycentrics(d1, d2, d3, d4, d5, d6, select):
    """Barycentrics ``(u, v, w)`` of the closest point of triangle ``abc`` to ``p``.

    ``d1 = ab·ap, d2 = ac·ap, d3 = ab·bp, d4 = ac·bp, d5 = ab·cp, d6 = ac·cp`` (any broadcastable shape,
    NumPy or Dr.Jit arrays); ``select(mask, x, y)`` is the element-wise choice. A degenerate triangle's
    zero denominators are replaced by 1 (finite results; the vertex/edge regions then decide).
    """
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    sd = lambda num, den: num / select(den != 0, den, 1.0)  # noqa: E731
    den = va + vb + vc
    v = sd(vb, den)
    w = sd(vc, den)
    u = 1.0 - v - w
    # edges and vertices, from lowest to highest priority (each overrides the previous)
    rBC = (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0)
    t = sd(d4 - d3, (d4 - d3) + (d5 - d6))
    u, v, w = select(rBC, 0.0, u), select(rBC, 1.0 - t, v), select(rBC, t, w)
    rAC = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
    t = sd(d2, d2 - d6)
    u, v, w = select(rAC, 1.0 - t, u), select(rAC, 0.0, v), select(rAC, t, w)
    rC = (d6 >= 0) & (d5 <= d6)
    u, v, w = select(rC, 0.0, u), select(rC, 0.0, v), select(rC, 1.0, w)
    rAB = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
    t = sd(d1, d1 - d3)
    u, v, w = select(rAB, 1.0 - t, u), select(rAB, t, v), select(rAB, 0.0, w)
    rB = (d3 >= 0) & (d4 <= d3)
    u, v, w = select(rB, 0.0, u), select(rB, 1.0, v), select(rB, 0.0, w)
    rA = (d1 <= 0) & (d2 <= 0)
    u, v, w = select(rA, 1.0, u), select(rA, 0.0, v), select(rA, 0.0, w)
    return u, v, w
