"""The light package root: ``import mifacerf``, the pure modules and ``mifacerf --help`` load no Mitsuba.

Each check runs in a fresh interpreter (the test process itself has long imported Mitsuba). The
Mitsuba-user orders (``import mitsuba`` before or after ``import mifacerf``) are checked with a
built model in ``tests/rendering/test_plugin_registration.py``.
"""
import json
import subprocess
import sys
import time

import click
import pytest

from helpers.source_tree import ROOT, source_modules

HEAVY = ("mitsuba", "drjit")


def _modules_after(code: str) -> set[str]:
    """The names in ``sys.modules`` after running ``code`` in a fresh interpreter."""
    probe = code + "\nimport json as _j, sys as _s\nprint('MODULES=' + _j.dumps(sorted(_s.modules)))\n"
    r = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    line = [x for x in r.stdout.splitlines() if x.startswith("MODULES=")][-1]
    return set(json.loads(line[len("MODULES="):]))


@pytest.mark.parametrize("module", ["mifacerf", "mifacerf.capture.hardware.protocol", "mifacerf.formats.capture"])
def test_pure_module_imports_without_mitsuba(module):
    loaded = _modules_after(f"import {module}")
    assert not [m for m in HEAVY if m in loaded], f"import {module} loads {[m for m in HEAVY if m in loaded]}"
    assert "mifacerf.plugins" not in loaded and "mifacerf.rendering" not in loaded


def test_root_loads_nothing_but_itself():
    loaded = _modules_after("import mifacerf")
    assert sorted(m for m in loaded if m.startswith("mifacerf")) == ["mifacerf"]
    assert "numpy" not in loaded


def test_no_module_but_the_plugins_imports_mitsuba_at_import_time():
    """Mitsuba is loaded on first use (``variant.ensure_variant()`` inside functions), never by an import."""
    names = [m for m in source_modules() if not m.startswith("mifacerf.plugins")]
    code = (
        "import importlib, sys\n"
        f"for name in {names!r}:\n"
        "    importlib.import_module(name)\n"
        f"    heavy = [m for m in {HEAVY!r} if m in sys.modules]\n"
        "    if heavy:\n"
        "        raise SystemExit(f'import {name} loads {heavy}')\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert r.returncode == 0, (r.stderr or r.stdout)[-2000:]


HELP = "import sys\nfrom mifacerf.cli import main\nsys.argv = ['mifacerf', '--help']\ntry:\n    main()\nexcept SystemExit:\n    pass\n"


def test_help_imports_no_stage():
    loaded = _modules_after(HELP)
    ours = sorted(m for m in loaded if m.startswith("mifacerf"))
    assert ours == ["mifacerf", "mifacerf.cli"], f"mifacerf --help imports {ours}"
    assert not [m for m in (*HEAVY, "numpy") if m in loaded]


def test_help_is_fast():
    """``mifacerf --help`` under 0.5 s (best of three: the machine is shared)."""
    times = []
    for _ in range(3):
        t0 = time.perf_counter()
        r = subprocess.run([sys.executable, "-c", "from mifacerf.cli import main; main()", "--help"],
                           capture_output=True, text=True, cwd=ROOT, timeout=60)
        times.append(time.perf_counter() - t0)
        assert r.returncode == 0 and "Commands:" in r.stdout, r.stderr
    assert min(times) < 0.5, times


def test_help_summaries_match_the_commands():
    """The summaries ``--help`` shows without importing are the commands' own short help."""
    from click.testing import CliRunner

    from mifacerf.cli import LAZY_COMMANDS, load_command, main

    for name, (_, summary) in LAZY_COMMANDS.items():
        cmd = load_command(name)
        assert isinstance(cmd, click.Command) and not cmd.hidden, name
        for limit in (20, 45, 80, 1000):
            assert click.Command(name, help=summary).get_short_help_str(limit) == cmd.get_short_help_str(limit), (
                f"{name}: LAZY_COMMANDS' summary {summary!r} is not the first sentence of the command's help "
                f"{cmd.get_short_help_str(1000)!r}; copy that sentence into mifacerf/cli.py")
    out = CliRunner().invoke(main, ["--help"]).output
    for name in LAZY_COMMANDS:
        assert f"\n  {name} " in out, name
