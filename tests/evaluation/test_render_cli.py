"""`mifacerf evaluate render` prints what the user sees per case and per kind (the report itself is
measured end to end in tests/rendering/test_eyes_teeth_tiny.py::test_evaluation_report)."""
from click.testing import CliRunner


def test_evaluate_render_prints_composite_iou_uncovered(tmp_path, monkeypatch):
    import mifacerf.evaluation.render_cases as rc
    from mifacerf.cli import main

    s = lambda x: {"n": 1, "mean": x, "min": x, "median": x, "max": x}  # noqa: E731
    case = {"case": "a", "label": "a:neutral@cam0", "env": "sky", "psnr": 35.0, "psnr_composite": 21.5,
            "silhouette_iou": 0.75, "uncovered": 0.25}
    report = {"cases": [case], "truth_noise_psnr": 40.0,
              "summary": {"a": {"psnr": s(35.0), "psnr_noise_corrected": s(36.0), "psnr_composite": s(21.5),
                                "silhouette_iou": s(0.75), "uncovered": s(0.25), "seconds": s(0.5),
                                "error_share": {"face": s(0.1), "extension": s(0.6), "silhouette": s(0.25),
                                                "extra": s(0.05)}}}}
    seen = {}

    def evaluate(*a, **k):
        seen.update(k)
        return report
    monkeypatch.setattr(rc, "evaluate", evaluate)
    (tmp_path / "m").mkdir()
    r = CliRunner().invoke(main, ["evaluate", "render", str(tmp_path), str(tmp_path / "m"), "-o", str(tmp_path / "ev"),
                                  "--seed", "1", "--size", "64"])
    assert r.exit_code == 0, r.output
    assert "a:neutral@cam0" in r.output and "composite 21.50 dB, IoU 0.7500, uncovered 25.00 %" in r.output
    assert "case a: PSNR 35.00 dB" in r.output and "composite 21.50 dB (min 21.50), IoU 0.7500" in r.output
    assert "uncovered 25.00 % (max 25.00 %)" in r.output
    assert "composite error: face 10 %, extension 60 %, silhouette 25 %, extra 5 %" in r.output
    assert seen["size"] == 64 and seen["seed"] == 1
