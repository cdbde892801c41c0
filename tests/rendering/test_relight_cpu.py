"""The exact relight sum on the CPU (:mod:`mifacerf.rendering.relight_cpu`, Numba): against a float64
NumPy sum, exact for every finite half, the texels it selects the chunk loop's, and the renderer's frames
equal to Dr.Jit's kernel's to float32 rounding."""
import numpy as np
import pytest

pytest.importorskip("numba")

from mifacerf.rendering import relight_cpu  # noqa: E402
from mifacerf.rendering.relight_cpu import check_map, lit_images  # noqa: E402


def _chunk(rng, rows, n_lights, V, side):
    rf = (rng.standard_normal((rows, n_lights, 3)) * 0.05).astype(np.float16)
    rf[0, 0] = [np.float16(6e-8), np.float16(-3e-5), np.float16(65504)]   # subnormals, the largest half
    rf[1] = 0
    bary = rng.random((rows, 3)).astype(np.float32)
    bary /= bary.sum(1, keepdims=True)
    fv = rng.integers(0, V, (rows, 3))
    lin = rng.choice(side * side, rows, replace=False)
    cov = np.where(rng.random(rows) < 0.2, -1.0, 1.0).astype(np.float32)
    return rf, (bary, fv, lin, cov)


def _reference(rf, m, w, light, ids, size):
    """The chunk loop of ``Renderer.light_frame`` and ``lit_texels``' sum, in float64 NumPy."""
    bary, fv, lin, cov = m
    wt = bary * w[fv]
    keep = wt.sum(1) > 0
    coef = (wt[keep] / wt[keep].sum(1, keepdims=True)).astype(np.float32).astype(np.float64)
    lam = np.einsum("nk,nkj->nj", coef, light.astype(np.float64)[fv[keep]])
    f = rf.astype(np.float64)[keep]                  # (n, L, 3)
    if ids is not None:
        f = f[:, ids]
    rgb = (f.reshape(len(f), f.shape[1] * 3) * lam).reshape(f.shape).sum(1)
    img = np.zeros((size, 4))
    img[lin[keep], :3] = rgb
    img[lin[keep], 3] = cov[keep]
    return img, int(keep.sum())


@pytest.mark.parametrize("n_lights, subset", [(192, False), (30, False), (7, False), (30, True), (16, True)])
def test_lit_images_is_the_chunk_loops_sum(n_lights, subset):
    """Three chunks of two sources — a chunk with zero weights on some vertices, one with none at all —
    against the float64 sum: the same texels lit, the same pixels written, values to float32 rounding."""
    rng = np.random.default_rng(n_lights + subset)
    V, side = 11, 70
    ids = np.sort(rng.choice(n_lights, n_lights - 3, replace=False)) if subset else None
    k = n_lights if ids is None else len(ids)
    lights = [rng.random((V, k * 3)).astype(np.float32) for _ in range(2)]
    chunks = [_chunk(rng, rows, n_lights, V, side) for rows in (300, 57, 4100)]   # 4100: two work items
    weights = rng.random((3, V))
    weights[0, :4] = 0            # some vertices without weight: their texels partly weighted or not lit
    weights[0, 4] = 1e-12         # and one with a tiny weight: its texels are lit all the same
    chunks[0][1][1][:10] = [0, 1, 4]
    weights[1] = 0                # a chunk with nothing to light
    images, lit = lit_images([c[0] for c in chunks], lights, [0, 1, 0], weights, [c[1] for c in chunks],
                             [side * side] * 3, ids)
    images = images.reshape(3, side * side, 4)
    for c, (rf, m) in enumerate(chunks):
        ref, n = _reference(rf, m, weights[c], lights[[0, 1, 0][c]], ids, side * side)
        assert lit[c] == n
        np.testing.assert_array_equal(images[c, :, 3], ref[:, 3])
        np.testing.assert_allclose(images[c, :, :3], ref[:, :3], rtol=2e-5, atol=2e-6)
    assert lit[1] == 0 and not images[1].any()


def test_every_finite_half_is_decoded_exactly():
    """One light of weight 1 per texel, the others 0: each lit value is its half, to the bit
    (NumPy's float16 → float32 conversion is the oracle); subnormals, signed zeros, the largest half."""
    bits = np.arange(1 << 16, dtype=np.uint16)
    halves = bits.view(np.float16)
    halves = halves[np.isfinite(halves)]
    n_lights = 16
    rows = -(-len(halves) // (3 * n_lights))
    rf = np.zeros(rows * n_lights * 3, np.float16)
    rf[:len(halves)] = halves
    rf = rf.reshape(rows, n_lights, 3)
    out = np.empty((rows, n_lights, 3), np.float32)
    side = int(np.ceil(np.sqrt(rows)))
    m = check_map(np.tile([1.0, 0, 0], (rows, 1)), np.zeros((rows, 3), np.int64), np.arange(rows),
                  np.ones(rows), 1, side * side)
    for li in range(n_lights):
        light = np.zeros((1, n_lights * 3), np.float32)
        light[0, 3 * li:3 * li + 3] = 1.0
        img, _ = lit_images([rf], [light], [0], np.ones((1, 1)), [m], [side * side])
        out[:, li] = img.reshape(-1, 4)[:rows, :3]
    got = out.reshape(-1)[:len(halves)]
    want = halves.astype(np.float32)
    np.testing.assert_array_equal(np.abs(got).view(np.uint32), np.abs(want).view(np.uint32))


def test_the_kernels_half_decode_is_numpys_on_every_bit_pattern():
    """The decode the kernel inlines (LLVM's half → float widening) against NumPy's float16 → float32 on
    all 65,536 patterns: the same bits for every non-NaN (signed zeros, subnormals, infinities), NaN for NaN."""
    from mifacerf.rendering._numba_kernels import halves

    bits = np.arange(1 << 16, dtype=np.uint32).astype(np.uint16)
    got = np.empty(len(bits), np.float32)
    halves(bits, got)
    want = bits.view(np.float16).astype(np.float32)
    nan = np.isnan(want)
    assert nan.sum() == 2046 and np.isnan(got[nan]).all()
    np.testing.assert_array_equal(got[~nan].view(np.uint32), want[~nan].view(np.uint32))


def test_bad_maps_and_shapes_are_named():
    ok = (np.full((4, 3), 1 / 3, np.float32), np.zeros((4, 3), np.int64), np.arange(4), np.ones(4, np.float32))
    with pytest.raises(ValueError, match="vertex ids 7..7 outside the mesh's 5 vertices"):
        check_map(ok[0], np.full((4, 3), 7), ok[2], ok[3], 5, 16)
    with pytest.raises(ValueError, match="pixel indices 0..3 outside the image's 3 pixels"):
        check_map(*ok, 5, 3)
    with pytest.raises(ValueError, match=r"bary \(4, 2\)"):
        check_map(ok[0][:, :2], *ok[1:], 5, 16)
    rf = np.zeros((4, 2, 3), np.float16)
    with pytest.raises(ValueError, match="lighting of 9 values a vertex for a field of 6 a row"):
        lit_images([rf], [np.ones((1, 9), np.float32)], [0], np.ones((1, 1)), [check_map(*ok, 1, 16)], [16])
    with pytest.raises(ValueError, match="lighting of 2 vertices for weights of 1"):
        lit_images([rf], [np.ones((2, 6), np.float32)], [0], np.ones((1, 1)), [check_map(*ok, 1, 16)], [16])


def test_the_renderers_frames_match_drjits_kernel(toy_model, monkeypatch):
    """The renderer through the CPU kernel and through Dr.Jit's (``MIFACERF_NUMBA_RELIGHT=0``): the same
    coverage, the same texels and chunks, colours to float32 rounding; a blend from a novel view, under an
    environment whose dark lights are skipped (a light subset) and one where all are used."""
    from mifacerf import environment as E
    from mifacerf.camera import Camera
    from mifacerf.rendering.relight import cpu_kernel
    from mifacerf.rendering.renderer import Renderer, RenderStats

    model = toy_model
    W = np.zeros((model.n_vertices, len(model.expressions)))
    W[:, 0], W[:, 1] = 0.35, 0.65
    target = 0.35 * model.vertices[0] + 0.65 * model.vertices[1]
    cam = Camera.look_at("novel", [0.25, 0.1, 1.2], [0, 0, 0], width=40, height=40, focal=50.0)
    for env in (E.generated("interior", 32), E.generated("sky", 32)):
        out = {}
        for flag in ("1", "0"):
            monkeypatch.setenv("MIFACERF_NUMBA_RELIGHT", flag)
            assert cpu_kernel() == (flag == "1")
            st = RenderStats()
            out[flag] = (Renderer(model).render(target, W, cam, env, spp=2, stats=st), st)
        (a, sa), (b, sb) = out["1"], out["0"]
        assert (sa.texels, sa.chunks, sa.lights_skipped) == (sb.texels, sb.chunks, sb.lights_skipped)
        np.testing.assert_array_equal(a[..., 3], b[..., 3])
        np.testing.assert_allclose(a[..., :3], b[..., :3], rtol=1e-5, atol=1e-6 * b[..., :3].max())


def test_switched_off_and_threads(monkeypatch):
    monkeypatch.setenv("MIFACERF_NUMBA_RELIGHT", "0")
    assert not relight_cpu.available()
    monkeypatch.delenv("MIFACERF_NUMBA_RELIGHT")
    assert relight_cpu.available()
    assert relight_cpu.threads() >= 1


@pytest.mark.parametrize("method, rank", [("sh", 2), ("pca", 5)])
def test_compressed_frames_match_drjits_kernel(toy_model, tmp_path, monkeypatch, method, rank):
    """The compressed methods through the CPU kernel (their ``rows``: ``sh``'s coefficients as a field of
    J lights, ``pca``'s (1, C_1 … C_K) against (m_v, β_v)) and through their Dr.Jit kernels: the same
    coverage, texels and chunks, colours to float32 rounding; and a wrong layout would not pass (the pca
    rows with the mean's term dropped are visibly off)."""
    import shutil

    from mifacerf import environment as E
    from mifacerf.camera import Camera
    from mifacerf.rendering import compression as C
    from mifacerf.rendering.model import Model
    from mifacerf.rendering.renderer import Renderer, RenderStats

    shutil.copytree(toy_model.root, tmp_path / "model")
    model = Model(tmp_path / "model")
    C.compress_model(model, rank, progress=False, method=method)
    W = np.zeros((model.n_vertices, len(model.expressions)))
    W[:, 0], W[:, 1] = 0.4, 0.6
    target = 0.4 * model.vertices[0] + 0.6 * model.vertices[1]
    cam = Camera.look_at("novel", [0.2, 0.1, 1.2], [0, 0, 0], width=40, height=40, focal=50.0)
    env = E.generated("interior", 32)
    out = {}
    for flag in ("1", "0"):
        monkeypatch.setenv("MIFACERF_NUMBA_RELIGHT", flag)
        st = RenderStats()
        out[flag] = (Renderer(model, method=method, rank=rank).render(target, W, cam, env, spp=2, stats=st), st)
    (a, sa), (b, sb) = out["1"], out["0"]
    assert sa.texels > 0 and (sa.texels, sa.chunks) == (sb.texels, sb.chunks)
    np.testing.assert_array_equal(a[..., 3], b[..., 3])
    np.testing.assert_allclose(a[..., :3], b[..., :3], rtol=2e-5, atol=2e-6 * b[..., :3].max())
    if method == "pca":      # the oracle can tell: the mean's term left out of the rows changes the image
        rows = C.COMPRESSION_METHODS["pca"].rows

        def no_mean(data, lighting, keep):
            f, light, ids = rows(data, lighting, keep)
            light = light.copy()
            light[:, :3] = 0
            return f, light, ids

        monkeypatch.setenv("MIFACERF_NUMBA_RELIGHT", "1")
        r = Renderer(model, method=method, rank=rank)
        monkeypatch.setattr(r, "compression", C.CompressionMethod(None, r.compression.load, r.compression.lit,
                                                                  rows=no_mean))
        bad = r.render(target, W, cam, env, spp=2)
        assert np.abs(bad[..., :3] - b[..., :3]).max() > 0.1 * b[..., :3].max()
