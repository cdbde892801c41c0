"""Helpers of the render evaluation (mifacerf.evaluation.render_cases) that need no model."""
import numpy as np
import pytest


def _rig():
    from mifacerf.camera import Camera

    cams = []
    for yaw in (-40, 0, 40):
        for pitch in (10, -10):
            y, p = np.radians(yaw), np.radians(pitch)
            eye = 1.2 * np.array([np.sin(y) * np.cos(p), np.sin(p), np.cos(y) * np.cos(p)])
            cams.append(Camera.look_at(f"y{yaw}p{pitch}", eye, [0, 0, 0], width=64, height=64, focal=200.0))
    return cams


@pytest.mark.parametrize("degrees, side", [(30.0, 1.0), (30.0, -1.0), (12.5, 1.0)])
def test_camera_off_the_rig_is_the_asked_angle_from_the_nearest_camera(degrees, side):
    from mifacerf.evaluation.render_cases import camera_off_the_rig, view_angle

    cams = _rig()
    cam = camera_off_the_rig(cams, degrees, side)
    assert view_angle(cam, cams, np.zeros(3)) == pytest.approx(degrees, abs=1e-6)
    assert np.sign(cam.centre[0]) == side and abs(np.degrees(np.arctan2(cam.centre[0], cam.centre[2]))) > 40
    assert np.linalg.norm(cam.centre) == pytest.approx(1.2)
