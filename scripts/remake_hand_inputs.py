"""Write a synth output's ``capture/hand/`` again with the current subject loader (its template, teeth
strips, extensions and clicks), keeping the images: for a capture made by an older loader whose dots
are the same (the script checks) — docs/your-own-head.md, "Measured"::

    python scripts/remake_hand_inputs.py SYNTH_OUT
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np


def main(out: str) -> None:
    from mifacerf.formats.capture import Capture
    from mifacerf.synthetic.hand_inputs import write_hand_inputs
    from mifacerf.synthetic.presets import Expression
    from mifacerf.synthetic.synth import read_truth, subject_from_truth

    out = Path(out)
    truth = read_truth(out)
    subject = subject_from_truth(out)
    painted = np.load(out / "truth" / "expressions" / "neutral.npz")["dots"]
    if painted.shape != subject.dots_neutral.shape or np.abs(painted - subject.dots_neutral).max() > 1e-9:
        raise SystemExit(f"{out}: the current loader places other dots than the images show; synthesise again")
    exprs = [Expression(e["name"], e["category"], np.asarray(e["params"])) for e in truth["expressions"]]
    poses = {e.name: subject.pose(e.params) for e in exprs}
    write_hand_inputs(out / "capture", subject, exprs, poses, Capture(out / "capture").rig)
    print(f"{out / 'capture' / 'hand'}: {len(subject.template.kinds)} template vertices, teeth "
          f"{sorted(subject.template.teeth)}, extensions {sorted(subject.template.extensions)}")


if __name__ == "__main__":
    main(sys.argv[1])
