"""Evaluation of a registration against the synthetic subject's ground truth (never used by registration).

``evaluate(capture, truth, registration)`` compares, per expression:

* **fiducials** — the fraction registered (status 1), of all and of those the truth shows in at
  least two views (in the frame, unoccluded by the template mesh, cosine to the view > 0.2), and
  the median / 95th-percentile 3-D error of the registered ones, in metres and in *pixel
  footprints* (the error divided by the size of one pixel at the dot's depth, averaged over the
  cameras that see it); ``misregistered_fraction``: registered dots more than 3 px from the truth;
  ``registered_of_imaged``: of the dots that actually *show* in at least two views (seen as above
  and with a dot strength ≥ 0.25 within a pixel of the true projection — hair, ears and lids hide
  some dots the template mesh does not know of); ``single_view_dots`` and their median error
  (px): those registered from one view, their depth from the estimate;
* **residual dot visibility** — the mean dot-filter response (dot-strength units: 1 = a
  typical dot) at the true dot positions visible in each view, in the diffuse proxy of the
  captured images (*before*) and of the dot-free images (*after*, the registration's patches
  applied);
* **lips and eyelids** — the 3-D error of the margin vertices; **head pose** — rotation
  (degrees) and translation errors; **teeth** — error of the lower teeth's marked point and of
  their rotation (degrees);
  **eyes** — eye-centre error (where the truth has eye transforms).

``mifacerf evaluate registration OUT [--registration DIR] [--json FILE]`` prints the table
(``OUT`` a ``mifacerf synth`` output folder with ``capture/`` and ``truth/``).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..formats.capture import Capture
from ..formats.registration import Registration
from ..registration.dots import DotFilter, peak_near
from ..geometry.rigid import rotation_angle_deg
from ..registration.hand import Template
from ..registration.proxies import cone_weights, proxies_for
from ..geometry.visibility import Visibility
from ..stats import median_p95


def _stats(x):
    """(median, p95) of the finite values, unrounded; (None, None) when none is finite."""
    s = median_p95(x, digits=None)
    return s["median"], s["p95"]


def footprints(cams, X, visible) -> np.ndarray:
    """(N,) metres per pixel at each point's depth, averaged over the cameras in ``visible`` (C, N)."""
    fp = np.stack([cam.world_to_camera(X)[:, 2] / np.sqrt(cam.K[0, 0] * cam.K[1, 1]) for cam in cams])
    w = visible.astype(float)
    w[:, w.sum(0) == 0] = 1.0
    return (fp * w).sum(0) / w.sum(0)


def dotfree_diffuse(reg: Registration, cap: Capture, name: str, cam, diffuse: np.ndarray, cone_deg: float):
    """The diffuse proxy of the dot-free field: the patched pixels replaced by their proxy values."""
    patch = reg.dotfree_patch(name, cam.name)
    out = diffuse.copy()
    if patch is None:
        return out
    pixels, values = patch
    w = cone_weights(cap.rig.lights, cam, cone_deg).astype(np.float32)
    out[pixels[:, 0], pixels[:, 1]] = np.tensordot(w, values.astype(np.float32), axes=(0, 0))
    return out


def evaluate(capture, truth, registration=None, expressions=None, dots_residual: bool = True) -> dict:
    """Per-expression metrics (see the module docstring) and their summary."""
    cap = capture if isinstance(capture, Capture) else Capture(capture)
    reg = Registration(registration or cap.root / "registration", capture=cap)
    tpl = Template.from_dict(reg.template)
    truth = Path(truth)
    cams = cap.rig.cameras
    dots = tpl.dot_ids
    vis = Visibility(tpl.triangles, tpl.n_vertices, tol=5e-4)
    filt = DotFilter.from_dict(reg.meta["dot_filter"]) if "dot_filter" in reg.meta else None
    cone = float(reg.meta.get("options", {}).get("cone_deg", 60.0))
    rows = {}
    neutral_truth = None
    for name in expressions or reg.expression_names:
        r = reg.expression(name)
        z = np.load(truth / "expressions" / f"{name}.npz")
        T = np.asarray(z["template_vertices"], np.float64)
        if neutral_truth is None:
            nz = np.load(truth / "expressions" / f"{reg.expression_names[0]}.npz")
            neutral_truth = np.asarray(nz["template_vertices"], np.float64)
        tvis = vis(T, cams, min_cos=0.2)
        err = np.linalg.norm(r.vertices - T, axis=1)
        fp = footprints(cams, T, tvis)
        ok = r.status[dots] == 1
        e_m, e_px = err[dots][ok], (err / fp)[dots][ok]
        row = {"registered_fraction": float(ok.mean()), "n_dots": int(len(dots)),
               "median_m": _stats(e_m)[0], "p95_m": _stats(e_m)[1],
               "median_px": _stats(e_px)[0], "p95_px": _stats(e_px)[1],
               "max_px": float(e_px.max()) if e_px.size else None,
               "unregistered_median_px": _stats((err / fp)[dots][~ok])[0],
               "seen_by_2plus_views": float((tvis[:, dots].sum(0) >= 2).mean()),
               "misregistered_fraction": float((e_px > 3.0).mean()) if e_px.size else 0.0}
        sv = np.asarray(reg.report(name).get("single_view_dots", []), np.int64)
        row["single_view_dots"] = int(len(sv))   # registered from one view (depth from the estimate)
        row["single_view_median_px"] = _stats((err / fp)[sv])[0] if len(sv) else None
        seen = tvis[:, dots].sum(0) >= 2
        row["registered_of_seen"] = float((ok & seen).sum() / max(seen.sum(), 1))
        if filt is not None:
            # "imaged": the true dot shows in the view as a dot (strength ≥ 0.25 within a pixel of its
            # true projection); hair, ears or eyelids hide some dots the template mesh cannot know of
            imaged = np.zeros((len(cams), len(dots)), bool)
            for c, cam in enumerate(cams):
                d0 = proxies_for(cap, name, cam.name, cone_deg=cone).diffuse
                _, val = peak_near(filt.strength(d0, cam.name), cam.project(T[dots])[0], 1.0)
                imaged[c] = tvis[c, dots] & (val >= 0.25)
            im2 = imaged.sum(0) >= 2
            row["imaged_2plus_views"] = float(im2.mean())
            row["registered_of_imaged"] = float((ok & im2).sum() / max(im2.sum(), 1))
        margins = tpl.margin_ids()
        if margins.size:
            row["margins_median_px"], row["margins_p95_px"] = _stats((err / fp)[margins])
        # head pose against the truth head transform (neutral -> expression)
        if "part_teeth_upper" in z.files:
            Th = z["part_teeth_upper"]
            dR = r.head_pose[:3, :3].T @ Th[:3, :3]
            row["head_rotation_deg"] = rotation_angle_deg(dR)
            c = T[tpl.dot_ids].mean(0)
            row["head_translation_m"] = float(np.linalg.norm(
                (r.head_pose[:3, :3] @ c + r.head_pose[:3, 3]) - (Th[:3, :3] @ c + Th[:3, 3])))
        if "part_teeth_lower" in z.files and tpl.lower_teeth_point is not None and np.isfinite(r.teeth).all():
            from ..geometry.rigid import apply

            p_rest = tpl.lower_teeth_point  # the user's template strip: compare the transforms on it
            Tl = z["part_teeth_lower"]
            row["lower_teeth_m"] = float(np.linalg.norm(apply(r.teeth[1], p_rest[None])[0]
                                                        - apply(Tl, p_rest[None])[0]))
            row["lower_teeth_rotation_deg"] = rotation_angle_deg(r.teeth[1][:3, :3].T @ Tl[:3, :3])
        if "part_eye_left" in z.files and np.isfinite(r.eye_centres).all():
            from ..synthetic import head as H

            ce = []
            for i, (part, sgn) in enumerate((("part_eye_left", 1.0), ("part_eye_right", -1.0))):
                Te = z[part]
                c_rest = H.EYE_CENTRE * np.array([sgn, 1, 1])
                ce.append(np.linalg.norm(r.eye_centres[i] - (Te[:3, :3] @ c_rest + Te[:3, 3])))
            row["eye_centre_m"] = float(np.max(ce))
        if dots_residual and filt is not None:
            before, after = [], []
            for c, cam in enumerate(cams):
                ids = dots[tvis[c, dots]]
                if ids.size == 0:
                    continue
                uv, _ = cam.project(T[ids])
                d0 = proxies_for(cap, name, cam.name, cone_deg=cone).diffuse
                d1 = dotfree_diffuse(reg, cap, name, cam, d0, cone)
                s = filt.scales.get(cam.name, 1.0)
                before.append(peak_near(np.maximum(filt.response(d0), 0) / s, uv, 1.0)[1])
                after.append(peak_near(np.maximum(filt.response(d1), 0) / s, uv, 1.0)[1])
            if before:
                row["dot_response_before"] = float(np.mean(np.concatenate(before)))
                row["dot_response_after"] = float(np.mean(np.concatenate(after)))
        rows[name] = row
    frac = [r["registered_fraction"] for r in rows.values()]
    summary = {
        "expressions": len(rows),
        "min_registered_of_seen": float(np.min([r["registered_of_seen"] for r in rows.values()])) if rows else None,
        "min_registered_of_imaged": float(np.min([r.get("registered_of_imaged", np.nan) for r in rows.values()]))
        if rows else None,
        "mean_registered_of_imaged": float(np.mean([r.get("registered_of_imaged", np.nan) for r in rows.values()]))
        if rows else None,
        "mean_registered_of_seen": float(np.mean([r["registered_of_seen"] for r in rows.values()])) if rows else None,
        "max_misregistered_fraction": float(np.max([r["misregistered_fraction"] for r in rows.values()]))
        if rows else None,
        "min_registered_fraction": float(np.min(frac)) if frac else None,
        "mean_registered_fraction": float(np.mean(frac)) if frac else None,
        "worst_median_px": max((r["median_px"] or 0) for r in rows.values()) if rows else None,
        "worst_p95_px": max((r["p95_px"] or 0) for r in rows.values()) if rows else None,
    }
    if rows and all("dot_response_before" in r for r in rows.values()):
        summary["dot_response_before"] = float(np.mean([r["dot_response_before"] for r in rows.values()]))
        summary["dot_response_after"] = float(np.mean([r["dot_response_after"] for r in rows.values()]))
    return {"per_expression": rows, "summary": summary}


def format_table(result: dict) -> str:
    """A Markdown table of :func:`evaluate`'s result."""
    head = ("| expression | registered: of all / of seen by ≥ 2 views / of imaged in ≥ 2 views | median err (mm / px) "
            "| p95 err (mm / px) | dot response before → after | lips/lids median px | head rot (deg) |")
    lines = [head, "|" + "---|" * 7]

    def f(x, k=2):
        return "–" if x is None else f"{x:.{k}f}"

    for name, r in result["per_expression"].items():
        lines.append(f"| {name} | {100 * r['registered_fraction']:.1f}% / {100 * r['registered_of_seen']:.1f}% / "
                     f"{100 * r.get('registered_of_imaged', np.nan):.1f}% | "
                     f"{f(r['median_m'] and r['median_m'] * 1e3)} / "
                     f"{f(r['median_px'])} | {f(r['p95_m'] and r['p95_m'] * 1e3)} / {f(r['p95_px'])} | "
                     f"{f(r.get('dot_response_before'), 3)} → {f(r.get('dot_response_after'), 3)} | "
                     f"{f(r.get('margins_median_px'))} | {f(r.get('head_rotation_deg'))} |")
    s = result["summary"]
    lines.append("")
    lines.append(f"min registered {100 * (s['min_registered_fraction'] or 0):.1f}% of all, "
                 f"{100 * (s['min_registered_of_seen'] or 0):.1f}% of those seen by ≥ 2 views (mean "
                 f"{100 * (s['mean_registered_of_seen'] or 0):.1f}%), {100 * (s['min_registered_of_imaged'] or 0):.1f}% "
                 f"of those imaged in ≥ 2 views (mean {100 * (s['mean_registered_of_imaged'] or 0):.1f}%); "
                 f"worst median {f(s['worst_median_px'])} px, "
                 f"worst p95 {f(s['worst_p95_px'])} px; dot response {f(s.get('dot_response_before'), 3)} → "
                 f"{f(s.get('dot_response_after'), 3)}")
    return "\n".join(lines)


def pictures(capture, truth, registration, folder, expression: str, crop: int | None = None) -> list[Path]:
    """PNGs for people, per camera of ``expression``: the two proxies, the dot-strength map, the true
    (green circles) and registered (red crosses; magenta = not registered) fiducials over the diffuse
    proxy, and the dot removal (before / after, one light). Returns the files written."""
    import cv2

    from ..imageio import write_png
    from ..pictures import grid, label, tile8

    cap = capture if isinstance(capture, Capture) else Capture(capture)
    reg = Registration(registration or cap.root / "registration", capture=cap)
    tpl = Template.from_dict(reg.template)
    filt = DotFilter.from_dict(reg.meta["dot_filter"])
    cone = float(reg.meta.get("options", {}).get("cone_deg", 60.0))
    r = reg.expression(expression)
    T = np.load(Path(truth) / "expressions" / f"{expression}.npz")["template_vertices"] if truth else None
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    written = []
    for c, cam in enumerate(cap.rig.cameras):
        p = proxies_for(cap, expression, cam.name, cone_deg=cone)
        s = filt.strength(p.diffuse, cam.name)
        scale = max(1, int(round(512 / cam.height)))
        ex = 1.0 / max(float(np.percentile(p.diffuse, 99.5)), 1e-12)

        def big(img8):
            return cv2.resize(img8, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)

        def at(uv):
            return int(round((uv[0] + 0.5) * scale - 0.5)), int(round((uv[1] + 0.5) * scale - 0.5))

        overlay = big(tile8(p.diffuse, ex))
        ids = tpl.dot_ids[r.visible[c, tpl.dot_ids]]
        if T is not None:
            for uv in cam.project(T[ids])[0]:
                cv2.circle(overlay, at(uv), max(2, scale), (0, 255, 0), 1, cv2.LINE_AA)
        for i, uv in zip(ids, cam.project(r.vertices[ids])[0]):
            cv2.drawMarker(overlay, at(uv), (255, 0, 0) if r.status[i] == 1 else (255, 0, 255),
                           cv2.MARKER_CROSS, max(3, scale + 1), 1)
        f0 = cap.field(expression, cam.name, lights=[0])[0]
        f1 = reg.field(expression, cam.name, lights=[0])[0]
        e1 = 1.0 / max(float(np.percentile(f0, 99.5)), 1e-12)
        tiles = [label(big(tile8(p.diffuse, ex)), f"{cam.name} diffuse - cone"),
                 label(big(tile8(p.p95, 1.0 / max(float(np.percentile(p.p95, 99.5)), 1e-12))), "95th percentile"),
                 label(big(tile8(np.clip(s / 1.5, 0, 1)[..., None].repeat(3, -1) ** 2.2)), "dot strength"),
                 label(overlay, "truth (green) / registered (red)"),
                 label(big(tile8(f0, e1)), "light 0: captured"), label(big(tile8(f1, e1)), "light 0: dots removed")]
        if crop:
            h0 = (tiles[0].shape[0] - crop) // 2
            tiles = [t[h0:h0 + crop, h0:h0 + crop] for t in tiles]
        path = folder / f"{expression}_{cam.name}.png"
        write_png(path, grid(tiles, 3))
        written.append(path)
    return written
