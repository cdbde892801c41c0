"""mifacerf: animatable, relightable facial reflectance fields on Mitsuba 3.

Importing the package is light: it loads neither Mitsuba nor the renderer, so the command line
and the pure modules (the strobe controller's protocol, the folder formats) start fast. The
Python API (:func:`load_model`, :func:`composite`, :func:`environment_plate`) and the
sub-packages (``mifacerf.rendering``, ...) load on first use. The first use of rendering selects
the Mitsuba variant (:mod:`mifacerf.variant`) and registers mifacerf's Mitsuba plugins by name
(``facerf``, ``facerf_bsdf``; :mod:`mifacerf.plugins`). A program that imported ``mitsuba``
before ``import mifacerf`` gets the plugins registered at once, so a scene file using them
loads with plain ``mi.load_file``; any other program can call :func:`register_plugins`.

Pipeline stages, as sub-packages: capture (hardware, ``capture/``) → registration → blending →
rendering → tracking, evaluation; the synthetic subject and its simulated light stage live in
:mod:`mifacerf.synthetic`. ``docs/architecture.md`` describes the floors.
"""
import sys as _sys

__version__ = "0.1.0"
__all__ = ["load_model", "composite", "environment_plate", "register_plugins"]


def register_plugins():
    """Select the Mitsuba variant and register mifacerf's plugins (idempotent); returns ``mitsuba``."""
    from .variant import ensure_plugins

    return ensure_plugins()


def __getattr__(name):
    """The Python API and the sub-packages, imported on first access."""
    if name in ("load_model", "composite", "environment_plate"):
        from .rendering import api

        value = getattr(api, name)
    else:
        import importlib
        import importlib.util

        if name.startswith("_") or importlib.util.find_spec(f"{__name__}.{name}") is None:
            raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
        value = importlib.import_module(f"{__name__}.{name}")
    globals()[name] = value
    return value


if "mitsuba" in _sys.modules:  # a Mitsuba user: the plugins at once, as mi.load_file may need them
    register_plugins()
