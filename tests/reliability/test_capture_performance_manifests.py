"""Manifest keys of the capture and performance folders are required (no default stands in for a deleted
calibration); the performance folder carries checksums and refuses to mix two recordings."""
import json

import numpy as np
import pytest

from mifacerf.formats.capture import Capture, CaptureError, CaptureWriter, ExpressionEntry
from mifacerf.formats.performance import PerformanceError, PerformanceFolder, PerformanceWriter
from mifacerf.rig import LightStage, Rig, camera_ring


@pytest.fixture
def capture(tmp_path):
    rig = Rig(LightStage.semicircular_arm(2, 2), camera_ring([(-20, 0), (20, 0)], width=6, height=5))
    w = CaptureWriter(tmp_path / "cap", rig, [ExpressionEntry("neutral", "neutral")])
    rng = np.random.default_rng(0)
    for c in rig.cameras:
        for light in range(len(rig.lights)):
            w.write_image("neutral", c.name, light, rng.random((5, 6, 3)).astype(np.float32))
    w.finish()
    return tmp_path / "cap"


def _edit(path, edit):
    m = json.loads(path.read_text())
    edit(m)
    path.write_text(json.dumps(m))


CAPTURE_KEYS = [
    (lambda m: m.pop("image_pattern"), "lacks 'image_pattern'"),
    (lambda m: m.pop("checksums"), "lacks 'checksums'"),
    (lambda m: m["rig"]["cameras"][0].pop("radiometry"), "camera 0: lacks 'radiometry'"),
    (lambda m: m["rig"]["cameras"][1]["radiometry"].pop("exposure"), "radiometry: lacks 'exposure'"),
    (lambda m: m["rig"]["cameras"][0]["radiometry"].pop("colour_matrix"), "radiometry: lacks 'colour_matrix'"),
    (lambda m: m["rig"]["cameras"][0]["radiometry"].pop("response"), "radiometry: lacks 'response'"),
    (lambda m: m["rig"]["cameras"][0].pop("dist"), "camera 0: lacks 'dist'"),
    (lambda m: m["rig"]["lights"]["lights"][2].pop("irradiance"), "light 2: lacks 'irradiance'"),
    (lambda m: m["rig"]["lights"]["lights"][0].pop("strobe"), "light 0: lacks 'strobe'"),
    (lambda m: m["rig"]["lights"].pop("layout"), "rig.lights: lacks 'layout'"),
    (lambda m: m["expressions"][0].pop("category"), "expression entry 0: lacks 'category'"),
]


@pytest.mark.parametrize("edit,message", CAPTURE_KEYS, ids=[m for _, m in CAPTURE_KEYS])
def test_a_capture_manifest_without_a_key_is_refused(capture, edit, message):
    Capture(capture)
    _edit(capture / "manifest.json", edit)
    with pytest.raises(CaptureError, match=message.replace("(", r"\(")):
        Capture(capture)


def _perf(root, n=3, fps=30.0, seed=0, cams=None):
    cams = cams or camera_ring([(-20, 0), (20, 0)], width=6, height=5)
    w = PerformanceWriter(root, cams, fps, n, {"schema": "mifacerf.template/1"}, extra={"lighting": {}})
    rng = np.random.default_rng(seed)
    for f in range(n):
        for c in cams:
            if not w.has_frame(f):
                w.write(c.name, f, rng.random((5, 6, 3)).astype(np.float32))
    return w.finish()


def test_performance_checksums_and_keys(tmp_path):
    perf = _perf(tmp_path / "perf")
    pf = PerformanceFolder(perf)
    assert len(pf.checksums) == 6 and pf.verify() == []
    frame = perf / "frames" / "cam1" / "F00001.exr"
    data = bytearray(frame.read_bytes())
    data[-10] ^= 1
    frame.write_bytes(bytes(data))
    problems = PerformanceFolder(perf).verify()
    assert len(problems) == 1 and "F00001.exr: checksum mismatch" in problems[0]
    for key in ("frame_pattern", "template", "checksums"):
        _edit(perf / "manifest.json", lambda m: m.pop(key))
        with pytest.raises(PerformanceError, match=f"lacks '{key}'"):
            PerformanceFolder(perf)
        _perf(perf)                                    # same settings: resumed, manifest written again


def test_a_recording_with_other_settings_is_not_mixed_in(tmp_path):
    perf = _perf(tmp_path / "perf", n=3)
    before = {p: p.read_bytes() for p in perf.rglob("*.exr")}
    with pytest.raises(PerformanceError, match=r"other settings \(n_frames differ\)"):
        _perf(perf, n=4)
    with pytest.raises(PerformanceError, match=r"other settings \(fps differ\)"):
        _perf(perf, fps=60.0)
    assert {p: p.read_bytes() for p in perf.rglob("*.exr")} == before
    _perf(perf, n=3, seed=1)                           # the same settings resume: frames kept as they are
    assert {p: p.read_bytes() for p in perf.rglob("*.exr")} == before


def test_two_recordings_into_one_performance_folder_the_second_is_refused(tmp_path):
    """The writer holds the folder's lock until finish: a second recording (another process; here another
    thread, which flock treats alike) is refused at once and writes nothing; once the first is done, a
    recording with the same settings resumes."""
    from mifacerf.errors import RefusedError

    from .faults import hold_lock

    perf = _perf(tmp_path / "perf", n=3)
    before = {p: p.read_bytes() for p in perf.rglob("*") if p.is_file()}
    release = hold_lock(perf, PerformanceError)
    try:
        with pytest.raises(RefusedError, match=r"perf: locked by PID .*another performance recording"):
            _perf(perf, n=3)
    finally:
        release()
    assert {p: p.read_bytes() for p in perf.rglob("*") if p.is_file()} == before
    _perf(perf, n=3)


def test_performance_frames_are_checked_when_read(tmp_path):
    """Item 3: a frame damaged after the recording is found when it is read (tracking reads every frame
    through PerformanceFolder.read), not only by 'mifacerf verify': the size of each frame at open, its
    checksum at first read; a mismatch names the file. A frame missing is a dropped one (None)."""
    perf = _perf(tmp_path / "perf")
    assert set(json.loads((perf / "manifest.json").read_text())["sizes"]) == set(PerformanceFolder(perf).checksums)
    flipped = perf / "frames" / "cam1" / "F00001.exr"
    data = bytearray(flipped.read_bytes())
    data[len(data) // 2] ^= 0x10                       # same size: opening stays cheap and passes
    flipped.write_bytes(bytes(data))
    pf = PerformanceFolder(perf)
    assert pf.read("cam0", 1).shape == (5, 6, 3)
    with pytest.raises(PerformanceError, match=r"cam1/F00001.exr: checksum mismatch"):
        pf.read("cam1", 1)
    truncated = perf / "frames" / "cam0" / "F00002.exr"
    truncated.write_bytes(truncated.read_bytes()[:-7])
    with pytest.raises(PerformanceError, match=r"cam0/F00002.exr: \d+ bytes, the manifest says \d+"):
        PerformanceFolder(perf)
    truncated.unlink()                                  # deleted: a dropped frame, reported by verify
    flipped.unlink()
    pf = PerformanceFolder(perf)
    assert pf.read("cam0", 2) is None and pf.read("cam1", 1) is None
    assert any("F00002.exr: missing" in p for p in pf.verify())
    extra = perf / "frames" / "cam0" / "F00007.exr"     # a frame added after the recording
    extra.write_bytes((perf / "frames" / "cam0" / "F00000.exr").read_bytes())
    with pytest.raises(PerformanceError, match=r"F00007.exr: not in the manifest's checksums"):
        pf.read("cam0", 7)
