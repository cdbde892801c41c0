"""facerf_bsdf under Mitsuba's other emitters: a closed-form check (directional) and consistency (point, spot)."""
import numpy as np
import pytest


@pytest.mark.slow
def test_directional_light_along_a_stage_light_reproduces_that_lights_field(toy_model, mi):
    """A directional emitter exactly along light-stage light l, irradiance 1, through the material and `direct`
    = the model's own relighting with light l alone (the facerf integrator under an environment non-zero
    only on l's cell, integral 1). Measured at 32², 16 spp: 34.7-38.0 dB, mean ratio 0.985-1.013 over the
    five most frontal lights (the residual is the material's per-hit view/texel interpolation)."""
    from mifacerf.evaluation.material import directional_oracle

    rows = directional_oracle(toy_model.root, size=24, spp=8)
    assert len(rows) == 5
    for r in rows:
        assert r["psnr"] > 30 and abs(r["brightness"] - 1) < 0.03, rows


@pytest.mark.slow
def test_point_and_spot_lights_far_along_a_direction_match_the_directional_light(toy_model, mi):
    """A point light (and a wide spot) at distance d along a direction, intensity d² (irradiance 1 at the
    face), renders as the directional emitter of irradiance 1 along it, to the 1/d² falloff across the face."""
    from mifacerf.camera import Camera
    from mifacerf.rendering.sensors import sensor_dict
    from mifacerf.variant import ensure_plugins

    ensure_plugins()
    cam = Camera.look_at("t", [0.12, 0.1, 1.0], [0, 0, 0], width=24, height=24, focal=96.0)
    w = np.array([0.3, 0.4, 1.0])
    w /= np.linalg.norm(w)
    d = 20.0
    pos = (w * d).tolist()
    emitters = {"directional": {"type": "directional", "direction": (-w).tolist(), "irradiance": 1.0},
                "point": {"type": "point", "position": pos, "intensity": d * d},
                "spot": {"type": "spot", "intensity": d * d, "cutoff_angle": 20.0, "beam_width": 15.0,
                         "to_world": mi.ScalarTransform4f().look_at(origin=pos, target=[0, 0, 0], up=[0, 1, 0])}}
    img = {}
    for name, em in emitters.items():
        scene = mi.load_dict({"type": "scene", "integrator": {"type": "direct"}, "sensor": sensor_dict(cam, spp=8),
                              "light": em, "face": {"type": "facerf_face", "model": str(toy_model.root),
                                                    "bsdf": {"type": "facerf_bsdf"}}})
        img[name] = np.asarray(mi.render(scene, seed=0))
    mask = img["directional"][..., 3] > 0.999
    ref = img["directional"][..., :3][mask].mean()
    assert ref > 0
    for name in ("point", "spot"):
        assert abs(img[name][..., :3][mask].mean() / ref - 1) < 0.02, name


@pytest.mark.slow
def test_regions_splits_the_error_by_pixel_class(toy_model, mi):
    """evaluation.material.regions: per pixel class (the toy has skin, no parts) its pixels, its share of the
    squared error and the brightness; the material without shadow rays ('unshadowed') renders the face too."""
    from mifacerf.evaluation.material import regions

    for integ in ("direct", "unshadowed"):
        out = regions(toy_model.root, env="sky", size=16, spp=4, integrator=integ)
        by = {r["class"]: r for r in out["rows"]}
        assert "skin" in by and by["skin"]["pixels"] > 20
        assert 0 < by["skin"]["error_share"] <= 1.0001
        assert 0 < out["worst_1pc"] <= out["worst_5pc"] <= 1
        assert 0.5 < out["brightness"] < 1.5, out


def test_integrator_options_on_the_command_line(capsys):
    """``NAME:key=value,...`` of ``--integrators``: booleans, integers, floats and strings; a bare key is one
    argparse error naming the option, no traceback."""
    import pytest

    from mifacerf.evaluation import material as M

    assert M._integrator_options("direct") == ("direct", {})
    assert M._integrator_options("facerf_direct:part_rays=false,emitter_samples=4,x=0.5,y=z") == (
        "facerf_direct", {"part_rays": False, "emitter_samples": 4, "x": 0.5, "y": "z"})
    with pytest.raises(SystemExit):
        M.main(["no-model", "--regions", "--integrators", "facerf_direct:part_rays"])
    err = capsys.readouterr().err
    assert "--integrators: integrator option 'part_rays': expected key=value" in err and "Traceback" not in err


def test_a_malformed_eye_is_one_line_naming_the_option(capsys):
    """``--eye`` takes three finite numbers away from the origin; anything else is one argparse error naming
    the option, before any model is opened (the model path here does not exist)."""
    import pytest

    from mifacerf.evaluation import material as M

    for bad in ("1,2", "a,b,c", "0,0,0", "nan,0,1"):
        with pytest.raises(SystemExit):
            M.main(["no-model", "--eye", bad])
        err = capsys.readouterr().err
        assert f"--eye: expected three finite numbers X,Y,Z away from the origin, got {bad!r}" in err, err
        assert "Traceback" not in err


def test_visibility_emitter_with_a_mode_that_has_no_envmap_is_one_line(capsys):
    """``--visibility-emitter`` references the comparison's envmap; with a mode whose scenes hold none by that
    name it is one argparse error naming both options, before any model is opened."""
    import pytest

    from mifacerf.evaluation import material as M

    for mode in (["--hat", "synth"], ["--emitters"], ["--directional"]):
        with pytest.raises(SystemExit):
            M.main(["no-model", "--visibility-emitter", *mode])
        err = capsys.readouterr().err
        assert f"--visibility-emitter: only with the comparison or --regions, not with {mode[0]}" in err, err
        assert "Traceback" not in err
