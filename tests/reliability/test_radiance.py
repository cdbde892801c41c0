"""Issue 15 defect 5: negative or non-finite radiance in a capture is refused by registration and build,
with an error naming the image file, expression, camera and light; tiny negatives (noise) are accepted."""
import shutil

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mifacerf.errors import MifacerfError
from mifacerf.validation import NEGATIVE_TOLERANCE, RadianceError, check_field


def _field():
    rng = np.random.default_rng(0)
    return rng.uniform(0, 0.6, (4, 8, 8, 3)).astype(np.float32)


def test_noise_is_accepted_and_a_negative_patch_is_not():
    f = _field()
    f[1, 0, 0] = -0.5 * NEGATIVE_TOLERANCE * f[1].max()      # noise: within the tolerance
    check_field(f, "smile", "cam0")
    f[2, 2:4, 2:4] = -5.0
    with pytest.raises(RadianceError, match=r"L002\.exr \(smile, cam0, light 2\): 12 pixel value\(s\) down to -5"):
        check_field(f, "smile", "cam0", lambda light: f"images/smile/cam0/L{light:03d}.exr")
    assert issubclass(RadianceError, MifacerfError)


@pytest.mark.parametrize("value", [np.nan, np.inf, -np.inf])
def test_non_finite_is_refused(value):
    f = _field()
    f[3, 1, 1, 2] = value
    with pytest.raises(RadianceError, match="light 3: 1 NaN/Inf"):
        check_field(f, "neutral", "cam1")


def _reference_bad_images(f):
    """The rule of mifacerf.validation, image by image over the finite values (the docstring's words)."""
    bad, kinds = [], []
    for i, img in enumerate(f):
        v = img.reshape(-1)
        ok = np.isfinite(v)
        peak = max(float(v[ok].max()) if ok.any() else -np.inf, 1e-3)
        low = float(v[ok].min()) if ok.any() else np.inf
        if not ok.all() or low < -NEGATIVE_TOLERANCE * peak:
            bad.append(i)
            kinds.append(f"{int((~ok).sum())} NaN/Inf" if not ok.all() else
                         f"{int((v < -NEGATIVE_TOLERANCE * peak).sum())} pixel value.s. down to .*negative radiance")
    return bad, kinds


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(1, 5), st.integers(0, 6))
def test_the_one_pass_check_refuses_exactly_what_the_rule_refuses(seed, n_images, n_faults):
    """NaN, ±Inf, negatives at or around the tolerance, all-dark images and images that are all NaN."""
    rng = np.random.default_rng(seed)
    f = rng.uniform(0, 0.6, (n_images, 3, 4, 3)).astype(np.float32)
    if rng.random() < 0.3:
        f[rng.integers(n_images)] = rng.uniform(0, 1e-4, (3, 4, 3))           # all-dark: the peak floor
    for _ in range(n_faults):
        i, y, x, c = rng.integers(n_images), rng.integers(3), rng.integers(4), rng.integers(3)
        kind = rng.integers(5)
        if kind == 3:
            f[i] = np.nan
        else:
            peak = max(float(f[i][np.isfinite(f[i])].max(initial=0.0)), 1e-3)
            f[i, y, x, c] = [np.nan, np.inf, -np.inf][kind] if kind < 3 else \
                -NEGATIVE_TOLERANCE * peak * rng.choice([0.5, 0.999, 1.001, 3.0])
    bad, kinds = _reference_bad_images(f)
    if not bad:
        check_field(f, "e", "c")
        return
    more = rf".*; {len(bad) - 1} more" if len(bad) > 1 else r"(?!.*more image)"
    with pytest.raises(RadianceError, match=rf"light {bad[0]}: {kinds[0]}{more}"):
        check_field(f, "e", "c")


def test_build_refuses_a_capture_with_a_negative_patch(toy_truth, tmp_path):
    from mifacerf.formats.capture import Capture
    from mifacerf.formats.files import sha256_file
    from mifacerf.imageio import read_exr, write_exr
    from mifacerf.rendering.build import build_model

    cap = tmp_path / "capture"
    shutil.copytree(toy_truth, cap)
    c = Capture(cap)
    name, cam = c.expressions[1].name if hasattr(c.expressions[1], "name") else c.expressions[1], c.rig.cameras[0].name
    path = c.image_path(name, cam, 3)
    img = read_exr(path)
    img[5:15, 5:15] = -5.0
    old_sha = sha256_file(path)
    write_exr(path, img, half=False)       # as the camera wrote it: the manifest's checksum follows
    manifest = cap / "manifest.json"
    manifest.write_text(manifest.read_text().replace(old_sha, sha256_file(path)))
    for cache in (cap / "cache").rglob("*.npy") if (cap / "cache").exists() else []:
        cache.unlink()
    with pytest.raises(RadianceError, match=f"L003.exr .{name}, {cam}, light 3.: .*negative radiance"):
        build_model(cap, tmp_path / "model", progress=False)
    assert not (tmp_path / "model" / "model.json").exists()
