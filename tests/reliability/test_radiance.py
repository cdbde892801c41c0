"""Issue 15 defect 5: negative or non-finite radiance in a capture is refused by registration and build,
with an error naming the image file, expression, camera and light; tiny negatives (noise) are accepted."""
import shutil

import numpy as np
import pytest

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
