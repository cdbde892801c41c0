"""The studio's API on a tiny synthetic capture: views, triangulation, saves (versions, conflicts, atomicity),
bad input, the overrides honoured by registration, and no file of the truth opened."""
import json
import os

import numpy as np
import pytest
from openwatch import watch_opens


def _h(tok):
    return {"X-Studio-Token": tok}


def test_session_lists_expressions_cameras_and_template(capture, client_for):
    c, tok = client_for(capture)
    d = c.get("/api/session", headers=_h(tok)).json()
    assert [e["name"] for e in d["expressions"]] == ["neutral", "smile"]
    assert all(not e["registered"] and e["missing_images"] == 0 for e in d["expressions"])
    assert all(e["coarse_points"] == 18 for e in d["expressions"])      # the synthetic user's clicks
    assert [cam["name"] for cam in d["cameras"]] == ["cam0", "cam1", "cam2"]
    assert d["neutral"] == "neutral" and d["template"]["n_vertices"] > 300
    assert len(d["template"]["edges"]) > d["template"]["n_vertices"]


@pytest.mark.parametrize("kind", ["diffuse", "p95", "sum", "light", "dots"])
def test_views_are_tone_mapped_pngs(capture, client_for, kind):
    import cv2

    c, tok = client_for(capture)
    r = c.get(f"/api/image/neutral/cam1.png?kind={kind}&light=3&exposure=0.5&gamma=2.2&token={tok}")
    assert r.status_code == 200 and r.headers["content-type"] == "image/png"
    img = cv2.imdecode(np.frombuffer(r.content, np.uint8), cv2.IMREAD_COLOR)
    assert img.shape == (128, 128, 3)
    assert img.max() > 100 and img.min() < 10                          # a lit face on a dark background
    brighter = c.get(f"/api/image/neutral/cam1.png?kind={kind}&light=3&exposure=2&token={tok}")
    img2 = cv2.imdecode(np.frombuffer(brighter.content, np.uint8), cv2.IMREAD_COLOR)
    assert img2.astype(float).mean() > img.astype(float).mean()


def test_bad_view_requests_are_one_line_errors(capture, client_for):
    c, tok = client_for(capture)
    for url in ["/api/image/nope/cam0.png", "/api/image/neutral/cam9.png", "/api/image/neutral/cam0.png?kind=x",
                "/api/image/neutral/cam0.png?kind=light&light=999", "/api/image/neutral/cam0.png?exposure=abc"]:
        r = c.get(url, headers=_h(tok))
        assert r.status_code == 400, url
        assert "\n" not in r.json()["error"]


def test_triangulation_of_clicks_and_clicks_outside_the_image(capture, client_for):
    from mifacerf.formats.capture import Capture

    c, tok = client_for(capture)
    cams = Capture(capture).rig.cameras
    X = np.array([0.004, 0.02, 0.09])
    clicks = {cam.name: cam.project(X[None])[0][0].tolist() for cam in cams[:2]}
    r = c.post("/api/triangulate", headers=_h(tok), json={"clicks": clicks}).json()
    assert r["ok"] and np.allclose(r["position"], X, atol=1e-6)
    assert set(r["reprojection"]) == {"cam0", "cam1", "cam2"}
    assert np.allclose(r["reprojection"]["cam2"], cams[2].project(X[None])[0][0], atol=1e-3)
    assert max(r["residual_px"].values()) < 1e-3
    # one view + a depth: on that view's ray at that depth
    one = c.post("/api/triangulate", headers=_h(tok), json={"clicks": {"cam0": clicks["cam0"]},
                                                              "depth_from": (X + [0, 0, 0.0]).tolist()}).json()
    assert np.allclose(one["position"], X, atol=1e-6)
    assert not c.post("/api/triangulate", headers=_h(tok), json={"clicks": {"cam0": clicks["cam0"]}}).json()["ok"]
    r = c.post("/api/triangulate", headers=_h(tok), json={"clicks": {"cam0": [500, 3], "cam1": [3, 3]}})
    assert r.status_code == 400 and "outside" in r.json()["error"]


def test_saves_are_versioned_and_a_second_tab_loses_nothing(capture, client_for):
    c, tok = client_for(capture)
    a = c.get("/api/expression/smile", headers=_h(tok)).json()      # tab A
    b = c.get("/api/expression/smile", headers=_h(tok)).json()      # tab B
    assert a["version"] == b["version"]
    sa = a["state"]
    sa["rotoscope"]["points"]["lower_teeth"] = {"cam0": [60.0, 80.0], "cam1": [61.5, 80.5]}
    r = c.put("/api/expression/smile/hand", headers=_h(tok), json={"version": a["version"], "state": sa})
    assert r.status_code == 200 and r.json()["version"] != a["version"]
    rot = json.loads((capture / "hand" / "rotoscope" / "smile.json").read_text())
    assert rot["points"]["lower_teeth"]["cam1"] == [61.5, 80.5] and rot["format"] == "mifacerf.rotoscope"
    # tab B saves from the old version: refused, told, and its state kept on disk
    sb = b["state"]
    sb["coarse"].pop("0")
    r = c.put("/api/expression/smile/hand", headers=_h(tok), json={"version": b["version"], "state": sb})
    assert r.status_code == 409
    d = r.json()
    assert d["conflict"] and d["current"]["rotoscope"]["points"]["lower_teeth"]["cam0"] == [60.0, 80.0]
    kept = json.loads((capture / d["kept"]).read_text())
    assert "0" not in kept["refused_state"]["coarse"]
    coarse = json.loads((capture / "hand" / "coarse_points.json").read_text())
    assert "0" in coarse["expressions"]["smile"]               # A's file untouched by B's refused save
    # the registration reads what the studio wrote
    from mifacerf.registration.hand import read_hand_inputs

    hi = read_hand_inputs(capture, ["cam0", "cam1", "cam2"])
    assert hi.rotoscope["smile"].points["lower_teeth"]["cam1"].tolist() == [61.5, 80.5]
    assert len(hi.coarse["smile"].clicks) == 18


def test_bad_edits_are_refused_and_leave_the_files(capture, client_for):
    c, tok = client_for(capture)
    d = c.get("/api/expression/smile", headers=_h(tok)).json()
    before = (capture / "hand" / "coarse_points.json").read_bytes()
    for bad in [{"coarse": {"0": {"clicks": {"cam0": [1e4, 2]}}}},           # outside the image
                {"coarse": {"0": {"clicks": {"camX": [1, 2]}}}},             # unknown camera
                {"coarse": {"99999": {"clicks": {"cam0": [1, 2]}}}},         # no such vertex
                {"rotoscope": {"curves": {"nose_tip": {"cam0": [[1, 2], [3, 4]]}}}},
                {"overrides": {"5": {"clicks": {"cam0": ["a", 2]}}}}]:
        r = c.put("/api/expression/smile/hand", headers=_h(tok), json={"version": d["version"], "state": bad})
        assert r.status_code == 400, bad
    assert (capture / "hand" / "coarse_points.json").read_bytes() == before


def test_a_save_killed_midway_leaves_the_previous_file_whole(capture, monkeypatch):
    from mifacerf.studio.session import Session

    s = Session(capture)
    before = (capture / "hand" / "coarse_points.json").read_bytes()
    st = s.hand_state("smile")
    st["coarse"]["0"]["clicks"]["cam0"] = [10.0, 10.0]

    def killed(*a, **k):
        raise KeyboardInterrupt("killed mid-save")
    monkeypatch.setattr(os, "replace", killed)
    with pytest.raises(KeyboardInterrupt):
        s.save_hand("smile", st, s.version("smile"))
    monkeypatch.undo()
    assert (capture / "hand" / "coarse_points.json").read_bytes() == before
    assert not [p for p in (capture / "hand").iterdir() if p.name.endswith(".tmp")]


def test_missing_images_are_listed_not_fatal(capture, client_for):
    (capture / "images" / "smile" / "cam2" / "L005.exr").unlink()
    c, tok = client_for(capture)
    ex = {e["name"]: e for e in c.get("/api/session", headers=_h(tok)).json()["expressions"]}
    assert ex["smile"]["missing_images"] == 1 and ex["neutral"]["missing_images"] == 0
    r = c.get(f"/api/image/smile/cam2.png?kind=sum&token={tok}")
    assert r.status_code == 400 and "L005" in r.json()["error"]
    assert c.get(f"/api/image/smile/cam1.png?kind=sum&token={tok}").status_code == 200


def test_not_a_capture_folder_is_one_line(tmp_path):
    from click.testing import CliRunner

    from mifacerf.studio.cli import studio_cmd

    r = CliRunner().invoke(studio_cmd, [str(tmp_path)])
    assert r.exit_code != 0
    assert "not a capture folder" in r.output and "Traceback" not in r.output
    assert len(r.output.strip().splitlines()) == 1


def test_port_in_use_next_free_or_clear_message(capture):
    import socket

    from mifacerf.studio.server import free_port, serve
    from mifacerf.studio.session import StudioError

    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    s.listen()
    port = s.getsockname()[1]
    try:
        nxt = free_port("127.0.0.1", port)
        assert nxt is not None and nxt != port
        with pytest.raises(StudioError, match="in use"):
            serve(capture, port=port, next_free=False, echo=lambda *a, **k: None)
    finally:
        s.close()


def _register(c, h, name):
    """Run "register this expression" through the API and wait for the job (its final state)."""
    import time

    job = c.post(f"/api/register/{name}", headers=h).json()
    for _ in range(900):
        j = c.get(f"/api/jobs/{job['id']}", headers=h).json()
        if j["state"] in ("done", "failed"):
            return j
        time.sleep(0.2)
    raise AssertionError("registration did not finish")


@pytest.mark.slow
def test_register_with_a_hand_fix_and_proposals_read_no_truth(capture, studio_capture, client_for):
    """Register the neutral through the API, fix one fiducial by hand, register again: the fix is kept
    (status hand_fixed, at the fixed position); the proposals for the smile come from the neutral.
    Nothing under the truth folder is opened."""
    _, truth = studio_capture
    with watch_opens(truth) as opened:
        c, tok = client_for(capture)
        h = _h(tok)

        def register(name):
            return _register(c, h, name)
        assert register("neutral")["state"] == "done"
        g = c.get("/api/expression/neutral", headers=h).json()
        st = g["geometry"]["status"]
        assert st.count("snapped") > 100
        vid = st.index("failed")                      # a fiducial registration could not place
        P = np.asarray(g["geometry"]["positions"][vid]) + [0.001, 0.0, 0.0]
        from mifacerf.formats.capture import Capture

        cams = Capture(capture).rig.cameras
        clicks = {cam.name: cam.project(P[None])[0][0].tolist() for cam in cams[:2]}
        state = g["state"]
        state["overrides"] = {str(vid): {"clicks": clicks, "position": None}}
        r = c.put("/api/expression/neutral/hand", headers=h, json={"version": g["version"], "state": state})
        assert r.status_code == 200
        ov = json.loads((capture / "hand" / "overrides.json").read_text())
        assert ov["format"] == "mifacerf.registration_overrides" and str(vid) in ov["expressions"]["neutral"]
        assert register("neutral")["state"] == "done"
        g2 = c.get("/api/expression/neutral", headers=h).json()
        assert g2["geometry"]["status"][vid] == "hand_fixed"
        assert np.allclose(g2["geometry"]["positions"][vid], P, atol=2e-6)
        assert g2["geometry"]["report"]["hand_fixed"] == [vid]
        prop = c.get("/api/proposals/smile", headers=h).json()
        assert prop["source"] == "neutral"
        assert len(prop["state"]["coarse"]) >= 12
        assert {"lip_upper", "lip_lower"} <= set(prop["state"]["rotoscope"]["curves"])
    assert opened == [], "the studio opened ground-truth files"


@pytest.mark.slow
def test_from_no_hand_inputs_to_registered_expressions(capture, studio_capture, client_for):
    """No hand/ at all: the template is proposed from the neutral's images (dots matched across views,
    lip and eyelid margins, eyes, teeth, regions, head points), accepted; then every expression is
    proposed, accepted unedited and registered. Registration runs on nothing but the studio's
    proposals, and nothing under the truth folder is opened on the way."""
    import shutil

    _, truth = studio_capture
    shutil.rmtree(capture / "hand")
    with watch_opens(truth) as opened:
        c, tok = client_for(capture)
        h = _h(tok)
        assert "missing" in c.get("/api/session", headers=h).json()["template_problem"]
        assert c.post("/api/register/neutral", headers=h).status_code == 400     # nothing to register into
        r = c.post("/api/proposals/template", headers=h, json={"accept": True}).json()
        assert r["accepted"] and r["summary"]["points"] >= 60
        tpl = json.loads((capture / "hand" / "template.json").read_text())
        assert tpl["schema"] == "mifacerf.template/1" and len(tpl["coarse_points"]) == 18
        assert len(tpl["triangles"]) > len(tpl["vertices"])
        assert set(tpl["margins"]) == {"lip_upper", "lip_lower", "lid_upper_L", "lid_lower_L", "lid_upper_R",
                                       "lid_lower_R"}
        assert set(tpl["eyes"]) == {"eye_left", "eye_right"} and set(tpl["teeth"]) == {"upper", "lower"}
        assert {"forehead", "nose", "chin", "mouth"} <= set(tpl["regions"])
        assert set(tpl["head_points"]) == {"ear_L", "ear_R", "nose_bridge"}
        kinds = [v["kind"] for v in tpl["vertices"]]
        n_dots = kinds.count("dot")
        # the left eye is on the subject's left (+X), the mouth below the eyes
        assert tpl["eyes"]["eye_left"]["centre"][0] > tpl["eyes"]["eye_right"]["centre"][0]
        lips = [tpl["vertices"][i]["position"][1] for i in tpl["margins"]["lip_upper"]]
        assert max(lips) < tpl["eyes"]["eye_left"]["centre"][1] - 0.04

        def register(name):
            return _register(c, h, name)
        for name in ("neutral", "smile"):
            g = c.get(f"/api/expression/{name}", headers=h).json()
            prop = c.get(f"/api/proposals/{name}", headers=h).json()
            assert prop["source"] == ("template" if name == "neutral" else "neutral")
            assert len(prop["state"]["coarse"]) >= 14 and len(prop["state"]["rotoscope"]["curves"]) == 8
            assert c.put(f"/api/expression/{name}/hand", headers=h,
                         json={"version": g["version"], "state": prop["state"]}).status_code == 200
            assert register(name)["state"] == "done"
        ex = {e["name"]: e for e in c.get("/api/session", headers=h).json()["expressions"]}
        for name in ("neutral", "smile"):
            assert ex[name]["registered"] and ex[name]["n_dots"] == n_dots
            assert ex[name]["dots_registered"] >= 0.45 * n_dots, ex[name]
        meta = json.loads((capture / "registration" / "registration.json").read_text())
        rep = meta["expressions"]["smile"]
        assert all(v["views"] for v in rep["lips_eyelids"].values() if isinstance(v, dict))
        eyes = np.load(capture / "registration" / "expressions" / "smile.npz")["eye_centres"]
        assert np.isfinite(eyes).all() and eyes[0, 0] > eyes[1, 0]     # from the proposed template's eyes
    assert opened == []
    assert sorted(p.name for p in (capture / "hand").iterdir()) == ["coarse_points.json", "rotoscope", "template.json"]


def test_views_with_no_dots_give_no_proposals_and_no_crash(capture, monkeypatch):
    """A view with no dots (here: every view's dot map blank) yields empty proposals with a note."""
    import mifacerf.studio.proposals as P
    from mifacerf.studio import template_proposal as TP
    from mifacerf.studio.session import Session

    s = Session(capture)
    blank = {c.name: np.zeros((c.height, c.width), np.float32) for c in s.cams}
    monkeypatch.setattr(P, "_strength_maps", lambda session, name: dict(blank))
    r = P.propose_expression(s, "smile")
    tpl = s.template()
    # only the coarse points that are no fiducial (mouth corners, ears) remain: they have no dot to find
    assert r["state"] is not None and r["state"]["coarse"]
    assert not any(tpl.is_dot[int(v)] for v in r["state"]["coarse"])
    P3, summary = TP.detect_and_match(s.cams, blank)
    assert len(P3) == 0 and summary["points"] == 0
