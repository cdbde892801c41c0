"""mifacerf's Mitsuba plugins, registered by name when :mod:`mifacerf` is imported.

* ``facerf`` (integrator): the exact environment-lit render of a face model (:mod:`.facerf_integrator`).
* ``facerf_bsdf`` (BSDF): the image-based material for Mitsuba's own emitters and integrators
  (:mod:`.facerf_bsdf`).
"""
from . import facerf_bsdf, facerf_integrator  # noqa: F401  (register "facerf_bsdf" and "facerf")
