"""The studio's bad input (issue 17): folders that are not captures, expressions with missing images, a
server killed mid-save (a real SIGKILL), two tabs editing the template, and the fiducials' status colours."""
import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest


def _h(tok):
    return {"X-Studio-Token": tok}


@pytest.mark.parametrize("case", ["empty", "broken-json", "other-format", "a-file", "missing"])
def test_folders_that_are_not_captures_are_one_line(tmp_path, case):
    from click.testing import CliRunner

    from mifacerf.studio.cli import studio_cmd

    p = tmp_path / "folder"
    if case != "missing":
        p.mkdir()
    if case == "broken-json":
        (p / "manifest.json").write_text("{not json")
    elif case == "other-format":
        (p / "manifest.json").write_text('{"format": "something else"}')
    elif case == "a-file":
        p.rmdir()
        p.write_text("not a folder")
    r = CliRunner().invoke(studio_cmd, [str(p), "--port", "1"])
    assert r.exit_code in (1, 2) and "Traceback" not in r.output, r.output
    said = {"empty": "not a capture folder", "missing": "not a capture folder", "broken-json": "not valid JSON",
            "other-format": "not a mifacerf capture manifest", "a-file": "is a file"}[case]
    assert said in r.output
    errors = [ln for ln in r.output.strip().splitlines() if "error" in ln.lower()]
    assert len(errors) == 1


def test_an_expression_with_a_whole_view_missing(capture, client_for):
    """Every image of one camera of the smile gone: listed, its view answers with the file's name, the
    other views and the neutral still work, and proposing or registering the smile is refused in one line
    naming what is missing (nothing written)."""
    import shutil

    shutil.rmtree(capture / "images" / "smile" / "cam2")
    c, tok = client_for(capture)
    h = _h(tok)
    d = c.get("/api/session", headers=h).json()
    ex = {e["name"]: e for e in d["expressions"]}
    assert ex["smile"]["missing_images"] == d["n_lights"] and ex["neutral"]["missing_images"] == 0
    r = c.get(f"/api/image/smile/cam2.png?token={tok}")
    assert r.status_code == 400 and "cam2/L000" in r.json()["error"]
    assert c.get(f"/api/image/smile/cam0.png?token={tok}").status_code == 200
    assert c.get("/api/expression/smile", headers=h).status_code == 200     # its clicks can still be edited
    before = sorted(p.relative_to(capture).as_posix() for p in capture.rglob("*") if p.is_file())
    for r in (c.get("/api/proposals/smile", headers=h), c.post("/api/register/smile", headers=h)):
        assert r.status_code == 400, r.text
        msg = r.json()["error"]
        assert "\n" not in msg and f"{d['n_lights']} image(s) missing" in msg and "smile/cam2/L000" in msg
    assert not (capture / "registration").exists()
    after = sorted(p.relative_to(capture).as_posix() for p in capture.rglob("*") if p.is_file())
    assert [p for p in after if not p.startswith("cache/")] == [p for p in before if not p.startswith("cache/")]


def test_two_tabs_editing_the_template_the_second_is_told(capture, client_for):
    c, tok = client_for(capture)
    h = _h(tok)
    a = c.get("/api/template", headers=h).json()
    b = c.get("/api/template", headers=h).json()
    assert a["version"] == b["version"]
    ta = a["template"]
    ta["vertices"][0]["position"][0] += 0.001
    r = c.put("/api/template", headers=h, json={"version": a["version"], "template": ta})
    assert r.status_code == 200
    saved = (capture / "hand" / "template.json").read_bytes()
    tb = b["template"]
    tb["vertices"][1]["position"][1] += 0.002
    r = c.put("/api/template", headers=h, json={"version": b["version"], "template": tb})
    assert r.status_code == 409 and r.json()["conflict"]
    assert (capture / "hand" / "template.json").read_bytes() == saved         # the first tab's edit stays
    kept = json.loads((capture / r.json()["kept"]).read_text())
    assert kept["expression"] == "template"
    assert kept["refused_state"]["vertices"][1]["position"] == tb["vertices"][1]["position"]   # nothing lost
    # loading the other version and saving again goes through
    cur = c.get("/api/template", headers=h).json()
    assert cur["template"]["vertices"][0]["position"] == ta["vertices"][0]["position"]
    cur["template"]["vertices"][1]["position"] = tb["vertices"][1]["position"]
    assert c.put("/api/template", headers=h, json={"version": cur["version"],
                                                     "template": cur["template"]}).status_code == 200


_KILLED_SAVE = r"""
import os, sys, time
from mifacerf.studio.session import Session

s = Session(sys.argv[1])
real_fsync = os.fsync

def stalled(fd):              # the new file is written but not yet renamed over the old one: killed here
    real_fsync(fd)
    print("WRITTEN", flush=True)
    time.sleep(120)
os.fsync = stalled
if sys.argv[2] == "hand":
    st = s.hand_state("smile")
    st["coarse"]["0"]["clicks"]["cam0"] = [10.0, 10.0]
    st["rotoscope"]["points"]["lower_teeth"] = {"cam0": [60.0, 80.0], "cam1": [61.0, 80.0]}
    s.save_hand("smile", st, s.version("smile"))
else:
    d = s.template_for_editing()
    d["template"]["vertices"][0]["position"][0] += 0.001
    s.save_template_edit(d["template"], d["version"])
"""


@pytest.mark.parametrize("what", ["hand", "template"])
def test_a_server_killed_mid_save_leaves_the_previous_file_whole(capture, tmp_path, what):
    """A process saving through the studio's session is SIGKILLed after writing the new file's bytes and
    before the rename: the previous file is whole and byte-identical, and a new studio reads and saves."""
    from mifacerf.studio.session import Session

    files = ["hand/coarse_points.json", "hand/template.json"] + \
        [p.relative_to(capture).as_posix() for p in (capture / "hand" / "rotoscope").glob("*.json")]
    before = {f: (capture / f).read_bytes() for f in files}
    script = tmp_path / "save.py"
    script.write_text(_KILLED_SAVE)
    p = subprocess.Popen([sys.executable, str(script), str(capture), what], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True)
    try:
        line = p.stdout.readline()
        assert line.strip() == "WRITTEN", (line, p.stderr.read() if p.poll() is not None else "")
        os.kill(p.pid, signal.SIGKILL)
        p.wait(30)
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode == -signal.SIGKILL
    assert {f: (capture / f).read_bytes() for f in files} == before
    s = Session(capture)                                   # a new server: reads, edits and saves
    st = s.hand_state("smile")
    st["rotoscope"]["points"]["nose_bridge"] = {"cam0": [64.0, 50.0], "cam1": [63.0, 50.0]}
    s.save_hand("smile", st, s.version("smile"))
    assert "nose_bridge" in json.loads((capture / "hand" / "rotoscope" / "smile.json").read_text())["points"]
    assert s.template() is not None


def test_fiducials_are_coloured_by_their_registration_status(capture, monkeypatch):
    """snapped / consensus / single-view / failed / flagged / hand-fixed, and placed / predicted for the
    vertices that are no fiducial, from the expression's status array and its report."""
    from types import SimpleNamespace

    from mifacerf.studio.session import Session

    s = Session(capture)
    tpl = s.template()
    dots = [int(v) for v in tpl.dot_ids[:7]]
    extra = [v for v in range(tpl.n_vertices) if not tpl.is_dot[v]][:2]
    status = np.ones(tpl.n_vertices, np.int8)
    status[dots[3]] = 0
    status[extra[1]] = 0
    reg = SimpleNamespace(status=status, vertices=tpl.vertices)
    report = {"consensus": {"registered": [dots[1]]}, "single_view_dots": [dots[2]], "hand_fixed": [dots[5]],
              "flags": [f"coarse fiducial(s) [{dots[4]}] did not snap to their dot: kept at the prediction",
                        f"dots [{dots[6]}] snapped onto a dot already taken: reverted to prediction"]}
    monkeypatch.setattr(s, "registered", lambda name: reg)
    monkeypatch.setattr(s, "registration_meta", lambda: {"expressions": {"smile": report}})
    st = s.vertex_status("smile")
    assert [st[v] for v in dots] == ["snapped", "consensus", "single_view", "failed", "flagged", "hand_fixed",
                                     "flagged"]
    assert [st[v] for v in extra] == ["placed", "predicted"]
    assert set(st) <= set(s.info()["status_codes"])
