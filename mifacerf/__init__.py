"""mifacerf: animatable, relightable facial reflectance fields on Mitsuba 3.

Importing the package selects the Mitsuba variant (:mod:`mifacerf.variant`) and
registers mifacerf's Mitsuba plugins by name (:mod:`mifacerf.plugins`).

Pipeline stages, as sub-packages: capture (hardware, ``capture/``) →
registration → blending → rendering → evaluation; the synthetic subject and
its simulated light stage live in :mod:`mifacerf.synthetic`.
"""
__version__ = "0.1.0"

from .variant import ensure_variant as _ensure_variant

_ensure_variant()
from . import plugins  # noqa: E402,F401  (registers the Mitsuba plugins by name)
from .rendering.api import composite, environment_plate, load_model  # noqa: E402,F401
