"""The synthetic subject is the same, bit for bit, whether its cached parts were just built or read back from
the cache (the static texture maps are stored in float16: a freshly built subject uses them rounded the same
way). A process with a cold cache and one with a warm cache — the main process and a worker — must render
the same capture (issue 20's byte-identical distributed synth)."""
import numpy as np


def test_cold_and_warm_cache_give_the_same_subject(tmp_path, monkeypatch):
    from mifacerf.synthetic.subject import Subject

    monkeypatch.setenv("MIFACERF_CACHE", str(tmp_path / "cache"))
    cold = Subject(128)                                   # builds and saves every cached part
    assert list((tmp_path / "cache" / "synthetic").glob("head-*-*.npz"))
    warm = Subject(128)                                   # reads them back
    for name in ("albedo", "roughness"):
        np.testing.assert_array_equal(getattr(cold.tex, name), getattr(warm.tex, name), err_msg=name)
    cold_clean, warm_clean = cold.without_dots(), warm.without_dots()
    for name in ("albedo", "roughness"):
        np.testing.assert_array_equal(getattr(cold_clean.tex, name), getattr(warm_clean.tex, name),
                                      err_msg=f"dot-free {name}")
