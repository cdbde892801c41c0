"""Bad values for EVERY option of every command, generated from the click command objects (a new
option is covered without editing this file): NaN, ±inf, below its range (zero, negative) for numbers,
the empty string for text and paths. Each must be a usage error (exit 2) naming the option, with no
traceback and nothing written. Number options must declare their domain (click.IntRange/FloatRange);
the few that take any finite value are listed here with the reason."""
import math

import click
import pytest
from click.testing import CliRunner

from mifacerf.cli import LAZY_COMMANDS, load_command, main

#: (command path, option): why any finite value is right
UNBOUNDED = {("truth", "--yaw"): "an angle", ("truth", "--pitch"): "an angle"}


def _commands():
    def walk(cmd, path):
        if isinstance(cmd, click.Group):
            for n, c in sorted(cmd.commands.items()):
                yield from walk(c, path + [n])
        else:
            yield path, cmd
    for name in sorted(LAZY_COMMANDS):
        yield from walk(load_command(name), [name])


def _cases():
    cases = []
    for path, cmd in _commands():
        for p in cmd.params:
            if isinstance(p, click.Option) and (p.is_flag or p.count or p.hidden and p.name == "crash_after_frames"):
                continue
            t = p.type
            flag = p.opts[-1] if isinstance(p, click.Option) else None
            key = (" ".join(path), flag or p.name)
            if isinstance(t, (click.types.IntParamType, click.types.FloatParamType)):
                values = ["nan", "inf", "-inf"] if isinstance(t, click.types.FloatParamType) else []
                lo = getattr(t, "min", None)
                if lo is None and key not in {(" ".join(k[0].split()), k[1]) for k in UNBOUNDED}:
                    values.append("UNBOUNDED")
                elif lo is not None:
                    below = lo if getattr(t, "min_open", False) else (lo - 1 if isinstance(lo, int) else lo - 1e-3)
                    values += sorted({str(below), str(min(below, -1))})
                if getattr(t, "max", None) is not None:
                    values.append(str(t.max + 1))
                values.append("")
            elif isinstance(t, (click.types.StringParamType, click.Path)):
                values = [""]
            elif isinstance(t, click.Choice):
                values = ["", "no-such-choice"]
            else:
                continue
            cases += [pytest.param(path, p, v, id=f"{' '.join(path)} {flag or p.name.upper()}={v!r}") for v in values]
    return cases


def _invoke(path, param, value):
    args = [*path, param.opts[-1], value] if isinstance(param, click.Option) else [*path, value]
    return CliRunner().invoke(main, args)


@pytest.mark.parametrize("path, param, value", _cases())
def test_bad_value_is_a_usage_error_naming_the_option(path, param, value, tmp_path, monkeypatch):
    assert value != "UNBOUNDED", f"{' '.join(path)} {param.opts[-1]}: declare its range (click.IntRange/FloatRange)"
    monkeypatch.chdir(tmp_path)
    r = _invoke(path, param, value)
    assert r.exit_code == 2, f"{' '.join(path)} {param.opts[-1]} {value!r}: exit {r.exit_code}\n{r.output}"
    assert "Traceback" not in r.output
    names = [*param.opts, param.name.upper(), param.human_readable_name]
    assert any(n in r.output for n in names), r.output
    assert list(tmp_path.iterdir()) == [], "a refused option wrote files"


def test_every_command_is_covered():
    covered = {" ".join(p.values[0]) for p in _cases()}
    assert covered >= {"capture", "build", "register", "render", "synth", "track", "drive", "bench", "compress"}
    assert len(_cases()) > 150
