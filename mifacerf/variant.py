"""The one place where mifacerf chooses its Mitsuba variant.

The default is ``llvm_ad_rgb`` (vectorised CPU, RGB). Override it with the
environment variable ``MIFACERF_VARIANT`` (for example ``cuda_ad_rgb`` on a
machine with an NVIDIA GPU, or ``scalar_rgb`` as a slow last resort).

The LLVM backend of Dr.Jit needs a recent LLVM shared library: LLVM 14 and 15
fail while compiling kernels ("Cannot select: fminimum"). :func:`find_libllvm`
looks for LLVM >= 16 and points Dr.Jit at it through ``DRJIT_LIBLLVM_PATH``
before Mitsuba is imported; the README's set-up installs Debian's
``libllvm19`` when none is found.

:func:`ensure_plugins` also registers mifacerf's Mitsuba plugins (``facerf``, ``facerf_bsdf``;
:mod:`mifacerf.plugins`). No module outside the plugins imports Mitsuba at import time: the package
root and the pure modules load without it (``docs/architecture.md``, "Mitsuba and the plugins").
"""
from __future__ import annotations

import glob
import importlib
import os
import re
from .errors import MifacerfError

DEFAULT_VARIANT = "llvm_ad_rgb"
PLUGINS_PACKAGE = "mifacerf.plugins"
MIN_LLVM_MAJOR = 16

_SEARCH_GLOBS = (
    "/usr/lib/x86_64-linux-gnu/libLLVM*.so*",
    "/usr/lib/aarch64-linux-gnu/libLLVM*.so*",
    "/usr/lib/llvm-*/lib/libLLVM*.so*",
    "/usr/lib64/libLLVM*.so*",
    "/usr/local/lib/libLLVM*.so*",
    "/opt/homebrew/opt/llvm/lib/libLLVM*.dylib",
)


class VariantError(MifacerfError, RuntimeError):
    """The requested Mitsuba variant cannot be used on this machine."""


def _llvm_major(path: str) -> int | None:
    name = os.path.basename(path)
    m = re.search(r"libLLVM[-.]?(\d+)", name) or re.search(r"libLLVM\.so\.(\d+)", name)
    if m:
        return int(m.group(1))
    m = re.search(r"llvm-(\d+)", path)
    return int(m.group(1)) if m else None


def find_libllvm(min_major: int = MIN_LLVM_MAJOR) -> str | None:
    """Path of the newest LLVM shared library with major version >= ``min_major``, or None."""
    best: tuple[int, str] | None = None
    for pattern in _SEARCH_GLOBS:
        for path in glob.glob(pattern):
            major = _llvm_major(path)
            if major is None or major < min_major or not os.path.isfile(path):
                continue
            if best is None or major > best[0]:
                best = (major, path)
    return best[1] if best else None


def variant_name() -> str:
    """The variant mifacerf uses: ``$MIFACERF_VARIANT`` or :data:`DEFAULT_VARIANT`."""
    return os.environ.get("MIFACERF_VARIANT", "").strip() or DEFAULT_VARIANT


def ensure_variant():
    """Select the Mitsuba variant (once) and return the ``mitsuba`` module.

    Raises :class:`VariantError` with an actionable message when the variant
    is unknown or the LLVM backend has no usable libLLVM.
    """
    name = variant_name()
    if name.startswith("llvm") and "DRJIT_LIBLLVM_PATH" not in os.environ:
        lib = find_libllvm()
        if lib is None:
            raise VariantError(
                f"Mitsuba variant {name!r} needs an LLVM >= {MIN_LLVM_MAJOR} shared library and none "
                "was found (LLVM 14/15 fail with 'Cannot select: fminimum'). On Debian/Ubuntu run "
                "'apt-get install libllvm19' (the README's set-up does this), point "
                "DRJIT_LIBLLVM_PATH at a libLLVM.so >= 16, or choose another variant with "
                "MIFACERF_VARIANT (e.g. cuda_ad_rgb, or the slow scalar_rgb)."
            )
        os.environ["DRJIT_LIBLLVM_PATH"] = lib
    import mitsuba as mi

    if mi.variant() == name:
        return mi
    if name not in mi.variants():
        raise VariantError(
            f"MIFACERF_VARIANT={name!r} is not a Mitsuba variant of this installation; "
            f"available: {', '.join(mi.variants())}"
        )
    try:
        mi.set_variant(name)
    except Exception as exc:  # the backend failed to initialise (no GPU, no libLLVM, ...)
        raise VariantError(f"Mitsuba variant {name!r} could not be initialised: {exc}") from exc
    return mi


def ensure_plugins():
    """Select the variant (:func:`ensure_variant`), register mifacerf's Mitsuba plugins, return ``mitsuba``.

    Idempotent: the plugins register themselves (``mi.register_integrator("facerf", ...)``,
    ``mi.register_bsdf("facerf_bsdf", ...)``) when :data:`PLUGINS_PACKAGE` is first imported, and
    a module is imported once. The package is named here rather than imported: the plugins wrap
    the renderer (they sit on the rendering floor), while this module is on the ground floor.
    """
    mi = ensure_variant()
    importlib.import_module(PLUGINS_PACKAGE)
    return mi
