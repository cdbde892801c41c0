"""Zhang's calibration of the draft rig's six cameras from ChArUco boards rendered by Mitsuba with
known intrinsics, distortion and poses."""
import json

import numpy as np
import pytest
from click.testing import CliRunner

from mifacerf.camera import Camera
from mifacerf.capture.calibration.charuco import BoardSpec, Detection, detect
from mifacerf.capture.calibration.zhang2000 import (CalibrationError, calibrate_rig, detect_views, pose_errors,
                                                    relative_pose_errors)
from mifacerf.capture.simulation.boards import read_board_dataset, write_board_dataset
from mifacerf.cli import main
from mifacerf.rig import preset

BOARD = BoardSpec(9, 7, 0.03, 0.022)


@pytest.fixture(scope="module")
def boards(tmp_path_factory):
    rig = preset("draft").rig()
    root = tmp_path_factory.mktemp("boards")
    write_board_dataset(root, rig.cameras, BOARD, n_views=20, spp=4, tilt_deg=55, seed=0)
    board, images, desc = read_board_dataset(root)
    truth = json.loads((root / "truth.json").read_text())
    return root, rig, images, desc, truth


@pytest.fixture(scope="module")
def calibration(boards):
    root, rig, images, desc, truth = boards
    det = detect_views(BOARD, images)
    world = desc["world_pose"]
    cal = calibrate_rig(BOARD, det, {c.name: (c.width, c.height) for c in rig.cameras},
                        principal_prior_px=0.01 * 256, world_view=0,
                        world_pose=(np.asarray(world["R"]), np.asarray(world["t"])))
    return cal, det


def test_charuco_adapter_on_the_printed_board():
    img = BOARD.image(px_per_square=40)
    d = detect(BOARD, img)
    assert d is not None and len(d) == BOARD.n_corners
    # corner (i, j) of the print lies on the pixel boundary i*40 -> pixel-centre coordinate i*40 - 0.5
    expected = d.object_points[:, :2] / BOARD.square * 40 - 0.5
    np.testing.assert_allclose(d.image_points, expected, atol=0.3)
    assert detect(BOARD, np.full((100, 100), 128, np.uint8)) is None


def test_rendered_boards_follow_the_camera_model(boards):
    """Corners detected in the Mitsuba renders sit where the true camera projects the true board."""
    root, rig, images, desc, truth = boards
    errs = []
    for cam in rig.cameras:
        for v, img in enumerate(images[cam.name]):
            d = detect(BOARD, img)
            if d is None:
                continue
            R, t = (np.asarray(truth["board_poses"][v][k]) for k in ("R", "t"))
            uv, _ = cam.project(d.object_points @ R.T + t)
            errs.append(np.linalg.norm(uv - d.image_points, axis=1))
    e = np.concatenate(errs)
    assert len(e) > 1000
    assert np.median(e) < 0.3 and np.mean(e < 1.0) > 0.9


def test_zhang_recovers_the_rendered_truth(boards, calibration):
    root, rig, *_ = boards
    cal, det = calibration
    assert all(len(det[c.name]) >= 10 for c in rig.cameras)  # every camera saw the board 10+ times
    assert cal.rms < 0.5
    for truth in rig.cameras:
        e = pose_errors(cal.camera(truth.name), truth)
        assert e["focal_rel"] < 0.015, (truth.name, e)
        assert e["principal_px"] < 3.0, (truth.name, e)
        assert e["rotation_deg"] < 0.2, (truth.name, e)
        assert e["centre_m"] < 0.02, (truth.name, e)
    rel = relative_pose_errors([cal.camera(c.name) for c in rig.cameras], rig.cameras)
    assert max(r["rotation_deg"] for r in rel) < 0.25 and max(r["centre_m"] for r in rel) < 0.025


def test_calibration_refuses_hopeless_input(boards):
    root, rig, images, *_ = boards
    det = detect_views(BOARD, {"cam0": images["cam0"][:2]})
    with pytest.raises(CalibrationError, match="needs >= 3"):
        calibrate_rig(BOARD, det, {"cam0": (256, 256)})
    # two cameras that never see the board at the same time cannot be related
    d0 = detect_views(BOARD, {"cam0": images["cam0"]})["cam0"]
    d1 = detect_views(BOARD, {"cam1": images["cam1"]})["cam1"]
    split = {"cam0": {v: d for v, d in d0.items() if v % 2 == 0},
             "cam1": {v + 100: d for v, d in d1.items()}}
    with pytest.raises(CalibrationError, match="share no board view"):
        calibrate_rig(BOARD, split, {"cam0": (256, 256), "cam1": (256, 256)})


def test_cli_geometry_reports_errors_and_applies_to_a_capture(boards, tmp_path):
    root, rig, *_ = boards
    from helpers.capture import new_session, run_lab, tiny_rig

    cap_rig = tiny_rig(2, 2, 2, 32)
    cap_rig.cameras = [c.resized(32, 32) for c in rig.cameras[:2]]  # the draft rig's first two cameras
    s = new_session(tmp_path / "cap", cap_rig, 1)
    run_lab(s)  # the calibration holds six cameras; the capture uses the first two
    r = CliRunner().invoke(main, ["calibrate", "geometry", str(root), "--truth", str(root / "truth.json"),
                                  "--out", str(tmp_path / "geometry.json"), "--apply", str(tmp_path / "cap")])
    assert r.exit_code == 0, r.output
    assert "err f=" in r.output and "rms reprojection error" in r.output
    result = json.loads((tmp_path / "geometry.json").read_text())
    assert len(result["errors"]["absolute"]) == 6
    manifest = json.loads((tmp_path / "cap" / "manifest.json").read_text())
    assert manifest["calibration"][-1]["geometry"]["method"] == "zhang2000"
    cam0 = Camera.from_dict(manifest["rig"]["cameras"][0])
    est = Camera.from_dict(result["cameras"][0]["camera"]).resized(32, 32)
    np.testing.assert_allclose(cam0.K, est.K)
    assert list((tmp_path / "cap").glob("manifest.*.json"))  # the previous manifest is kept


def test_detection_dataclass_shapes():
    d = Detection(np.arange(3), np.zeros((3, 2)), np.zeros((3, 3)))
    assert len(d) == 3
