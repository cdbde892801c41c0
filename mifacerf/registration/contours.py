"""Lips and eyelids (paper §4.2): relaxing a margin until its silhouette meets the rotoscoped curves.

"We rotoscope the lip boundary in at least two camera views, and then initialize the lip
geometry using a set of fiducial dots near the lips to morph the lip geometry from the
reference expression to the new expression. This estimate is then iteratively relaxed to
make its silhouette align with the rotoscoped boundary in each of the rotoscoped views.
The eyelids are rotoscoped and warped into place in the same way."

A margin is an ordered list of template vertices (the inner lip boundary, an eyelid's
edge). Each iteration (:func:`relax_margin`):

* projects the margin into every rotoscoped view and finds, for every vertex, the nearest
  point of that view's polyline; interior vertices are pulled only *across* the curve
  (along its 2-D normal — sliding along a curve is not observed), the two end vertices (the
  corners) towards the matching ends of the polyline;
* solves for 3-D steps of all margin vertices at once: the linearised pixel residuals of
  all views (Jacobians of the full camera model), a smoothness term keeping the margin's edge
  vectors close to the initial estimate's (the morph knows how the vertices are spaced along
  the curve; the curves do not), and a weak damping of each step;
* applies the step. Ten iterations converge (nearest points change little near the answer).

:func:`propagate` then carries the margins' displacement into the nearby non-fiducial
vertices (harmonic interpolation on the template graph: margins fixed to their new
displacement, everything outside the movable band fixed at zero), so the lips and lids
deform smoothly behind their edges.
"""
from __future__ import annotations

import numpy as np

from ..camera import Camera


def closest_on_polyline(poly: np.ndarray, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Nearest points (N, 2) on an open polyline (P, 2) and the unit tangents (N, 2) there."""
    A, B = poly[:-1], poly[1:]
    AB = B - A
    L2 = np.maximum((AB ** 2).sum(1), 1e-12)
    t = np.clip(np.einsum("nsk,sk->ns", pts[:, None] - A[None], AB) / L2[None], 0, 1)
    Q = A[None] + t[..., None] * AB[None]
    d = ((pts[:, None] - Q) ** 2).sum(-1)
    k = np.argmin(d, axis=1)
    idx = np.arange(len(pts))
    tang = AB[k] / np.sqrt(L2[k])[:, None]
    return Q[idx, k], tang


def projection_jacobian(cam: Camera, X: np.ndarray, h: float = 1e-6) -> np.ndarray:
    """(N, 2, 3) derivative of the pixel projection at world points X (N, 3)."""
    J = np.empty((len(X), 2, 3))
    for k in range(3):
        d = np.zeros(3)
        d[k] = h
        J[:, :, k] = (cam.project(X + d)[0] - cam.project(X - d)[0]) / (2 * h)
    return J


def curve_residuals(cam: Camera, X: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """Distances (N,) in pixels from the projections of X to the polyline."""
    p, _ = cam.project(X)
    q, _ = closest_on_polyline(poly, p)
    return np.linalg.norm(q - p, axis=1)


def relax_margin(X0: np.ndarray, views: dict, cams: dict, iterations: int = 30, smooth: float = 0.5,
                 stay: float = 0.02, corners: bool = True) -> np.ndarray:
    """Relax an ordered margin X0 (n, 3) onto rotoscoped polylines ``views`` {camera: (P, 2)}.

    ``smooth`` / ``stay``: weights of the smoothness and stay-put terms, relative to one view's
    typical squared Jacobian (so they are independent of the image resolution).
    ``corners``: pull the end vertices to the polyline's ends.
    """
    X = np.asarray(X0, np.float64).copy()
    Xref = X.copy()
    n = len(X)
    if n == 0 or len(views) == 0:
        return X
    for _ in range(iterations):
        H = np.zeros((n, 3, 3))
        g = np.zeros((n, 3))
        scale = 0.0
        for name, poly in views.items():
            cam = cams[name]
            poly = np.asarray(poly, np.float64)
            p, _ = cam.project(X)
            J = projection_jacobian(cam, X)
            q, tang = closest_on_polyline(poly, p)
            nrm = np.stack([-tang[:, 1], tang[:, 0]], 1)
            r = np.einsum("nk,nk->n", nrm, q - p)
            Jn = np.einsum("nk,nkj->nj", nrm, J)
            H += np.einsum("ni,nj->nij", Jn, Jn)
            g += Jn * r[:, None]
            if corners and n >= 2:
                ends = poly[[0, -1]]
                straight = np.linalg.norm(p[0] - ends[0]) + np.linalg.norm(p[-1] - ends[1])
                swapped = np.linalg.norm(p[0] - ends[1]) + np.linalg.norm(p[-1] - ends[0])
                if swapped < straight:
                    ends = ends[::-1]
                for i, e in ((0, ends[0]), (n - 1, ends[1])):
                    H[i] += J[i].T @ J[i]
                    g[i] += J[i].T @ (e - p[i])
            scale += np.mean(np.einsum("nij,nij->n", J, J)) / 2
        scale /= len(views)
        # block system: (H_i + s·deg_i + stay) δ_i − s Σ_nb δ_nb = g_i
        A = np.zeros((3 * n, 3 * n))
        for i in range(n):
            A[3 * i:3 * i + 3, 3 * i:3 * i + 3] = H[i] + stay * scale * np.eye(3)
            for j in (i - 1, i + 1):
                if 0 <= j < n:
                    A[3 * i:3 * i + 3, 3 * i:3 * i + 3] += smooth * scale * np.eye(3)
                    A[3 * i:3 * i + 3, 3 * j:3 * j + 3] -= smooth * scale * np.eye(3)
        # the smoothness term keeps the margin's edge vectors close to the initial estimate's
        # (relative to X0, not to the current iterate, so vertices cannot drift along the curve)
        b = g.copy()
        r = (X[:-1] - X[1:]) - (Xref[:-1] - Xref[1:])
        b[:-1] -= smooth * scale * r
        b[1:] += smooth * scale * r
        delta = np.linalg.solve(A, b.reshape(-1)).reshape(n, 3)
        X += delta
        if np.abs(delta).max() < 1e-7:
            break
    return X


def rings(n_vertices: int, triangles: np.ndarray, seeds: np.ndarray, k: int) -> np.ndarray:
    """Graph distance (≤ k, else -1) of every vertex from ``seeds`` on the template's edges."""
    from ..geometry.graph import edge_graph

    A = edge_graph(np.asarray(triangles, np.int64).reshape(-1, 3), n_vertices)
    dist = np.full(n_vertices, -1)
    dist[np.asarray(seeds, np.int64)] = 0
    front = np.zeros(n_vertices, bool)
    front[np.asarray(seeds, np.int64)] = True
    for d in range(1, k + 1):
        nxt = (A @ front.astype(float)) > 0
        nxt &= dist < 0
        dist[nxt] = d
        front = nxt
    return dist


def propagate(V_before: np.ndarray, V_after_margins: np.ndarray, triangles: np.ndarray, margin_ids: np.ndarray,
              movable: np.ndarray) -> np.ndarray:
    """Carry the margins' displacement into ``movable`` vertices by harmonic interpolation."""
    import scipy.sparse as sp
    import scipy.sparse.linalg as spla

    V = np.asarray(V_after_margins, np.float64).copy()
    D = np.zeros_like(V)
    margin_ids = np.asarray(margin_ids, np.int64)
    D[margin_ids] = V[margin_ids] - V_before[margin_ids]
    free = np.setdiff1d(np.asarray(movable, np.int64), margin_ids)
    if free.size == 0:
        return V
    n = len(V)
    from ..geometry.graph import edge_graph

    A = edge_graph(np.asarray(triangles, np.int64).reshape(-1, 3), n).astype(float)
    L = sp.diags(np.asarray(A.sum(1)).ravel()) - A
    Lff = L[free][:, free].tocsc()
    fixed = np.setdiff1d(np.arange(n), free)
    rhs = -(L[free][:, fixed] @ D[fixed])
    Df = spla.splu(Lff + 1e-12 * sp.eye(len(free))).solve(np.asarray(rhs))
    V[free] = V_before[free] + Df
    return V
