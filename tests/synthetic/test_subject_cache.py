"""The synthetic subject is the same, bit for bit, whether its cached parts were just built or read back from
the cache (the static texture maps are stored in float16: a freshly built subject uses them rounded the same
way). A process with a cold cache and one with a warm cache — the main process and a worker — must render
the same capture (issue 20's byte-identical distributed synth)."""
import numpy as np


def test_cold_and_warm_cache_give_the_same_subject(tmp_path, monkeypatch):
    import shutil

    from mifacerf.synthetic import cache
    from mifacerf.synthetic.subject import Subject, default_subject

    first = default_subject()          # (built once per process, shared with other tests): its dots and skin
    # the suite's cache without the two static maps: the slow texture-independent parts are read, not
    # rebuilt (they are not what this test is about); the 128-texel parts are built if missing
    shutil.copytree(cache.cache_dir(), tmp_path / "cache" / "synthetic")
    monkeypatch.setenv("MIFACERF_CACHE", str(tmp_path / "cache"))
    static = [cache.key("skin-static", 128, float(first.dots_neutral.sum())),
              cache.key("skin-static-nodots", 128, float(first.skin_rest.sum()))]
    for name in static:
        (cache.cache_dir() / f"{name}.npz").unlink(missing_ok=True)
    cold = Subject(128)                                   # builds and saves the static maps
    assert (cache.cache_dir() / f"{static[0]}.npz").exists()
    warm = Subject(128)                                   # reads them back
    for name in ("albedo", "roughness"):
        np.testing.assert_array_equal(getattr(cold.tex, name), getattr(warm.tex, name), err_msg=name)
    cold_clean, warm_clean = cold.without_dots(), warm.without_dots()
    for name in ("albedo", "roughness"):
        np.testing.assert_array_equal(getattr(cold_clean.tex, name), getattr(warm_clean.tex, name),
                                      err_msg=f"dot-free {name}")
