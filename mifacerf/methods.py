"""Methods chosen by name: the one pattern every swappable step of the pipeline follows.

A step with alternatives keeps a registry ``<STEP>_METHODS = {name: implementation}`` in the module
that implements it (the first entry is the default, also named by ``DEFAULT_<STEP>_METHOD``) and
one dispatcher that takes ``method=`` and looks the name up with :func:`lookup`, so every caller
(renderer, model, CLI, benchmark, demo) chooses by the same names and an unknown name fails the
same way. Adding a method is one new function (or entry object) plus one registry line; CLI
options take their choices from the registry (``click.Choice(list(<STEP>_METHODS))``).

Registries: :data:`mifacerf.rendering.compression.COMPRESSION_METHODS`,
:data:`mifacerf.environment.LIGHT_BASIS_METHODS`, :data:`mifacerf.registration.dot_removal.DOT_FILL_METHODS`,
:data:`mifacerf.capture.motion.SHARPNESS_METHODS`,
:data:`mifacerf.capture.calibration.radiometric.RESPONSE_METHODS`.
"""
from __future__ import annotations


def lookup(methods: dict, method, kind: str):
    """The entry of ``methods`` named ``method``; a ValueError naming the choices for any other name.

    ``kind`` names the step in the message: ``unknown <kind> method 'foo'; choose one of a, b``.
    """
    try:
        return methods[method]
    except (KeyError, TypeError):
        raise ValueError(f"unknown {kind} method {method!r}; choose one of {', '.join(methods)}") from None
