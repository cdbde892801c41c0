"""The source tree as installed modules, for the packaging, architecture and package-root tests.

``capture/`` and ``plugins/`` sit at the top of the repository and install as ``mifacerf.capture``
and ``mifacerf.plugins``: the mapping is pyproject's ``[tool.setuptools] package-dir``, read here
so that the tests name every file by the module it becomes.
"""
from __future__ import annotations

import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def pyproject() -> dict:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())


def package_dirs() -> dict[str, Path]:
    """{installed package: source folder} from pyproject's ``package-dir``."""
    return {pkg: ROOT / folder for pkg, folder in pyproject()["tool"]["setuptools"]["package-dir"].items()}


def _walk(pkg: str, folder: Path, skip: set[Path]):
    """(package, folder) of ``folder`` and every folder below it with an ``__init__.py`` on the way down."""
    if folder in skip or not (folder / "__init__.py").is_file():
        return
    yield pkg, folder
    for sub in sorted(p for p in folder.iterdir() if p.is_dir() and p.name != "__pycache__"):
        yield from _walk(f"{pkg}.{sub.name}", sub, skip)


def source_packages() -> dict[str, Path]:
    """{installed package name: source folder} of every package in the tree."""
    dirs = package_dirs()
    skip = set(dirs.values())
    out = {}
    for pkg, folder in dirs.items():
        out.update(_walk(pkg, folder, skip - {folder}))
    return dict(sorted(out.items()))


def source_modules() -> dict[str, Path]:
    """{module name: file} of every ``.py`` file of every package (a package's ``__init__`` is the package)."""
    out = {}
    for pkg, folder in source_packages().items():
        for f in sorted(folder.glob("*.py")):
            out[pkg if f.stem == "__init__" else f"{pkg}.{f.stem}"] = f
    return dict(sorted(out.items()))


def stray_files() -> list[Path]:
    """``.py`` files under the mapped folders that no package holds (they would not be installed)."""
    held = set(source_modules().values())
    return sorted(f for folder in package_dirs().values() for f in folder.rglob("*.py")
                  if "__pycache__" not in f.parts and f not in held)
