"""Pictures for people: labelled image grids (contact sheets, comparison strips, error maps).

Inputs are linear sRGB float images (H, W, 3|4); outputs are 8-bit sRGB arrays ready
for :func:`mifacerf.imageio.write_png`. RGBA input is composited over a grey
background so faces with alpha read well.
"""
from __future__ import annotations

import numpy as np

from .imageio import to_srgb8

BACKGROUND = 0.18  # linear grey behind RGBA tiles


def tile8(image: np.ndarray, exposure: float = 1.0, size: int | None = None) -> np.ndarray:
    """One tile: linear (H, W, 3|4) → sRGB uint8 (H, W, 3), alpha over grey, optionally resized to ``size``."""
    import cv2

    if np.asarray(image).dtype == np.uint8:  # already an 8-bit picture (e.g. an error map)
        out = np.asarray(image)
        if size is not None and out.shape[0] != size:
            out = cv2.resize(out, (int(round(out.shape[1] * size / out.shape[0])), size),
                             interpolation=cv2.INTER_NEAREST)
        return out
    img = np.asarray(image, np.float32)
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=-1)
    if img.shape[-1] == 4:
        img = img[..., :3] * exposure + BACKGROUND * (1 - img[..., 3:4])
        out = to_srgb8(img)
    else:
        out = to_srgb8(img, exposure)
    if size is not None and out.shape[0] != size:
        out = cv2.resize(out, (int(round(out.shape[1] * size / out.shape[0])), size),
                         interpolation=cv2.INTER_AREA if out.shape[0] > size else cv2.INTER_NEAREST)
    return out


def label(tile: np.ndarray, text: str, scale: float = 0.4) -> np.ndarray:
    """Write ``text`` in the tile's top-left corner (white on a dark band)."""
    import cv2

    out = tile.copy()
    (w, h), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
    cv2.rectangle(out, (0, 0), (min(w + 6, out.shape[1]), h + base + 4), (0, 0, 0), -1)
    cv2.putText(out, text, (3, h + 2), cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), 1, cv2.LINE_AA)
    return out


def grid(tiles: list[np.ndarray], columns: int, pad: int = 2) -> np.ndarray:
    """Arrange equally sized uint8 tiles (H, W, 3) in rows of ``columns``."""
    if not tiles:
        raise ValueError("no tiles")
    h, w = tiles[0].shape[:2]
    rows = (len(tiles) + columns - 1) // columns
    out = np.full((rows * (h + pad) + pad, columns * (w + pad) + pad, 3), 24, np.uint8)
    for i, t in enumerate(tiles):
        r, c = divmod(i, columns)
        out[pad + r * (h + pad): pad + r * (h + pad) + h, pad + c * (w + pad): pad + c * (w + pad) + w] = t[:h, :w]
    return out


def error_map(a: np.ndarray, b: np.ndarray, scale: float = 0.1, mask: np.ndarray | None = None) -> np.ndarray:
    """Absolute error |a − b| (mean over RGB) as a colour map; ``scale`` = the error shown as full red."""
    import cv2

    err = np.abs(np.asarray(a, np.float32)[..., :3] - np.asarray(b, np.float32)[..., :3]).mean(-1)
    v = np.clip(err / scale, 0, 1)
    cmap = cv2.applyColorMap((v * 255).astype(np.uint8), cv2.COLORMAP_INFERNO)
    cmap = cv2.cvtColor(cmap, cv2.COLOR_BGR2RGB)
    if mask is not None:
        cmap[~mask] = 40
    return cmap
