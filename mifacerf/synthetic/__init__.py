"""The synthetic subject: a procedural, deformable head with exact ground truth.

::

    from mifacerf.synthetic import default_subject, Subject, Pose, SubjectScene, load_mesh_subject
    subj = default_subject()
    pose = subj.pose(subj.params(smile_L=1, jaw_open=0.2))
    scene = SubjectScene(subj)          # one Mitsuba scene, updated with scene.set_pose(pose)

Modules: :mod:`.head` (geometry), :mod:`.expressions` (controls and deformation),
:mod:`.parts` (eyes, teeth, mouth interior), :mod:`.textures` (atlas, albedo, roughness,
normal map, wrinkles), :mod:`.dots` (fiducials), :mod:`.template` (registration template),
:mod:`.presets` (captured expressions), :mod:`.subject` (the subject and its poses),
:mod:`.scene` (Mitsuba scene), :mod:`.mesh_subject` (a user's own blendshape meshes),
:mod:`.preview` (contact sheets of its expressions: ``mifacerf preview --preset draft``),
:mod:`.performance` (a scripted facial performance: the trajectory), :mod:`.recording` (its
multi-view video, truth and keyframe marks: ``mifacerf synth OUT --performance SECONDS``).
Expensive build steps are cached under ``$MIFACERF_CACHE`` (default ``~/.cache/mifacerf``).
"""
from .expressions import CONTROLS, Control
from .presets import Expression
from .scene import PART_IDS, SubjectScene
from .subject import Part, Pose, Subject, Textures, default_subject
from .template import Template


def load_mesh_subject(*args, **kwargs):
    """A subject from user meshes (see :func:`mifacerf.synthetic.mesh_subject.load_mesh_subject`)."""
    from .mesh_subject import load_mesh_subject as _load

    return _load(*args, **kwargs)


__all__ = ["default_subject", "Subject", "Pose", "Part", "Textures", "SubjectScene", "PART_IDS",
           "load_mesh_subject", "Control", "CONTROLS", "Expression", "Template"]
