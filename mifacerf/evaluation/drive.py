"""The model driven by a track against path-traced ground truth (``mifacerf evaluate drive OUT TRACK --model MODEL``).

:func:`evaluate_drive` runs :func:`mifacerf.tracking.drive.drive` with a :class:`TruthComparison`
observer: every driven frame is also path-traced from the performance's true parameters under the
same environment and camera (:class:`mifacerf.synthetic.truth_scene.TruthRenderer`, seed 0), and
``drive.json`` gains, per environment:

* ``psnr_db`` per frame and ``psnr_summary`` (mean, min, median) over the face — pixels fully on
  modelled parts of the posed truth (template skin, eyes, teeth; :mod:`.masks`) and fully covered by
  both images;
* ``truth_noise_psnr_db``: a second path-traced render of the first frame (seed 1) against the first,
  + 3 dB = one render against the noise-free expectation (the PSNR ceiling);
* ``truth_pixel_coherence`` (the render's coherence measures on the truth), ``truth_spp``,
  ``truth_seconds_per_frame``;

and in ``weights``: ``truth_coherence`` (the weight coherence of the true meshes' §5 weights) and
``vs_truth_mean_tv`` (mean total-variation distance between the rendered and the true weights).
Files: ``DRIVE/<env>/truth/F<frame:05d>.exr`` (the truth, RGBA half float; a resumed run reads them
back) and ``strip.png`` with the truth's row above the render's.
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from ..tracking.coherence import PixelCoherence, weight_summary
from ..tracking.drive import FrameObserver
from .metrics import psnr


def face_pixels(truth_renderer, env, camera, truth_rgba: np.ndarray, render_rgba: np.ndarray) -> np.ndarray:
    """The pixels the rendering measurement compares: fully on modelled parts of the posed truth
    (template skin, eyes, teeth) and fully covered by the render."""
    from .masks import classify_pixels, face_mask

    classes = classify_pixels(truth_renderer.scene(env), camera, spp=4)
    return face_mask(classes) & (truth_rgba[..., 3] > 0.999) & (render_rgba[..., 3] > 0.999)


class TruthComparison(FrameObserver):
    """The :class:`~mifacerf.tracking.drive.FrameObserver` that compares every driven frame with its
    path-traced truth (module docstring); ``truth`` a ``mifacerf synth`` output folder."""

    def __init__(self, truth, truth_spp: int = 64):
        self.truth, self.spp = truth, truth_spp

    def weights(self, face, frames, W):
        from ..synthetic.truth_scene import TruthRenderer
        from ..synthetic.recording import read_truth

        # the truth's scene is built here, after the model's weights, as drive did before the observer
        self.renderer = TruthRenderer.from_synth(self.truth)
        recorded = read_truth(self.truth)
        self.params, self.template_vertices = recorded["params"], recorded["template_vertices"]
        Wt = np.stack([face.target(mesh=self.template_vertices[f])[1] for f in frames])
        return {"truth_coherence": weight_summary(Wt),
                "vs_truth_mean_tv": round(float((0.5 * np.abs(W - Wt).sum(-1)).mean()), 5)}

    def begin(self, name, env, camera, folder):
        self.name, self.env, self.camera, self.folder = name, env, camera, Path(folder)
        self.coherence = PixelCoherence()
        self.scores, self.seconds, self.strip, self.first = [], [], [], None

    def _pose(self, f):
        self.renderer.scene(self.env).set_pose(self.renderer.subject.pose(self.params[f], textures=False))

    def frame(self, f, rgba, plate, picked):
        from ..imageio import read_exr, write_exr
        from ..rendering.api import composite

        self.first = f if self.first is None else self.first
        path = self.folder / "truth" / f"F{f:05d}.exr"
        t0 = time.perf_counter()
        if path.exists():   # a resumed run: the truth is already path-traced
            gt = read_exr(path, channels=4)
            self._pose(f)
        else:
            path.parent.mkdir(parents=True, exist_ok=True)
            gt = self.renderer.render(self.params[f], self.camera, self.env, spp=self.spp, seed=0)
            write_exr(path, gt)
        self.seconds.append(time.perf_counter() - t0)
        self.coherence.add(gt)
        m = face_pixels(self.renderer, self.env, self.camera, gt, rgba)
        self.scores.append(psnr(rgba, gt, m) if m.any() else float("nan"))
        if picked:
            self.strip.append(composite(gt, plate))
        return f"PSNR {self.scores[-1]:.1f} dB"

    def end(self):
        from ..imageio import read_exr

        if not self.scores:
            return {}, [], ""
        f0 = self.first
        gt2 = self.renderer.render(self.params[f0], self.camera, self.env, spp=self.spp, seed=1)
        gt1 = read_exr(self.folder / "truth" / f"F{f0:05d}.exr", channels=4)
        self._pose(f0)
        m = face_pixels(self.renderer, self.env, self.camera, gt1, gt1)
        s = np.asarray(self.scores)
        e = {"truth_noise_psnr_db": round(float(psnr(gt2, gt1, m) + 10 * np.log10(2)), 3) if m.any() else None,
             "psnr_db": [round(float(x), 3) for x in s],
             "psnr_summary": {"mean": round(float(np.nanmean(s)), 3), "min": round(float(np.nanmin(s)), 3),
                              "median": round(float(np.nanmedian(s)), 3)},
             "truth_pixel_coherence": self.coherence.summary(), "truth_spp": self.spp,
             "truth_seconds_per_frame": round(float(np.mean(self.seconds)), 3)}
        note = f", PSNR mean {e['psnr_summary']['mean']:.2f} dB (min {e['psnr_summary']['min']:.2f})"
        return e, [(f"truth {self.name}", self.strip)], note


def evaluate_drive(track, model, truth, out=None, truth_spp: int = 64, **options) -> Path:
    """:func:`mifacerf.tracking.drive.drive` (``options`` are its keywords) with every frame compared to its
    path-traced truth; ``truth`` a ``mifacerf synth`` output folder. Returns the drive folder."""
    from ..tracking.drive import drive

    return drive(track, model, out, observer=TruthComparison(truth, truth_spp), **options)
