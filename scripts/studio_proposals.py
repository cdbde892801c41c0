"""Registration from the studio's proposals accepted unedited, against registration from the synthetic
user's (truth-derived) hand inputs — the table in docs/registration.md.

    python scripts/studio_proposals.py OUT [--preset tiny] [--expressions neutral,smile,...] [--json FILE]

1. ``mifacerf synth OUT/synth`` (skipped when it exists); its truth is moved to ``OUT/hidden-truth``.
2. *hand*: a copy of the capture with the synthetic user's hand inputs, registered (``register_capture``).
3. *proposed*: a copy whose ``hand/coarse_points.json`` and ``hand/rotoscope/`` are deleted — the
   template stays the user's (``--proposed-template`` replaces it by the studio's proposal from the
   neutral's images, which has no margins, eyes or teeth and other vertices, so its errors are not
   comparable vertex by vertex and are not evaluated). Expression by expression, the neutral first, the
   studio proposes the coarse points, curves and marks (:func:`mifacerf.studio.proposals.propose_expression`,
   from the nearest registered expression), they are saved unedited, and the expression is registered
   (:func:`mifacerf.studio.jobs.register_expression`, as the page's button). An audit hook fails the
   run if anything under the truth folder is opened during this step.
4. Both registrations are evaluated against the truth (:func:`mifacerf.evaluation.registration.evaluate`),
   and the proposals are compared with the synthetic user's inputs: a scripted user edits every
   proposal that is missing or off by more than ``--tolerance-px`` (a coarse point's 3-D position, in
   pixel footprints; a curve's RMS distance to the user's polyline in the views both have; a mark) —
   each such edit is one click-in-two-views or one curve redrawn.
"""
from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np


def _curve_rms(a: np.ndarray, b: np.ndarray) -> float:
    """RMS distance (px) of polyline a's vertices from polyline b (segments)."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    if len(b) < 2:
        return float(np.sqrt(np.mean(np.sum((a - b[0]) ** 2, 1))))
    p, q = b[:-1], b[1:]
    d = q - p
    t = np.clip(np.einsum("nij,ij->ni", a[:, None] - p[None], d) / np.maximum((d * d).sum(1), 1e-12), 0, 1)
    proj = p[None] + t[..., None] * d[None]
    return float(np.sqrt(np.mean(np.min(np.sum((a[:, None] - proj) ** 2, -1), 1))))


def edits_needed(session, name: str, proposed: dict, user: dict, tol_px: float) -> dict:
    from mifacerf.geometry.footprint import centre_footprint

    fp = centre_footprint(session.cams)
    out = {"coarse_missing": 0, "coarse_off": 0, "curves_missing": 0, "curves_off": 0, "marks_missing": 0,
           "marks_off": 0}
    for vid, item in user["coarse"].items():
        if item.get("position") is None:
            continue
        p = proposed["coarse"].get(vid)
        if p is None or p.get("position") is None:
            out["coarse_missing"] += 1
        elif np.linalg.norm(np.subtract(p["position"], item["position"])) > tol_px * fp:
            out["coarse_off"] += 1
    for cname, views in user["rotoscope"]["curves"].items():
        pv = proposed["rotoscope"]["curves"].get(cname, {})
        shared = [c for c in views if c in pv]
        if len(pv) < 2:
            out["curves_missing"] += 1
        elif not shared or max(_curve_rms(pv[c], views[c]) for c in shared) > tol_px:
            out["curves_off"] += 1
    for pname, views in user["rotoscope"]["points"].items():
        pv = proposed["rotoscope"]["points"].get(pname, {})
        shared = [c for c in views if c in pv]
        if len(pv) < 2:
            out["marks_missing"] += 1
        elif not shared or max(np.hypot(*np.subtract(pv[c], views[c])) for c in shared) > tol_px:
            out["marks_off"] += 1
    out["total"] = sum(out.values())
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--preset", default="tiny")
    ap.add_argument("--expressions", default=None, help="comma-separated (default: the preset's)")
    ap.add_argument("--tolerance-px", type=float, default=2.0)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)

    from mifacerf.evaluation.registration import evaluate
    from mifacerf.registration import register_capture
    from mifacerf.studio.jobs import register_expression
    from mifacerf.studio.proposals import propose_expression
    from mifacerf.studio.session import Session
    from mifacerf.synthetic.synth import synthesize

    out = args.out
    synth, truth = out / "synth", out / "hidden-truth"
    if not (synth / "capture" / "manifest.json").exists():
        exprs = args.expressions.split(",") if args.expressions else None
        t0 = time.time()
        synthesize(synth, preset=args.preset, expressions=exprs, progress=False)
        print(f"synthesised in {time.time() - t0:.0f} s", flush=True)
    if (synth / "truth").exists():
        if truth.exists():
            shutil.rmtree(truth)
        shutil.move(str(synth / "truth"), truth)
    hand_cap, prop_cap = out / "hand" / "capture", out / "proposed" / "capture"
    for d in (hand_cap, prop_cap):
        if d.parent.exists():
            shutil.rmtree(d.parent)
        shutil.copytree(synth / "capture", d, ignore=shutil.ignore_patterns("registration"))
    t0 = time.time()
    register_capture(hand_cap, progress=False)
    t_hand = time.time() - t0
    print(f"registered from the user's hand inputs in {t_hand:.0f} s", flush=True)

    user = Session(hand_cap)
    (prop_cap / "hand" / "coarse_points.json").unlink()
    shutil.rmtree(prop_cap / "hand" / "rotoscope")
    opened = []
    root = str(truth.resolve())

    def audit(event, a):
        if event == "open" and a and isinstance(a[0], str) and a[0].startswith(root):
            opened.append(a[0])
    sys.addaudithook(audit)
    s = Session(prop_cap)
    order = [s.neutral] + [n for n in s.cap.expression_names if n != s.neutral]
    edits, sources = {}, {}
    t0 = time.time()
    for name in order:
        p = propose_expression(s, name)
        sources[name] = p["source"]
        state = p["state"] or {}
        s.save_hand(name, state, s.version(name))
        edits[name] = edits_needed(s, name, s.hand_state(name), user.hand_state(name), args.tolerance_px)
        register_expression(prop_cap, name)
        s.invalidate()
        print(f"  {name}: proposed from {p['source']}; {p['note']}", flush=True)
    t_prop = time.time() - t0
    truth_opened = list(opened)
    opened.clear()
    assert not truth_opened, f"the proposals chain opened truth files: {truth_opened[:3]}"

    ev_hand = evaluate(hand_cap, truth)["per_expression"]
    ev_prop = evaluate(prop_cap, truth)["per_expression"]
    rows = []
    print()
    print("| expression | proposed from | registered (hand / proposed) | median px (hand / proposed) | "
          "p95 px (hand / proposed) | > 3 px off (hand / proposed) | edits needed (coarse, curves, marks) |")
    print("|---|---|---|---|---|---|---|")
    for name in order:
        h, p, e = ev_hand[name], ev_prop[name], edits[name]
        rows.append({"expression": name, "source": sources[name], "hand": h, "proposed": p, "edits": e})
        print(f"| {name} | {sources[name]} | {100 * h['registered_fraction']:.1f}% / {100 * p['registered_fraction']:.1f}% "
              f"| {h['median_px']:.2f} / {p['median_px']:.2f} | {h['p95_px']:.2f} / {p['p95_px']:.2f} "
              f"| {100 * h['misregistered_fraction']:.1f}% / {100 * p['misregistered_fraction']:.1f}% "
              f"| {e['total']} ({e['coarse_missing'] + e['coarse_off']}, {e['curves_missing'] + e['curves_off']}, "
              f"{e['marks_missing'] + e['marks_off']}) |")
    print(f"\nregistration time: hand {t_hand:.0f} s, proposals + registration {t_prop:.0f} s; "
          f"truth files opened by the proposal chain: {len(truth_opened)}")
    if args.json:
        args.json.write_text(json.dumps({"rows": rows, "time_s": {"hand": t_hand, "proposed": t_prop},
                                         "tolerance_px": args.tolerance_px}, indent=1, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
