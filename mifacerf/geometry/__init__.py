"""The geometry ground floor: small, pure helpers every pipeline stage may import.

This package imports no pipeline stage (capture, synthetic, registration, blending, rendering,
tracking, evaluation) and nothing heavy at import time; Mitsuba is loaded by
:mod:`.meshscene` only on first use. Modules, one concept each (flat, named for the method where
there is a published one):

- :mod:`.footprint`: the size of one pixel at the rig centre (metres per pixel).
- :mod:`.horn1987`: closed-form absolute orientation (rigid fit of two point sets), Horn (1987).
- :mod:`.triangulate`: multi-view triangulation through calibrated, distorted cameras.
- :mod:`.schaefer2006`: moving-least-squares affine deformation of points by anchors, Schaefer et al. (2006).
- :mod:`.rigid`: rigid transforms as 4 × 4 matrices (apply, rotation angle, least-squares and robust fits).
- :mod:`.visibility`: per-vertex visibility of a mesh from the cameras (ray-traced, facing test).
- :mod:`.maxima`: 3 × 3 local maxima of a 2-D map (dot-strength maps).
- :mod:`.margins`: lip and eyelid margins of a template mesh from its hole loops.
- :mod:`.vectors`: row-wise lengths of many small vectors (``np.linalg.norm(axis=1)``'s values, fast).
- :mod:`.meshscene`: a triangle mesh in its own Mitsuba scene for ray casting (visibility).
"""
