"""Performance capture (paper §6.4, §7): record, track and drive the model with a multi-view performance.

Modules: :mod:`.folder` (the performance folder format), :mod:`.track2d` (dots followed in every
camera), :mod:`.track3d` (triangulation, head pose, the
per-frame mesh), :mod:`.keyframes` (eyes and lips from hand-marked keyframes), :mod:`.drive`
(per-frame §5 weights, relit renders, composite, video), :mod:`.coherence` (temporal stability),
:mod:`.overlay` (a picture of a tracked frame), :mod:`.cli`. Documentation: ``docs/tracking.md``.
The synthetic performance it is tested on (the scripted trajectory and the recorded video) is
:mod:`mifacerf.synthetic.performance` and :mod:`mifacerf.synthetic.recording`.
The comparisons with the synthetic truth are :mod:`mifacerf.evaluation.tracking` and
:mod:`mifacerf.evaluation.drive`.
"""
