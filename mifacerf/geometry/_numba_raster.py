"""The Numba kernel of :mod:`.raster` (imported on first use: Numba loads only when a frame needs it)."""
import numba
import numpy as np


@numba.njit(cache=True, boundscheck=False, nogil=True)
def raster_rows(P, faces, plane, order, starts, grid, cull_back, best, tri, u, v, band_lo, band_hi):
    """Nearest front hits of the camera samples ``plane`` (N, 2) — rays from the origin along (x, y, 1) in
    camera coordinates — on the triangles ``faces`` (F, 3) of the vertices ``P`` (V, 3) (camera
    coordinates, every z > 0: the caller checks). ``order`` (N,) the samples sorted by grid cell, cell k's
    being ``order[starts[k]:starts[k + 1]]``; ``grid`` (x0, y0, 1 / cell, columns, rows) of the plane.
    ``cull_back``: triangles whose normal (right-hand rule) faces away from the camera are skipped.
    Writes, where a triangle is nearer than ``best`` (N,) (the depth z, +inf to start): ``best``, ``tri``
    (N,) and the barycentrics ``u``, ``v`` of corners 1 and 2 (Möller–Trumbore, float64, edges inclusive),
    for the samples of grid rows ``band_lo`` ≤ j < ``band_hi`` only (threads take disjoint bands).
    Returns the triangles tested."""
    x0, y0, inv, gw, gh = grid[0], grid[1], grid[2], int(grid[3]), int(grid[4])
    tested = 0
    for f in range(faces.shape[0]):
        a = P[faces[f, 0]]
        b = P[faces[f, 1]]
        c = P[faces[f, 2]]
        e1x, e1y, e1z = b[0] - a[0], b[1] - a[1], b[2] - a[2]
        e2x, e2y, e2z = c[0] - a[0], c[1] - a[1], c[2] - a[2]
        # the normal e1 x e2; the ray towards a meets the face from behind where n . a > 0
        nx = e1y * e2z - e1z * e2y
        ny = e1z * e2x - e1x * e2z
        nz = e1x * e2y - e1y * e2x
        if cull_back and nx * a[0] + ny * a[1] + nz * a[2] > 0.0:
            continue
        ax, ay = a[0] / a[2], a[1] / a[2]
        bx, by = b[0] / b[2], b[1] / b[2]
        cx, cy = c[0] / c[2], c[1] / c[2]
        i0 = int(np.floor((min(ax, bx, cx) - x0) * inv))
        i1 = int(np.floor((max(ax, bx, cx) - x0) * inv))
        j0 = int(np.floor((min(ay, by, cy) - y0) * inv))
        j1 = int(np.floor((max(ay, by, cy) - y0) * inv))
        if i1 < 0 or j1 < band_lo or i0 >= gw or j0 >= band_hi:
            continue
        i0, j0 = max(i0, 0), max(j0, band_lo)
        i1, j1 = min(i1, gw - 1), min(j1, band_hi - 1)
        tested += 1
        tx, ty, tz = -a[0], -a[1], -a[2]          # origin - a
        qx = ty * e1z - tz * e1y                  # q = (o - a) x e1
        qy = tz * e1x - tx * e1z
        qz = tx * e1y - ty * e1x
        depth_num = e2x * qx + e2y * qy + e2z * qz
        for j in range(j0, j1 + 1):
            for i in range(i0, i1 + 1):
                k = j * gw + i
                for m in range(starts[k], starts[k + 1]):
                    s = order[m]
                    dx, dy = plane[s, 0], plane[s, 1]
                    # p = d x e2, det = e1 . p (d = (dx, dy, 1))
                    px = dy * e2z - e2y
                    py = e2x - dx * e2z
                    pz = dx * e2y - dy * e2x
                    det = e1x * px + e1y * py + e1z * pz
                    if det == 0.0:
                        continue
                    rdet = 1.0 / det
                    uu = (tx * px + ty * py + tz * pz) * rdet
                    if uu < 0.0 or uu > 1.0:
                        continue
                    vv = (dx * qx + dy * qy + qz) * rdet
                    if vv < 0.0 or uu + vv > 1.0:
                        continue
                    z = depth_num * rdet                 # t along (dx, dy, 1): the depth
                    if z > 0.0 and z < best[s]:
                        best[s] = z
                        tri[s] = f
                        u[s] = uu
                        v[s] = vv
    return tested


@numba.njit(cache=True, boundscheck=False, nogil=True)
def finish_rows(best, tri, u, v, norm, kept, parent, corner_bary, out_tri, out_sub, out_bary, out_t):
    """The hits of :func:`raster_rows` in :class:`.meshscene.Hits`' form: ``out_sub`` the rasterised
    triangle (through ``kept`` (F',) where only some faces were rasterised; empty: all), ``out_tri`` its
    coarse face (through ``parent`` (F,) and ``corner_bary`` (F, 3, 3) where the triangles are sub-faces
    of a tessellation; empty: the same), ``out_bary`` (N, 3) the barycentrics there (1 − u − v, u, v mapped
    through the sub-face's corners), ``out_t`` (N,) the distance ``best`` · ``norm`` (inf: no hit)."""
    sub_faces = parent.shape[0] > 0
    for s in range(best.shape[0]):
        f = tri[s]
        if f < 0:
            out_tri[s] = -1
            out_sub[s] = -1
            out_bary[s, 0] = 0.0
            out_bary[s, 1] = 0.0
            out_bary[s, 2] = 0.0
            out_t[s] = np.inf
            continue
        if kept.shape[0] > 0:
            f = kept[f]
        out_sub[s] = f
        b0 = 1.0 - u[s] - v[s]
        b1 = u[s]
        b2 = v[s]
        if sub_faces:
            out_tri[s] = parent[f]
            for d in range(3):
                out_bary[s, d] = b0 * corner_bary[f, 0, d] + b1 * corner_bary[f, 1, d] + b2 * corner_bary[f, 2, d]
        else:
            out_tri[s] = f
            out_bary[s, 0] = b0
            out_bary[s, 1] = b1
            out_bary[s, 2] = b2
        out_t[s] = best[s] * norm[s]
