"""Reference charts for radiometric calibration, from colour-science's reference data.

* The **ColorChecker 24** (X-Rite, "after November 2014" formulation):
  ``colour.CCS_COLOURCHECKERS['ColorChecker24 - After November 2014']`` gives each
  patch's CIE xyY under D50; :func:`colorchecker_reference` adapts them to D65
  (Bradford) and returns linear sRGB reflectances, the units of mifacerf's images.
* The **grey chart**: the ColorChecker's neutral row (white 9.5 ... black 2), the
  grey scale used to recover each camera's response curve.

Layout (both): a grid of square patches ``patch`` metres wide with ``gap`` metres
between them on a dark frame, patches numbered row-major from the top-left as
printed. Chart frame like the calibration board's: origin at the top-left corner,
+x right, +y down, +z into the chart; metres.

Measuring patches: :func:`patch_means` maps a chart's four outer corners (pixels,
given per camera: clicked by hand or, in simulation, projected) to every patch
centre by a homography and averages a disc of ``inner`` x the patch size.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

COLORCHECKER = "ColorChecker24 - After November 2014"
FRAME_REFLECTANCE = 0.04


@dataclass(frozen=True)
class ChartLayout:
    """A ``rows`` x ``cols`` grid of ``patch``-metre squares with ``gap`` metres between them and a
    ``margin``-metre frame."""

    rows: int
    cols: int
    patch: float = 0.03
    gap: float = 0.005
    margin: float = 0.01

    @property
    def size(self) -> tuple[float, float]:
        """(width, height) in metres."""
        return (2 * self.margin + self.cols * self.patch + (self.cols - 1) * self.gap,
                2 * self.margin + self.rows * self.patch + (self.rows - 1) * self.gap)

    def centres(self) -> np.ndarray:
        """Patch centres (rows*cols, 2) in the chart frame, row-major."""
        i, j = np.meshgrid(np.arange(self.rows), np.arange(self.cols), indexing="ij")
        x = self.margin + j * (self.patch + self.gap) + self.patch / 2
        y = self.margin + i * (self.patch + self.gap) + self.patch / 2
        return np.stack([x.ravel(), y.ravel()], axis=1)

    def corners(self) -> np.ndarray:
        """The four outer corners (4, 2): top-left, top-right, bottom-right, bottom-left."""
        w, h = self.size
        return np.array([[0, 0], [w, 0], [w, h], [0, h]], np.float64)

    def patch_at(self, xy: np.ndarray) -> np.ndarray:
        """Patch index at chart points (N, 2); -1 on the frame or outside."""
        xy = np.asarray(xy, np.float64)
        pitch = self.patch + self.gap
        u = (xy[:, 0] - self.margin) / pitch
        v = (xy[:, 1] - self.margin) / pitch
        j, i = np.floor(u).astype(int), np.floor(v).astype(int)
        inside = ((u - j) * pitch < self.patch) & ((v - i) * pitch < self.patch) & \
                 (j >= 0) & (j < self.cols) & (i >= 0) & (i < self.rows)
        return np.where(inside, i * self.cols + j, -1)

    def to_dict(self) -> dict:
        return asdict(self)


def colorchecker_reference(clip: bool = True) -> tuple[list[str], np.ndarray]:
    """Patch names and linear sRGB (D65) reflectances (24, 3) of the ColorChecker 24.

    ``clip``: negative components (the cyan patch lies just outside sRGB) set to 0,
    so the reference is renderable in linear sRGB.
    """
    import colour

    cc = colour.CCS_COLOURCHECKERS[COLORCHECKER]
    xyY = np.array(list(cc.data.values()), np.float64)
    rgb = colour.XYZ_to_RGB(colour.xyY_to_XYZ(xyY), "sRGB", illuminant=cc.illuminant,
                            chromatic_adaptation_transform="Bradford")
    return list(cc.data.keys()), (np.clip(rgb, 0.0, None) if clip else rgb)


def grey_reference() -> tuple[list[str], np.ndarray]:
    """The neutral row of the ColorChecker: names and reflectances (6,) (luminance, linear)."""
    names, rgb = colorchecker_reference()
    w = np.array([0.2126, 0.7152, 0.0722])
    return names[18:], rgb[18:] @ w


COLORCHECKER_LAYOUT = ChartLayout(4, 6)
GREY_LAYOUT = ChartLayout(2, 3)


def patch_means(image: np.ndarray, corners_px: np.ndarray, layout: ChartLayout, inner: float = 0.5):
    """Mean value (and pixel count) of each patch: ((P, C), (P,)).

    ``corners_px`` (4, 2): the chart's outer corners in the image (pixel centres at integers),
    in :meth:`ChartLayout.corners` order.
    """
    import cv2

    img = np.asarray(image, np.float64)
    if img.ndim == 2:
        img = img[..., None]
    H = cv2.getPerspectiveTransform(layout.corners().astype(np.float32), np.asarray(corners_px, np.float32))
    centres = cv2.perspectiveTransform(layout.centres()[None].astype(np.float64), H)[0]
    # patch radius in pixels from the local scale of the homography
    radius_m = inner * layout.patch / 2
    edge = cv2.perspectiveTransform((layout.centres() + [radius_m, 0])[None].astype(np.float64), H)[0]
    edge2 = cv2.perspectiveTransform((layout.centres() + [0, radius_m])[None].astype(np.float64), H)[0]
    r = np.minimum(np.linalg.norm(edge - centres, axis=1), np.linalg.norm(edge2 - centres, axis=1))
    hh, ww = img.shape[:2]
    yy, xx = np.mgrid[:hh, :ww]
    means = np.full((len(centres), img.shape[2]), np.nan)
    counts = np.zeros(len(centres), int)
    for p, (c, rp) in enumerate(zip(centres, r)):
        m = (xx - c[0]) ** 2 + (yy - c[1]) ** 2 <= max(rp, 0.75) ** 2
        counts[p] = int(m.sum())
        if counts[p]:
            means[p] = img[m].mean(axis=0)
    return means, counts
