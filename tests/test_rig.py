import numpy as np
import pytest

from mifacerf.rig import LightStage, Rig, preset, voronoi_solid_angles


def test_paper_stage_has_480_distinct_directions_tiling_the_sphere():
    ls = LightStage.semicircular_arm(16, 30)
    assert len(ls) == 480
    assert len(np.unique(np.round(ls.directions, 9), axis=0)) == 480
    np.testing.assert_allclose(ls.solid_angles.sum(), 4 * np.pi, rtol=1e-9)
    assert np.all(ls.solid_angles > 0)
    # index convention l = j * n_strobes + k, theta_k measured from +Y
    k, j = 3, 5
    l = j * 30 + k
    theta = (k + 0.5) * np.pi / 30
    phi = 2 * np.pi * j / 16
    np.testing.assert_allclose(ls.directions[l], [np.sin(theta) * np.sin(phi), np.cos(theta),
                                                  np.sin(theta) * np.cos(phi)], atol=1e-12)


def test_solid_angles_match_analytic_band_areas():
    """A full ring of arm positions: each strobe's cells together cover its latitude band."""
    n_pos, n_str = 64, 8
    ls = LightStage.semicircular_arm(n_pos, n_str)
    band = ls.solid_angles.reshape(n_pos, n_str).sum(axis=0)
    edges = np.arange(n_str + 1) * np.pi / n_str
    mid = (edges[:-1] + edges[1:]) / 2
    # Voronoi boundaries between rings lie half-way in angle → the band between mid-latitudes
    b = np.concatenate([[0], (mid[:-1] + mid[1:]) / 2, [np.pi]])
    analytic = 2 * np.pi * (np.cos(b[:-1]) - np.cos(b[1:]))
    np.testing.assert_allclose(band, analytic, rtol=0.02)


def test_degenerate_layouts_are_finite_and_documented():
    circle = np.stack([np.cos(np.linspace(0, 2 * np.pi, 7)[:-1]), np.zeros(6),
                       np.sin(np.linspace(0, 2 * np.pi, 7)[:-1])], axis=1)
    np.testing.assert_allclose(voronoi_solid_angles(circle), 4 * np.pi / 6)
    np.testing.assert_allclose(voronoi_solid_angles(np.eye(3)), 4 * np.pi / 3)
    with pytest.raises(ValueError, match="duplicates"):
        voronoi_solid_angles(np.array([[0, 1, 0], [0, 1, 0], [1, 0, 0], [0, 0, 1.0]]))


def test_rig_round_trip_and_presets():
    rig = preset("tiny").rig()
    assert len(rig.cameras) == 3 and len(rig.lights) == 48
    r2 = Rig.from_dict(rig.to_dict())
    np.testing.assert_array_equal(r2.lights.directions, rig.lights.directions)
    np.testing.assert_array_equal(r2.lights.irradiance, rig.lights.irradiance)
    assert [c.name for c in r2.cameras] == [c.name for c in rig.cameras]
    with pytest.raises(ValueError, match="unknown preset"):
        preset("huge")


def test_cameras_face_the_subject():
    for name in ("tiny", "draft"):
        for cam in preset(name).rig().cameras:
            uv, z = cam.project(np.array([[0.0, 0.0, 0.05]]))
            assert z[0] > 1.0
            assert 0.25 * cam.width < uv[0, 0] < 0.75 * cam.width
            assert 0.25 * cam.height < uv[0, 1] < 0.75 * cam.height
