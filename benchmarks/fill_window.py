"""The fill of hits no field covers (``frame.resolve_pixels``) over the gap's window against over the whole
image, side by side, alternating, on a synthetic frame: a head-sized ellipse of hits, 4 spp, with one
uncovered disc of ``--gap`` pixels' radius at the neck; median of 7 each and whether the images agree::

    python benchmarks/fill_window.py [--size 1024] [--gap 20]
"""
from __future__ import annotations

import argparse
import statistics
import time

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", type=int, default=1024)
    ap.add_argument("--gap", type=int, default=20)
    a = ap.parse_args()
    from mifacerf.rendering.frame import resolve_pixels

    H = W = a.size
    spp = 4
    pix = np.repeat(np.arange(H * W), spp)
    yy, xx = np.divmod(pix, W)
    inside = ((yy - H / 2) / (0.39 * H)) ** 2 + ((xx - W / 2) / (0.29 * W)) ** 2 < 1
    pix, yy, xx = pix[inside], yy[inside], xx[inside]
    colour = np.random.default_rng(0).random((len(pix), 3))
    covered = (yy - 0.86 * H) ** 2 + (xx - W / 2) ** 2 > a.gap ** 2
    times = {True: [], False: []}
    out = {}
    for _ in range(7):
        for window in (True, False):
            t0 = time.perf_counter()
            out[window] = resolve_pixels(pix, colour, covered, H, W, spp, window=window)
            times[window].append(time.perf_counter() - t0)
    w, f = statistics.median(times[True]), statistics.median(times[False])
    print(f"{a.size}², {out[True][1]} pixels filled: window {w:.3f} s, whole image {f:.3f} s (x{f / w:.1f}); "
          f"images identical: {bool(np.array_equal(out[True][0], out[False][0]))}")


if __name__ == "__main__":
    main()
