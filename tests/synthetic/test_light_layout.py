"""The light stage's discretisation against path-traced truth (mifacerf.evaluation.lightstage)."""
import pytest


@pytest.mark.slow
def test_more_lights_relight_closer_to_the_truth(tmp_path):
    """Relit OLAT images converge to the path-traced truth as the arm gets more stops and strobes:
    the discretisation of the environment is the light stage's only error."""
    from mifacerf.evaluation.lightstage import layout_vs_truth
    from mifacerf.rig import LightStage
    from mifacerf.synthetic.synth import synthesize

    synthesize(tmp_path, preset="tiny", expressions=["neutral"], progress=False)
    layouts = {f"{p}x{s}": LightStage.semicircular_arm(p, s).directions for p, s in ((4, 4), (8, 6), (16, 12))}
    rows = layout_vs_truth(tmp_path, layouts, ["interior"], spp_truth=128)
    got = {r["layout"]: r["psnr"] for r in rows}
    assert got["4x4"] < got["8x6"] < got["16x12"]
    assert got["16x12"] - got["4x4"] > 6.0   # measured 19.2 / 29.6 / 32.2 dB (truth 128 spp x 2)
