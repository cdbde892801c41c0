"""Pixel footprints: the size in metres of one pixel at a given depth.

World units are metres; cameras are :class:`mifacerf.camera.Camera` (OpenCV frames). The rig
centre is the world origin, so a camera's distance to the rig centre is ``|camera.centre|``.
"""
from __future__ import annotations

import numpy as np


def centre_footprint(cameras) -> float:
    """Median over ``cameras`` of the size (metres) of one pixel at the rig centre.

    Each camera's footprint is :meth:`~mifacerf.camera.Camera.pixel_footprint` at a depth equal to
    its distance from the world origin. Lengths "in pixel footprints" throughout the pipeline are
    divided by this number.
    """
    return float(np.median([c.pixel_footprint(np.linalg.norm(c.centre)) for c in cameras]))
