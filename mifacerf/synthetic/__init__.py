"""The synthetic subject: a procedural, deformable head photographed by a simulated light stage.

Work in progress; see :mod:`.head` (geometry), :mod:`.expressions` (controls and deformation) and
:mod:`.parts` (eyes, teeth, mouth interior).
"""
