"""mifacerf's Mitsuba plugins, registered by name when this package is imported.

:func:`mifacerf.variant.ensure_plugins` imports it: the rendering entry points (``load_model``,
the renderer, scene files) and ``import mifacerf`` in a program that already imported
``mitsuba`` call it; :func:`mifacerf.register_plugins` does it on request. Installed as
``mifacerf.plugins`` from the repository's top-level ``plugins/`` (pyproject's ``package-dir``).

* ``facerf`` (integrator): the exact environment-lit render of a face model (:mod:`.facerf_integrator`).
* ``facerf_bsdf`` (BSDF): the image-based material for Mitsuba's own emitters and integrators
  (:mod:`.facerf_bsdf`).
* ``facerf_direct`` (integrator): Mitsuba's direct illumination with a near-field shadow rule for the
  material's skin (``facerf_bsdf`` ``near_occluders``; :mod:`.facerf_direct`).
* ``facerf_face`` (shape): the face mesh with its eyes, teeth and mouth interior, from the model folder,
  posed by scene parameters (:mod:`.facerf_shape`).
"""
from . import facerf_bsdf, facerf_direct, facerf_integrator, facerf_shape  # noqa: F401  (register the plugins)
