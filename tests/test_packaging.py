"""The built wheel holds every package, module and data file of the tree, under its installed name.

``capture/`` and ``plugins/`` install as ``mifacerf.capture`` and ``mifacerf.plugins`` through
pyproject's ``package-dir``, and ``packages`` lists every package by hand: a package added to the tree
but not to that list is silently left out of an install. This test builds the wheel offline (pip,
no build isolation, from a copy of the sources so the tree gets no ``build/``), unpacks it (a pure
wheel unpacks to what ``pip install --target`` writes) and imports every module from there.
"""
import configparser
import shutil
import subprocess
import sys
import zipfile

import pytest

from helpers.source_tree import ROOT, package_dirs, pyproject, source_modules, source_packages, stray_files


def _installed_path(module: str, package: bool) -> str:
    return module.replace(".", "/") + ("/__init__.py" if package else ".py")


def _data_files(packages: dict) -> list[str]:
    """Installed paths of the non-Python files of each package (its folder and non-package sub-folders)."""
    out = []
    for pkg, folder in packages.items():
        for f in sorted(folder.rglob("*")):
            if not f.is_file() or f.suffix in (".py", ".pyc") or "__pycache__" in f.parts:
                continue
            if next(d for d in f.parents if (d / "__init__.py").is_file()) == folder:
                out.append(f"{pkg.replace('.', '/')}/{f.relative_to(folder).as_posix()}")
    return out


@pytest.fixture(scope="module")
def wheel(tmp_path_factory):
    """(names in the wheel, folder it is unpacked to)."""
    tmp = tmp_path_factory.mktemp("wheel")
    src = tmp / "src"
    src.mkdir()
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc")
    shutil.copy2(ROOT / "pyproject.toml", src)
    shutil.copy2(ROOT / pyproject()["project"]["readme"], src)
    for folder in {p.relative_to(ROOT).parts[0] for p in package_dirs().values()}:
        shutil.copytree(ROOT / folder, src / folder, ignore=ignore)
    r = subprocess.run([sys.executable, "-m", "pip", "wheel", ".", "--no-deps", "--no-build-isolation",
                        "--no-index", "-q", "-w", str(tmp / "dist")], cwd=src, capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, ("pip wheel failed (the test extra provides 'wheel': pip install -e '.[test]')\n"
                               + r.stderr[-3000:])
    (whl,) = (tmp / "dist").glob("mifacerf-*.whl")
    site = tmp / "site"
    with zipfile.ZipFile(whl) as z:
        names = set(z.namelist())
        z.extractall(site)
    return names, site


def test_every_package_module_and_data_file_is_in_the_wheel(wheel):
    names, site = wheel
    (info,) = {n.split("/")[0] for n in names if n.split("/")[0].endswith(".dist-info")}
    meta = configparser.ConfigParser()
    meta.read_string("[wheel]\n" + (site / info / "WHEEL").read_text())
    assert meta["wheel"]["Root-Is-Purelib"] == "true"
    assert not stray_files(), f"not in any package (no __init__.py on the way): {stray_files()}"
    packages = source_packages()
    missing = [p for p in packages if _installed_path(p, True) not in names]
    assert not missing, (f"packages of the tree missing from the wheel: {missing}; add them to "
                         "[tool.setuptools] packages in pyproject.toml (capture/ and plugins/ install as "
                         "mifacerf.capture, mifacerf.plugins)")
    missing = [m for m in source_modules() if _installed_path(m, m in packages) not in names]
    assert not missing, f"modules missing from the wheel: {missing}"
    data = _data_files(packages)
    missing = [d for d in data if d not in names]
    assert not missing, f"data files missing from the wheel (pyproject's package-data): {missing}"
    installed = {n[:-len("/__init__.py")].replace("/", ".") for n in names if n.endswith("/__init__.py")}
    assert installed == set(packages), f"the wheel's packages differ from the tree's: {installed ^ set(packages)}"
    scripts = configparser.ConfigParser()
    scripts.read_string((site / info / "entry_points.txt").read_text())
    assert dict(scripts["console_scripts"]) == pyproject()["project"]["scripts"]


def test_every_module_imports_from_the_wheel(wheel):
    """Every module of the tree imports from the unpacked wheel, and from nowhere else."""
    _, site = wheel
    code = (
        "import importlib, sys\n"
        # the development install's finder would answer for anything the wheel lacks
        "sys.meta_path[:] = [f for f in sys.meta_path if not getattr(f, '__module__', '').startswith('__editable__')]\n"
        f"sys.path.insert(0, {str(site)!r})\n"
        f"for name in {list(source_modules())!r}:\n"
        "    m = importlib.import_module(name)\n"
        f"    assert m.__file__.startswith({str(site)!r}), (name, m.__file__)\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=site, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
