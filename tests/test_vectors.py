"""row_norms against NumPy's own norm: the same values bit for bit (float64 and float32, any K, zeros,
huge and tiny components), and a clear error on a wrong shape."""
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from hypothesis.extra.numpy import arrays

from mifacerf.geometry.vectors import row_norms


@settings(max_examples=60, deadline=None)
@given(arrays(st.sampled_from([np.float64, np.float32]), st.tuples(st.integers(0, 40), st.integers(1, 5)),
              elements=st.floats(-2.0 ** 60, 2.0 ** 60, allow_nan=False, width=32)))
def test_row_norms_equal_numpys_norm(a):
    np.testing.assert_array_equal(row_norms(a), np.linalg.norm(a, axis=1))


def test_row_norms_of_camera_rays_and_bad_shape():
    rng = np.random.default_rng(0)
    d = np.concatenate([rng.random((100_000, 2)) - 0.5, np.ones((100_000, 1))], 1) @ np.linalg.qr(rng.standard_normal((3, 3)))[0]
    np.testing.assert_array_equal(row_norms(d), np.linalg.norm(d, axis=1))
    with pytest.raises(ValueError, match=r"\(N, K\) array, got shape \(3,\)"):
        row_norms(np.ones(3))
