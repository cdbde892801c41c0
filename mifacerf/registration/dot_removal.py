"""Dot removal (paper §4.2, after [GGW*98]): the fiducials painted out of every OLAT image.

For one (expression, camera), the registered fiducials visible in that view are projected;
every pixel whose centre lies within ``r + margin`` pixels of a dot centre (``r`` the dot's
image radius) is replaced by the **harmonic interpolation** of the pixels round it (the
solution of Laplace's equation inside the mask with the surrounding pixels as boundary
values). The interpolation is linear and the same for every light: one sparse operator per
(expression, camera), applied to all lights and channels at once.
Only the changed pixels are stored (:meth:`RegistrationWriter.write_dotfree`).
"""
from __future__ import annotations

import numpy as np


def dot_mask(shape: tuple[int, int], centres: np.ndarray, radius) -> np.ndarray:
    """(H, W) bool: pixels whose centre lies within ``radius`` (scalar or (N,)) of a centre (N, 2)."""
    h, w = shape
    mask = np.zeros((h, w), bool)
    c = np.asarray(centres, np.float64).reshape(-1, 2)
    rad = np.broadcast_to(np.asarray(radius, np.float64), (len(c),))
    good = np.isfinite(c).all(1) & np.isfinite(rad)
    c, rad = c[good], rad[good]
    if len(c) == 0:
        return mask
    r = int(np.ceil(rad.max()))
    du, dv = np.meshgrid(np.arange(-r, r + 2), np.arange(-r, r + 2))
    U = np.floor(c[:, :1, None]).astype(int) + du[None]
    Vv = np.floor(c[:, 1:, None]).astype(int) + dv[None]
    d2 = (U - c[:, :1, None]) ** 2 + (Vv - c[:, 1:, None]) ** 2
    ok = (U >= 0) & (U < w) & (Vv >= 0) & (Vv < h) & (d2 <= rad[:, None, None] ** 2)
    mask[Vv[ok], U[ok]] = True
    return mask


class Inpainter:
    """Harmonic fill of a mask (4-neighbour Laplacian); ``pixels`` (P, 2) (row, column).

    Each connected blob of the mask is solved on its own (a small dense system), giving a
    sparse linear operator from the pixels round the blobs to the pixels inside; filling
    any number of images is one sparse × dense product.
    """

    def __init__(self, mask: np.ndarray, valid: np.ndarray | None = None):
        """``mask`` (H, W) pixels to fill; ``valid`` (H, W) pixels that see the subject (default all):
        the fill never writes outside them nor draws from outside them (the background next to a
        silhouette is a mirror boundary, not a colour to blend in)."""
        import scipy.sparse as sp
        from scipy import ndimage

        h, w = mask.shape
        valid = np.ones((h, w), bool) if valid is None else np.asarray(valid, bool)
        mask = np.asarray(mask, bool) & valid
        # the image border cannot be filled from outside: keep border pixels as boundary
        mask[0, :] = mask[-1, :] = mask[:, 0] = mask[:, -1] = False
        self.mask = mask
        self.shape = (h, w)
        labels, n = ndimage.label(mask)
        order = np.argsort(labels.ravel()[mask.ravel()], kind="stable")
        pix = np.flatnonzero(mask.ravel())[order]             # grouped by blob
        self.pixels = np.stack([pix // w, pix % w], 1)
        P = len(pix)
        lab = labels.ravel()[pix]
        starts = np.searchsorted(lab, np.arange(1, n + 2))
        rows, cols, vals = [], [], []
        keep = np.ones(P, bool)
        for k in range(n):
            a, b = starts[k], starts[k + 1]
            ids = pix[a:b]
            m = len(ids)
            local = {int(p): i for i, p in enumerate(ids)}
            A = 4.0 * np.eye(m)
            bnd: dict[int, int] = {}
            S_r, S_c = [], []
            r, c = ids // w, ids % w
            vflat = valid.ravel()
            for dr, dc in ((-1, 0), (1, 0), (0, -1), (0, 1)):
                nb = (r + dr) * w + (c + dc)
                for i, q in enumerate(nb):
                    j = local.get(int(q))
                    if j is not None:
                        A[i, j] -= 1.0
                    elif vflat[q]:
                        S_r.append(i)
                        S_c.append(bnd.setdefault(int(q), len(bnd)))
                    else:                       # background: mirror (Neumann) boundary
                        A[i, i] -= 1.0
            if not bnd:                         # nothing to fill from: leave the blob alone
                keep[a:b] = False
                continue
            S = np.zeros((m, len(bnd)))
            np.add.at(S, (np.array(S_r), np.array(S_c)), 1.0)
            Mk = np.linalg.solve(A, S)
            bpix = np.array(list(bnd.keys()))
            ii, jj = np.nonzero(Mk)
            rows.append(a + ii)
            cols.append(bpix[jj])
            vals.append(Mk[ii, jj])
        if rows:
            rows, cols, vals = np.concatenate(rows), np.concatenate(cols), np.concatenate(vals)
            remap = np.cumsum(keep) - 1
            self.pixels = self.pixels[keep]
            P = len(self.pixels)
            self.src = np.unique(cols)
            M = sp.csr_matrix((vals, (remap[rows], np.searchsorted(self.src, cols))), shape=(P, len(self.src)))
        else:
            self.pixels = self.pixels[:0]
            self.src = np.zeros(0, np.int64)
            M = sp.csr_matrix((0, 0))
        self.M = M

    def __len__(self) -> int:
        return len(self.pixels)

    def fill(self, images: np.ndarray) -> np.ndarray:
        """Filled values (..., P, C) for images (..., H, W, C) (any leading dimensions)."""
        images = np.asarray(images)
        lead, C = images.shape[:-3], images.shape[-1]
        P = len(self.pixels)
        if P == 0:
            return np.zeros(lead + (0, C), np.float32)
        flat = images.reshape(-1, self.shape[0] * self.shape[1], C)       # (B, HW, C)
        b = flat[:, self.src].astype(np.float64)                          # (B, nb, C)
        B = len(flat)
        x = self.M @ b.transpose(1, 0, 2).reshape(len(self.src), B * C)   # (P, B*C)
        return x.reshape(P, B, C).transpose(1, 0, 2).reshape(lead + (P, C)).astype(np.float32)

    def apply(self, image: np.ndarray) -> np.ndarray:
        """A copy of one image (H, W, C) with the mask filled."""
        out = np.array(image, copy=True)
        out[self.pixels[:, 0], self.pixels[:, 1]] = self.fill(image)
        return out


def mask_radius(dot_radius_px: float, margin: float = 1.0) -> float:
    """The removal radius in pixels: the dot's image radius plus ``margin`` (its blurred rim)."""
    return float(dot_radius_px + margin)
