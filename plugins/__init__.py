"""mifacerf's Mitsuba plugins, registered by name when :mod:`mifacerf` is imported.

* ``facerf`` (integrator): the exact environment-lit render of a face model
  (:mod:`.facerf_integrator`).
"""
from . import facerf_integrator  # noqa: F401  (registers "facerf")
