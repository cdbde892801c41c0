"""Register one capture twice — with the default options and with one option changed — and print the
truth's verdict on both side by side (evaluation only: the truth is read after registering)::

    python scripts/registration_side_by_side.py SYNTH_OUT OPTION=VALUE [--out DIR]

``SYNTH_OUT`` a ``mifacerf synth`` folder (``capture/``, ``truth/``); ``OPTION`` a field of
:class:`mifacerf.registration.register.Options` (``refit=false``, ``radius_px=4``). The two
registrations go to ``DIR/default`` and ``DIR/OPTION`` (default ``SYNTH_OUT/side_by_side``), the
capture's own registration is left alone. Prints per expression: registered fraction, of those imaged
in two views, registered dots more than 3 px off, p95 error (px), the fiducials only one run registered,
and both runs' wall times.
"""
from __future__ import annotations

import dataclasses
import sys
import time
from pathlib import Path


def _value(field, text: str):
    kind = field.type if isinstance(field.type, str) else field.type.__name__
    if "bool" in kind:
        if text.lower() not in ("true", "false", "1", "0"):
            raise SystemExit(f"{field.name}: expected true or false, got {text!r}")
        return text.lower() in ("true", "1")
    return type(field.default)(text)


def main(argv: list[str]) -> None:
    import numpy as np

    from mifacerf.evaluation.registration import evaluate
    from mifacerf.formats.registration import Registration
    from mifacerf.registration import register_capture
    from mifacerf.registration.hand import Template
    from mifacerf.registration.register import Options

    if len(argv) < 2 or "=" not in argv[1]:
        raise SystemExit(__doc__)
    synth, (key, text) = Path(argv[0]), argv[1].split("=", 1)
    out = Path(argv[argv.index("--out") + 1]) if "--out" in argv else synth / "side_by_side"
    fields = {f.name: f for f in dataclasses.fields(Options)}
    if key not in fields:
        raise SystemExit(f"{key}: not a registration option (one of {', '.join(sorted(fields))})")
    runs = {"default": Options(), f"{key}={text}": Options(**{key: _value(fields[key], text)})}
    rows, regs, times = {}, {}, {}
    for name, opt in runs.items():
        t = time.time()
        d = register_capture(synth / "capture", out=out / name.split("=")[0], options=opt, progress=False,
                             force=True)
        times[name] = time.time() - t
        rows[name] = evaluate(synth / "capture", synth / "truth", d, dots_residual=False)["per_expression"]
        regs[name] = Registration(d)
    a, b = runs
    print(f"| expression | registered {a} / {b} | of imaged | > 3 px off | p95 px | only {a} | only {b} |")
    print("|---|---|---|---|---|---|---|")
    for n in rows[a]:
        ra, rb = rows[a][n], rows[b][n]
        sa, sb = regs[a].expression(n).status, regs[b].expression(n).status
        dots = Template.from_dict(regs[a].template).dot_ids
        only_a = [int(v) for v in dots if sa[v] == 1 and sb[v] != 1]
        only_b = [int(v) for v in dots if sb[v] == 1 and sa[v] != 1]
        print(f"| {n} | {100 * ra['registered_fraction']:.1f} / {100 * rb['registered_fraction']:.1f} % "
              f"| {100 * ra['registered_of_imaged']:.1f} / {100 * rb['registered_of_imaged']:.1f} % "
              f"| {100 * ra['misregistered_fraction']:.2f} / {100 * rb['misregistered_fraction']:.2f} % "
              f"| {ra['p95_px']:.2f} / {rb['p95_px']:.2f} | {only_a} | {only_b} |")
    mean = {k: np.mean([r["registered_fraction"] for r in rows[k].values()]) for k in runs}
    print(f"mean registered {100 * mean[a]:.2f} % / {100 * mean[b]:.2f} %; wall {times[a]:.1f} s / {times[b]:.1f} s")


if __name__ == "__main__":
    main(sys.argv[1:])
