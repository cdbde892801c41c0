"""The Phong surface's culled trace of one 256² × 4 frame, side by side: the hits mapped to the coarse mesh
in NumPy after the sub-mesh's own trace (``PhongTessellation.to_coarse``) against ``CurvedMeshScene.trace``,
which maps them inside the ray cast's kernel; median of 9 warm runs each, and whether they agree::

    python benchmarks/curved_trace.py MODEL [--level 3] [--camera 2]
"""
from __future__ import annotations

import argparse
import time

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("model")
    ap.add_argument("--level", type=int, default=3)
    ap.add_argument("--camera", type=int, default=2)
    a = ap.parse_args()
    from mifacerf.camera import stratified_pixel_samples
    from mifacerf.geometry.meshscene import CurvedMeshScene
    from mifacerf.rendering.api import load_model

    m = load_model(a.model).model
    scene = CurvedMeshScene(m.vertices[m.expression_index(m.neutral)], m.triangles, a.level)
    cam = m.cameras[a.camera].resized(256, 256)
    _, d = cam.pixel_rays(stratified_pixel_samples(256, 256, 4, 0))

    def numpy_map():
        h = scene._curved.trace(cam.centre, d, cull_back=True)
        return scene.tessellation.to_coarse(h.tri, h.bary)

    def device_map():
        return scene.trace(cam.centre, d, cull_back=True)

    def median_ms(f):
        f()
        ts = []
        for _ in range(9):
            t0 = time.perf_counter()
            f()
            ts.append(time.perf_counter() - t0)
        return 1000 * float(np.median(ts))

    (tri, bary), h = numpy_map(), device_map()
    print(f"level {a.level}, {len(scene.tessellation.faces)} sub-faces, {len(d)} rays: NumPy map "
          f"{median_ms(numpy_map):.1f} ms, device map {median_ms(device_map):.1f} ms; same triangles "
          f"{bool((h.tri == tri).all())}, max barycentric difference {np.abs(h.bary - bary).max():.1e}")


if __name__ == "__main__":
    main()
