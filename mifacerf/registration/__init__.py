"""Registration (paper §3–4): from a light-stage capture to a morphable model in correspondence.

Public API::

    from mifacerf.registration import register_capture, Options
    out = register_capture("CAPTURE", out=None, expressions=None, force=False, options=Options())

Modules, one concept each: :mod:`.hand` (hand inputs), :mod:`.proxies`, :mod:`.dots` (filter,
strength maps), :mod:`.morph`, :mod:`.snap`,
:mod:`.eyes_teeth`, :mod:`.contours` (lips / eyelids), :mod:`.dot_removal`, :mod:`.texcoords`,
:mod:`.register` (orchestration), :mod:`.cli`. Documentation: ``docs/registration.md``.
Multi-view triangulation, ray-traced visibility, Horn's fit, the MLS affine map and the other shared
geometry are on the ground floor (:mod:`mifacerf.geometry`). The
evaluation against the synthetic truth is :mod:`mifacerf.evaluation.registration`.
"""
__all__ = ["Options", "RegistrationInputError", "register_capture"]


def __getattr__(name):  # lazy: ``mifacerf --help`` imports only the command's module
    if name in __all__:
        from . import register

        return getattr(register, name)
    raise AttributeError(name)
