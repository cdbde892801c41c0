"""Lip and eyelid margins of a template mesh, read off its hole loops.

A template (``mifacerf.template/1``, docs/registration.md) has the mouth and both eye openings as
holes, each a boundary loop of vertex ids that starts at one corner vertex and passes the other
corner once (the vertices' ``kinds`` ending in ``"_corner"``). Each loop splits at its corners
into two ordered margins, corners at both ends: the upper one as the loop runs, the lower one
from the first corner back along the loop's end to the second corner.
"""
from __future__ import annotations

import numpy as np

#: hole name → (upper margin name, lower margin name)
HOLE_MARGINS = {"mouth": ("lip_upper", "lip_lower"), "eye_left": ("lid_upper_L", "lid_lower_L"),
                "eye_right": ("lid_upper_R", "lid_lower_R")}


def margins_from_holes(holes: dict, kinds: list) -> dict:
    """Ordered margins {margin name: (n,) int64 vertex ids} from the hole loops ``holes`` {hole name:
    ``[corner, upper..., corner, lower reversed...]``} and the vertex ``kinds`` (T,). Holes other than
    :data:`HOLE_MARGINS`, and loops without exactly two corners (the first at position 0), are skipped."""
    out = {}
    for hole, loop in holes.items():
        if hole not in HOLE_MARGINS:
            continue
        loop = [int(i) for i in loop]
        corners = [k for k, v in enumerate(loop) if kinds[v].endswith("_corner")]
        if len(corners) != 2 or corners[0] != 0:
            continue
        k = corners[1]
        up_name, lo_name = HOLE_MARGINS[hole]
        out[up_name] = np.array(loop[:k + 1], np.int64)
        out[lo_name] = np.array([loop[0]] + loop[:k:-1] + [loop[k]], np.int64)
    return out
