"""Performance capture (paper §6.4, §7): record, track and drive the model with a multi-view performance.

Modules: :mod:`.performance` (the scripted trajectory of the synthetic subject), :mod:`.folder`
(the performance folder format), :mod:`.record` (rendering the multi-view video),
:mod:`.track2d` (dots followed in every camera), :mod:`.track3d` (triangulation, head pose, the
per-frame mesh), :mod:`.keyframes` (eyes and lips from hand-marked keyframes), :mod:`.drive`
(per-frame §5 weights, relit renders, composite, video), :mod:`.coherence` (temporal stability),
:mod:`.evaluate` (against the synthetic truth), :mod:`.cli`. Documentation: ``docs/tracking.md``.
"""
