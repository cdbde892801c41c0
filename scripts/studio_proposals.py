"""Registration from the studio's proposals accepted unedited, against registration from the synthetic
user's (truth-derived) hand inputs — the tables in docs/registration.md.

    python scripts/studio_proposals.py OUT [--preset tiny] [--expressions neutral,smile,...]
                                       [--capture CAPTURE --truth TRUTH] [--proposed-template] [--json FILE]
    python scripts/studio_proposals.py OUT --capture CAPTURE --truth TRUTH --check-template-only

1. ``mifacerf synth OUT/synth`` (skipped when it exists, or when ``--capture``/``--truth`` name an
   existing synthetic capture and its truth, which are only read: the copies below hard-link the images);
   its truth is moved to ``OUT/hidden-truth``.
2. *hand*: a copy of the capture with the synthetic user's hand inputs, registered (``register_capture``;
   skipped when ``OUT/hand/capture/registration`` already holds every expression).
3. *proposed*: a copy whose ``hand/coarse_points.json`` and ``hand/rotoscope/`` are deleted — with
   ``--proposed-template`` the whole ``hand/`` is deleted and the template is the studio's proposal from the
   neutral's images (:func:`mifacerf.studio.template_proposal.propose_template`), accepted unedited.
   Expression by expression, the neutral first, the studio proposes the coarse points, curves and marks
   (:func:`mifacerf.studio.proposals.propose_expression`, from the nearest registered expression), they are
   saved unedited, and the expression is registered (:func:`mifacerf.studio.jobs.register_expression`, as
   the page's button). An audit hook fails the run if anything under the truth folder is opened during
   this step.
4. Both registrations are evaluated against the truth (:func:`mifacerf.evaluation.registration.evaluate`;
   for a proposed template, whose vertices are other points than the truth's, each proposed dot is matched
   to the true fiducial nearest it on the neutral (within 1.5 mm, one to one) and the fraction registered
   is of the truth's fiducials), and the proposals are compared with the synthetic user's inputs: a scripted
   user edits every proposal that is missing or off by more than ``--tolerance-px`` (a coarse point's 3-D
   position, in pixel footprints, against the user's — or, for a proposed template, against the truth of
   its matched fiducial; a curve's RMS distance to the user's polyline in the views both have; a mark) —
   each such edit is one click-in-two-views or one curve redrawn. The flags the studio raises on its own
   proposals (``flagged`` in the proposal) are counted beside them: how many of the edits the page points at.
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


def edits_needed(session, name: str, proposed: dict, user: dict, tol_px: float, coarse_truth: dict | None = None,
                 flagged=()) -> dict:
    """The edits a scripted user makes (see the module docstring). ``coarse_truth`` {proposed coarse id:
    true position or None}: the reference for a proposed template's coarse points (else the user's)."""
    from mifacerf.geometry.footprint import centre_footprint

    fp = centre_footprint(session.cams)
    out = {"coarse_missing": 0, "coarse_off": 0, "curves_missing": 0, "curves_off": 0, "marks_missing": 0,
           "marks_off": 0}
    wrong = set()
    if coarse_truth is None:
        for vid, item in user["coarse"].items():
            if item.get("position") is None:
                continue
            p = proposed["coarse"].get(vid)
            if p is None or p.get("position") is None:
                out["coarse_missing"] += 1
                wrong.add(vid)
            elif np.linalg.norm(np.subtract(p["position"], item["position"])) > tol_px * fp:
                out["coarse_off"] += 1
                wrong.add(vid)
    else:
        for vid, X in coarse_truth.items():
            p = proposed["coarse"].get(vid)
            if p is None or p.get("position") is None:
                out["coarse_missing"] += 1
                wrong.add(vid)
            elif X is None or np.linalg.norm(np.subtract(p["position"], X)) > tol_px * fp:
                out["coarse_off"] += 1      # on no true dot at all, or on another one
                wrong.add(vid)
    flagged = {str(v) for v in flagged}
    out_flags = {"flagged": len(flagged), "flagged_and_wrong": len(flagged & wrong)}
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
    out.update(out_flags)
    return out


def match_truth(tpl, truth_neutral: np.ndarray, truth_dots: np.ndarray, tol: float = 0.0015) -> dict:
    """{proposed dot id: true fiducial id}: each proposed dot to the nearest true fiducial on the neutral
    within ``tol`` metres, one to one (the nearer pair wins)."""
    from scipy.spatial import cKDTree

    ids = tpl.dot_ids
    d, k = cKDTree(truth_neutral[truth_dots]).query(tpl.vertices[ids])
    best = {}
    for vid, dist, j in sorted(zip(ids, d, k), key=lambda t: t[1]):
        if dist <= tol and truth_dots[j] not in best.values():
            best[int(vid)] = int(truth_dots[j])
    return best


def proposed_coarse_truth(ptpl, match: dict, user_tpl, user_coarse: dict, T: np.ndarray) -> dict:
    """{proposed coarse id: reference position or None} for one expression: a dot's matched true fiducial
    (T: the truth's template vertices), a mouth corner's the user's clicked corner on the same side."""
    out = {}
    corners = {np.sign(user_tpl.vertices[int(k), 0]): item.get("position") for k, item in user_coarse.items()
               if user_tpl.kinds[int(k)] == "lip_corner"}
    for v in ptpl.coarse:
        v = int(v)
        if ptpl.kinds[v] == "lip_corner":
            out[str(v)] = corners.get(np.sign(ptpl.vertices[v, 0]))
        else:
            out[str(v)] = T[match[v]] if v in match else None
    return out


def evaluate_proposed_template(cap_dir: Path, truth: Path, truth_dots: np.ndarray) -> tuple[dict, dict]:
    """Per expression, the registration into a proposed template against the truth: registered of the
    truth's fiducials, median / p95 error (px) of the registered matched dots, share > 3 px off; and the
    match {proposed id: true id}."""
    from mifacerf.evaluation.registration import footprints
    from mifacerf.formats.capture import Capture
    from mifacerf.formats.registration import Registration
    from mifacerf.geometry.visibility import Visibility
    from mifacerf.registration.hand import Template

    cap = Capture(cap_dir)
    reg = Registration(cap_dir / "registration", capture=cap)
    tpl = Template.from_dict(reg.template)
    names = reg.expression_names
    T0 = np.load(truth / "expressions" / f"{names[0]}.npz")["template_vertices"]
    match = match_truth(tpl, T0, truth_dots)
    pid = np.array(sorted(match), np.int64)
    tid = np.array([match[int(v)] for v in pid], np.int64)
    vis = Visibility(tpl.triangles, tpl.n_vertices, tol=5e-4)
    rows = {}
    for name in names:
        r = reg.expression(name)
        T = np.load(truth / "expressions" / f"{name}.npz")["template_vertices"]
        ok = r.status[pid] == 1
        err = np.linalg.norm(r.vertices[pid] - T[tid], axis=1)
        fp = footprints(cap.rig.cameras, T[tid], vis(r.vertices, cap.rig.cameras, min_cos=0.2)[:, pid])
        e = (err / fp)[ok]
        rows[name] = {"registered_fraction": float(ok.sum() / len(truth_dots)),
                      "registered_of_proposed": float((r.status[tpl.dot_ids] == 1).mean()),
                      "proposed_dots": int(len(tpl.dot_ids)), "matched_dots": int(len(pid)),
                      "median_px": float(np.median(e)) if e.size else None,
                      "p95_px": float(np.percentile(e, 95)) if e.size else None,
                      "misregistered_fraction": float((e > 3.0).mean()) if e.size else 0.0}
    return rows, match


def missed_dots(session, doc: dict, user, truth: Path) -> dict:
    """The true fiducials no proposed dot matches (:func:`match_truth`): how many, by the user's regions, how
    many more than 5 cm to the side, and by the number of views (seen there, in the user's mesh) with a
    peak of the proposal's dot map within 1 px of them; the proposed dots matching none (phantoms) and
    how far each is from the nearest true fiducial (mm)."""
    from scipy.spatial import cKDTree

    from mifacerf.geometry.visibility import Visibility
    from mifacerf.registration.consensus import view_peaks
    from mifacerf.registration.hand import Template
    from mifacerf.registration.proxies import proxies_for
    from mifacerf.studio.proposals import untuned_filter

    ptpl = Template.from_dict(doc)
    T0 = np.load(truth / "expressions" / f"{session.neutral}.npz")["template_vertices"]
    match = match_truth(ptpl, T0, user.dot_ids)
    found = set(match.values())
    miss = np.array([int(v) for v in user.dot_ids if int(v) not in found], np.int64)
    regions = {int(v): k for k, ids in user.regions.items() for v in ids}
    by_region: dict = {}
    for v in miss:
        by_region[regions.get(int(v), "none")] = by_region.get(regions.get(int(v), "none"), 0) + 1
    vis = Visibility(user.triangles, user.n_vertices, tol=5e-4)(T0, session.cams, min_cos=0.2)[:, miss]
    f = untuned_filter(session, use_template=False)
    with_peak = np.zeros(len(miss), np.int64)
    for c, cam in enumerate(session.cams):
        m = f.strength(proxies_for(session.cap, session.neutral, cam.name).diffuse, cam.name)
        pk = view_peaks(m, 0.3, max(1.2, 1.5 * f.sigma)).uv
        if len(pk) and len(miss):
            d, _ = cKDTree(pk).query(cam.project(T0[miss])[0])
            with_peak += (d < 1.0) & vis[c]
    phantoms = [int(v) for v in ptpl.dot_ids if int(v) not in match]
    d_ph = cKDTree(T0[user.dot_ids]).query(ptpl.vertices[phantoms])[0] if phantoms else []
    return {"missed": int(len(miss)), "by_region": dict(sorted(by_region.items(), key=lambda kv: -kv[1])),
            "more_than_5cm_to_the_side": int((np.abs(T0[miss, 0] - T0[user.dot_ids, 0].mean()) > 0.05).sum()),
            "views_with_a_peak": np.bincount(with_peak, minlength=len(session.cams) + 1).tolist(),
            "phantoms_mm": [round(float(x) * 1000, 1) for x in d_ph]}


def template_vs_user(doc: dict, user) -> dict:
    """The proposed template's special vertices against the synthetic user's template (mm): every lip /
    eyelid margin vertex to the nearest vertex of the user's same margins (range), the eye centres."""
    from mifacerf.registration.hand import Template

    t = Template.from_dict(doc)
    out = {}
    for group, names in (("lips", ("lip_upper", "lip_lower")), ("lids_L", ("lid_upper_L", "lid_lower_L")),
                         ("lids_R", ("lid_upper_R", "lid_lower_R"))):
        if not all(n in t.margins and n in user.margins for n in names):
            out[group] = None
            continue
        P = t.vertices[np.unique(np.concatenate([t.margins[n] for n in names]))]
        Q = user.vertices[np.unique(np.concatenate([user.margins[n] for n in names]))]
        d = np.min(np.linalg.norm(P[:, None] - Q[None], axis=-1), axis=1) * 1000
        out[group] = [round(float(d.min()), 1), round(float(np.median(d)), 1), round(float(d.max()), 1)]
    for side in ("L", "R"):
        a, b = t.eyes.get(side, {}).get("centre"), user.eyes.get(side, {}).get("centre")
        out[f"eye_{side}"] = None if a is None or b is None else round(
            float(np.linalg.norm(np.subtract(a, b))) * 1000, 1)
    out["dots"] = int(len(t.dot_ids))
    return out


def _copy_capture(src: Path, dst: Path) -> None:
    """A copy of a capture folder: images and cache hard-linked (never modified in place), the rest copied."""
    import os

    if dst.parent.exists():
        shutil.rmtree(dst.parent)
    dst.mkdir(parents=True)
    for item in src.iterdir():
        if item.name == "registration":
            continue
        if item.name in ("images", "cache"):
            shutil.copytree(item, dst / item.name, copy_function=os.link)
        elif item.is_dir():
            shutil.copytree(item, dst / item.name)
        else:
            shutil.copy2(item, dst / item.name)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--preset", default="tiny")
    ap.add_argument("--expressions", default=None, help="comma-separated (default: the preset's / the capture's)")
    ap.add_argument("--capture", type=Path, default=None, help="an existing synthetic capture (read only)")
    ap.add_argument("--truth", type=Path, default=None, help="its truth folder (read only; with --capture)")
    ap.add_argument("--proposed-template", action="store_true",
                    help="the template too is the studio's proposal (no hand input at all)")
    ap.add_argument("--check-template-only", action="store_true",
                    help="only propose the template and compare its margins and eyes with the user's (mm)")
    ap.add_argument("--tolerance-px", type=float, default=2.0)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)

    from mifacerf.evaluation.registration import evaluate
    from mifacerf.registration import register_capture
    from mifacerf.registration.hand import Template
    from mifacerf.studio.jobs import register_expression
    from mifacerf.studio.proposals import propose_expression
    from mifacerf.studio.session import Session
    from mifacerf.studio.template_proposal import propose_template
    from mifacerf.synthetic.synth import synthesize

    out = args.out
    exprs = args.expressions.split(",") if args.expressions else None
    if args.capture is not None:
        source, truth = args.capture, args.truth
        if truth is None or not (truth / "expressions").is_dir():
            ap.error("--capture needs --truth (the synthetic truth folder)")
    else:
        synth, truth = out / "synth", out / "hidden-truth"
        if not (synth / "capture" / "manifest.json").exists():
            t0 = time.time()
            synthesize(synth, preset=args.preset, expressions=exprs, progress=False)
            print(f"synthesised in {time.time() - t0:.0f} s", flush=True)
        if (synth / "truth").exists():
            if truth.exists():
                shutil.rmtree(truth)
            shutil.move(str(synth / "truth"), truth)
        source = synth / "capture"
    if args.check_template_only:
        r = propose_template(Session(source))
        user_tpl = Template.from_dict(json.loads((source / "hand" / "template.json").read_text()))
        print(r["note"])
        print("proposed vs the user's template (mm; margins: min / median / max to the nearest user vertex):",
              json.dumps(template_vs_user(r["template"], user_tpl)))
        print("the user's fiducials the proposal misses:", json.dumps(missed_dots(Session(source), r["template"],
                                                                                   user_tpl, truth)))
        return 0
    hand_cap = out / "hand" / "capture"
    prop_cap = out / ("proposed-template" if args.proposed_template else "proposed") / "capture"
    t0 = time.time()
    from mifacerf.formats.capture import Capture

    names = exprs or Capture(source).expression_names
    meta = hand_cap / "registration" / "registration.json"
    if not (meta.exists() and set(names) <= set(json.loads(meta.read_text()).get("expressions", {}))):
        _copy_capture(source, hand_cap)
        register_capture(hand_cap, expressions=names, progress=False)
    t_hand = time.time() - t0
    print(f"registered from the user's hand inputs in {t_hand:.0f} s", flush=True)
    _copy_capture(source, prop_cap)

    user = Session(hand_cap)
    if args.proposed_template:
        shutil.rmtree(prop_cap / "hand")
    else:
        (prop_cap / "hand" / "coarse_points.json").unlink()
        shutil.rmtree(prop_cap / "hand" / "rotoscope")
    opened = []
    root = str(truth.resolve())

    def audit(event, a):
        if event == "open" and a and isinstance(a[0], str) and a[0].startswith(root):
            opened.append(a[0])
    sys.addaudithook(audit)
    s = Session(prop_cap)
    order = [s.neutral] + [n for n in names if n != s.neutral]
    edits, sources, states, flags = {}, {}, {}, {}
    t0 = time.time()
    tnote = None
    if args.proposed_template:
        r = propose_template(s)
        if r["template"] is None:
            raise SystemExit(f"no template proposed: {r['note']}")
        s.save_template(r["template"])
        tnote = r["note"]
        print(f"  template: {tnote}", flush=True)
        user_tpl = Template.from_dict(json.loads((hand_cap / "hand" / "template.json").read_text()))
        print(f"  proposed vs the user's template (mm): {json.dumps(template_vs_user(r['template'], user_tpl))}",
              flush=True)
    for name in order:
        p = propose_expression(s, name)
        sources[name] = p["source"]
        state = p["state"] or {}
        flags[name] = p.get("flagged", {})
        s.save_hand(name, state, s.version(name))
        states[name] = s.hand_state(name)
        register_expression(prop_cap, name)
        s.invalidate()
        print(f"  {name}: proposed from {p['source']}; {p['note']}", flush=True)
    t_prop = time.time() - t0
    truth_opened = list(opened)
    opened.clear()
    assert not truth_opened, f"the proposals chain opened truth files: {truth_opened[:3]}"

    ev_hand = evaluate(hand_cap, truth, expressions=order)["per_expression"]
    coarse_truth = None
    if args.proposed_template:
        user_tpl = Template.from_dict(json.loads((hand_cap / "hand" / "template.json").read_text()))
        ev_prop, match = evaluate_proposed_template(prop_cap, truth, user_tpl.dot_ids)
        ptpl = s.template()
        n_true = len(user_tpl.dot_ids)
        tedits = {"dots_proposed": int(len(ptpl.dot_ids)), "matched": len(match),
                  "phantoms_to_delete": int(len(ptpl.dot_ids) - len(match)),
                  "fiducials_to_add": int(n_true - len(match))}
        print(f"template edits to reach the user's fiducials: {json.dumps(tedits)}", flush=True)
        coarse_truth = {name: proposed_coarse_truth(ptpl, match, user_tpl, user.hand_state(name)["coarse"],
                                                    np.load(truth / "expressions" / f"{name}.npz")["template_vertices"])
                        for name in order}
    else:
        ev_prop = evaluate(prop_cap, truth)["per_expression"]
    for name in order:
        edits[name] = edits_needed(s, name, states[name], user.hand_state(name), args.tolerance_px,
                                   None if coarse_truth is None else coarse_truth[name],
                                   flags[name].get("coarse", {}))
    rows = []
    print()
    print("| expression | proposed from | registered (hand / proposed) | median px (hand / proposed) | "
          "p95 px (hand / proposed) | > 3 px off (hand / proposed) | edits needed (coarse, curves, marks) "
          "| flagged (of them wrong) |")
    print("|---|---|---|---|---|---|---|---|")
    for name in order:
        h, p, e = ev_hand[name], ev_prop[name], edits[name]
        rows.append({"expression": name, "source": sources[name], "hand": h, "proposed": p, "edits": e})
        print(f"| {name} | {sources[name]} | {100 * h['registered_fraction']:.1f}% / {100 * p['registered_fraction']:.1f}% "
              f"| {h['median_px']:.2f} / {p['median_px']:.2f} | {h['p95_px']:.2f} / {p['p95_px']:.2f} "
              f"| {100 * h['misregistered_fraction']:.1f}% / {100 * p['misregistered_fraction']:.1f}% "
              f"| {e['total']} ({e['coarse_missing'] + e['coarse_off']}, {e['curves_missing'] + e['curves_off']}, "
              f"{e['marks_missing'] + e['marks_off']}) | {e['flagged']} ({e['flagged_and_wrong']}) |")
    print(f"\nregistration time: hand {t_hand:.0f} s, proposals + registration {t_prop:.0f} s; "
          f"truth files opened by the proposal chain: {len(truth_opened)}")
    if tnote:
        print(f"template: {tnote}")
    if args.json:
        args.json.write_text(json.dumps({"rows": rows, "time_s": {"hand": t_hand, "proposed": t_prop},
                                         "tolerance_px": args.tolerance_px, "template_note": tnote},
                                        indent=1, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
