"""Methods chosen by name (mifacerf.methods): every registry's dispatcher refuses an unknown name with a
message listing the choices, runs each of its methods, and the CLI options offer exactly its names."""
import numpy as np
import pytest

from mifacerf import environment as E
from mifacerf.capture import motion
from mifacerf.capture.calibration import radiometric
from mifacerf.methods import lookup
from mifacerf.registration import dot_removal as DR
from mifacerf.rendering import compression as C


def _choices(registry) -> str:
    return "choose one of " + ", ".join(registry)


def test_lookup_names_the_step_and_the_choices():
    assert lookup({"a": 1, "b": 2}, "b", "test") == 2
    for bad in ("c", None, ["a"]):
        with pytest.raises(ValueError, match=r"unknown test method .*; choose one of a, b$"):
            lookup({"a": 1, "b": 2}, bad, "test")


def test_registries_list_their_default_first():
    assert next(iter(C.COMPRESSION_METHODS)) == C.DEFAULT_COMPRESSION_METHOD == "exact"
    assert next(iter(E.LIGHT_BASIS_METHODS)) == E.DEFAULT_LIGHT_BASIS_METHOD == "voronoi"
    assert next(iter(DR.DOT_FILL_METHODS)) == DR.DEFAULT_DOT_FILL_METHOD == "texture"
    assert next(iter(motion.SHARPNESS_METHODS)) == motion.DEFAULT_SHARPNESS_METHOD == "laplacian"
    assert next(iter(radiometric.RESPONSE_METHODS)) == radiometric.DEFAULT_RESPONSE_METHOD == "grey_olat"


def test_unknown_names_are_refused_with_the_choices(tmp_path):
    with pytest.raises(ValueError, match="unknown compression method 'svd'; " + _choices(C.COMPRESSION_METHODS)):
        C.compression_method("svd")
    with pytest.raises(ValueError, match="unknown light basis method 'sh'; " + _choices(E.LIGHT_BASIS_METHODS)):
        E.light_shares(np.eye(3), np.eye(3), method="sh")
    with pytest.raises(ValueError, match="unknown dot fill method 'blur'; " + _choices(DR.DOT_FILL_METHODS)):
        DR.fill_dots(DR.Inpainter(np.zeros((4, 4), bool)), np.zeros((1, 4, 4, 3)), method="blur")
    with pytest.raises(ValueError, match="unknown sharpness method 'fft'; " + _choices(motion.SHARPNESS_METHODS)):
        motion.take_score(np.zeros((1, 4, 4, 3)), method="fft")
    with pytest.raises(ValueError, match="unknown sharpness method 'fft'"):
        motion.MotionCheck(method="fft")
    with pytest.raises(ValueError, match="unknown response method 'x'; " + _choices(radiometric.RESPONSE_METHODS)):
        radiometric.response_data(tmp_path, {}, "cam0", method="x")
    from mifacerf.registration.register import Options

    with pytest.raises(ValueError, match="unknown dot fill method 'blur'"):
        Options(dot_fill="blur")
    with pytest.raises(ValueError, match="nothing to compress"):
        C.compress_model(None, 8, method="exact")


def test_cli_options_offer_the_registry_names():
    from mifacerf.capture.cli import response_cmd
    from mifacerf.registration.cli import register_cmd
    from mifacerf.rendering.cli import compress_cmd

    def choices(cmd, name):
        return list(next(p for p in cmd.params if p.name == name).type.choices)

    assert choices(register_cmd, "dot_fill") == list(DR.DOT_FILL_METHODS)
    assert choices(compress_cmd, "method") == [n for n, m in C.COMPRESSION_METHODS.items() if m.compress]
    assert choices(response_cmd, "method") == list(radiometric.RESPONSE_METHODS)


def test_each_light_basis_rule_through_its_dispatcher(rng):
    from mifacerf.rig import LightStage

    ls = LightStage.semicircular_arm(6, 5)
    q = rng.normal(size=(300, 3))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    for method in E.LIGHT_BASIS_METHODS:
        lights, shares = E.light_shares(q, ls.directions, method)
        assert lights.shape == shares.shape and lights.shape[0] == len(q)
        assert lights.min() >= 0 and lights.max() < len(ls)
        np.testing.assert_allclose(shares.sum(axis=1), 1.0, atol=1e-12)


def test_each_sharpness_measure_through_its_dispatcher(rng):
    frames = rng.random((3, 16, 16, 3))
    for method in motion.SHARPNESS_METHODS:
        assert np.isfinite(motion.take_score(frames, method))
