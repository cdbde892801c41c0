"""The exact relight kernel reads float16 fields as 64-bit words (four halves each, :class:`HalfWords`): the
same lit colours bit for bit as the Float16 gathers it replaced, for every light count, light subset and
half value (subnormals, signs, zeros, the largest half)."""
import numpy as np
import pytest

from mifacerf.rendering.relight import half_to_float, lit_texels, to_device_f16, to_device_words


def test_half_to_float_is_exact_for_every_finite_half():
    import drjit as dr

    from mifacerf.jitarrays import to_jit
    from mifacerf.variant import ensure_variant

    mi = ensure_variant()
    bits = np.arange(1 << 16, dtype=np.uint32)
    halves = bits.astype(np.uint16).view(np.float16)
    finite = np.isfinite(halves)
    out = half_to_float(to_jit(mi.UInt32, bits[finite]))
    dr.eval(out)
    np.testing.assert_array_equal(np.asarray(out).view(np.uint32), halves[finite].astype(np.float32).view(np.uint32))


@pytest.mark.parametrize("n_lights", [6, 7, 8, 16])
@pytest.mark.parametrize("subset", [False, True])
def test_words_and_float16_give_the_same_lit_colours(n_lights, subset):
    rng = np.random.default_rng(n_lights)
    rows, V, N = 41, 9, 23
    rf = (rng.standard_normal((rows, n_lights, 3)) * 0.05).astype(np.float16)
    rf[0, 0] = [np.float16(6e-8), np.float16(-3e-5), np.float16(65504)]   # subnormals, the largest half
    rf[1, :] = 0
    texels = rng.choice(rows, N, replace=False)
    vertex_ids = rng.integers(0, V, (N, 3))
    coef = rng.random((N, 3)).astype(np.float32)
    coef /= coef.sum(1, keepdims=True)
    ids = np.sort(rng.choice(n_lights, n_lights - 2, replace=False)) if subset else None
    k = n_lights if ids is None else len(ids)
    lighting = rng.random((V, k, 3)).astype(np.float32)
    a = lit_texels(to_device_f16(rf), n_lights, texels, vertex_ids, coef, lighting, ids)
    b = lit_texels(to_device_words(rf), n_lights, texels, vertex_ids, coef, lighting, ids)
    np.testing.assert_array_equal(a, b)
    ref = np.einsum("nk,nklc->nlc", coef, lighting[vertex_ids])
    sub = rf.astype(np.float32)[texels] if ids is None else rf.astype(np.float32)[texels][:, ids]
    np.testing.assert_allclose(b, np.einsum("nlc,nlc->nc", sub, ref), rtol=1e-4, atol=1e-6)
