"""The synthetic subject (:mod:`mifacerf.synthetic`) as a renderer for the synthetic cameras.

Implements the renderer interface of :mod:`.procedural`::

    render(expression_params, camera, lights) -> (len(lights), H, W, 3)

with the synthetic subject posed by ``expression_params`` (its parameter vector), its
Mitsuba scene (:class:`mifacerf.synthetic.SubjectScene`) and the batched OLAT renderer
(:func:`mifacerf.synthetic.olat.render_olat`): radiance per unit irradiance, linear sRGB.
The subject's own captured-expression list (:meth:`~mifacerf.synthetic.Subject.presets`)
names the session's expressions (:func:`subject_expressions`).
"""
from __future__ import annotations

import numpy as np

from ...camera import Camera
from ...formats.capture import ExpressionEntry
from ...rig import Rig


def _subject():
    from mifacerf.synthetic import default_subject

    return default_subject()


def subject_expressions(n: int | None = None, subject=None) -> list[ExpressionEntry]:
    """The first ``n`` of the synthetic subject's 60 expressions (names and categories)."""
    subject = subject or _subject()
    exprs = subject.presets("paper")
    if n is not None:
        if not 1 <= n <= len(exprs):
            raise ValueError(f"between 1 and {len(exprs)} expressions, got {n}")
        exprs = exprs[:n]
    return [ExpressionEntry(e.name, e.category) for e in exprs]


class SyntheticSubjectRenderer:
    """Renders the default synthetic subject (or ``subject``) with ``spp`` samples per pixel."""

    def __init__(self, rig: Rig, subject=None, spp: int = 4, seed: int = 0):
        from mifacerf.synthetic import SubjectScene

        self.rig = rig
        self.subject = subject or _subject()
        self.scene = SubjectScene(self.subject)
        self.spp, self.seed = spp, seed
        self._posed: bytes | None = None
        self._by_name = {e.name: e for e in self.subject.presets("paper")}

    def expression_params(self, name: str, index: int) -> np.ndarray:
        """The subject's parameter vector for the expression ``name``."""
        try:
            return np.asarray(self._by_name[name].params, np.float64)
        except KeyError:
            raise KeyError(f"the synthetic subject has no expression {name!r}; its expressions are "
                           f"{', '.join(self._by_name)}") from None

    def render(self, params, camera: Camera, lights) -> np.ndarray:
        from mifacerf.synthetic.olat import render_olat

        params = np.asarray(params, np.float64)
        key = params.tobytes()
        if key != self._posed:
            self.scene.set_pose(self.subject.pose(params))
            self._posed = key
        lights = np.asarray(lights, np.int64).reshape(-1)
        return render_olat(self.scene.scene, camera, self.rig.lights.directions[lights], None, spp=self.spp,
                           seed=self.seed)
