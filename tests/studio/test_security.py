"""The studio's server refuses what another page, another host or a crafted path could do (ASGI test client)."""
import os

import pytest

from mifacerf.studio.security import UnsafePath, allowed_hosts, safe_path


def test_safe_path_refuses_leaving_the_folder(tmp_path):
    root = tmp_path / "capture"
    (root / "hand").mkdir(parents=True)
    (root / "hand" / "template.json").write_text("{}")
    (tmp_path / "secret.txt").write_text("secret")
    os.symlink(tmp_path / "secret.txt", root / "hand" / "link.json")
    os.symlink(tmp_path, root / "up")
    assert safe_path(root, "hand/template.json") == (root / "hand" / "template.json").resolve()
    for bad in ["../secret.txt", "hand/../../secret.txt", "/etc/passwd", str(tmp_path / "secret.txt"),
                "hand/link.json", "up/secret.txt", "", "hand//template.json", "hand\\..\\..\\secret.txt",
                "C:/Windows", "~/x", "hand/\x00"]:
        with pytest.raises(UnsafePath):
            safe_path(root, bad)


def test_allowed_hosts():
    assert allowed_hosts("127.0.0.1", 8765) == {"127.0.0.1:8765", "localhost:8765"}
    assert "evil.example:8765" not in allowed_hosts("127.0.0.1", 8765)


def test_token_is_required_for_every_api_request(capture, client_for):
    c, tok = client_for(capture)
    assert c.get("/").status_code == 200                        # the page itself holds no data
    assert c.get("/api/session").status_code == 401
    assert c.get("/api/session", headers={"X-Studio-Token": "wrong"}).status_code == 401
    assert c.get("/api/session", headers={"X-Studio-Token": tok}).status_code == 200
    assert c.get(f"/api/image/neutral/cam0.png?token={tok}").status_code == 200   # an <img> carries it in the URL
    before = (capture / "hand" / "coarse_points.json").read_bytes()
    r = c.put("/api/expression/neutral/hand", json={"version": "x", "state": {}})
    assert r.status_code == 401
    r = c.post("/api/register/neutral")
    assert r.status_code == 401
    assert (capture / "hand" / "coarse_points.json").read_bytes() == before
    assert not (capture / "registration").exists()


def test_dns_rebinding_and_cross_site_requests_are_refused(capture, client_for):
    c, tok = client_for(capture)
    h = {"X-Studio-Token": tok}
    # a rebinding attack's requests carry the attacker's host name
    assert c.get("/api/session", headers={**h, "Host": "evil.example:8765"}).status_code == 421
    assert c.get("/", headers={"Host": "evil.example"}).status_code == 421
    # a cross-site form / fetch: the browser sends the other page's Origin
    before = (capture / "hand" / "coarse_points.json").read_bytes()
    r = c.put("/api/expression/neutral/hand", headers={**h, "Origin": "http://evil.example"},
              json={"version": "x", "state": {}})
    assert r.status_code == 403
    r = c.post("/api/triangulate", headers={**h, "Origin": "null"}, json={"clicks": {}})
    assert r.status_code == 403
    r = c.post("/api/register/neutral", headers={**h, "Sec-Fetch-Site": "cross-site"})
    assert r.status_code == 403
    assert (capture / "hand" / "coarse_points.json").read_bytes() == before
    # the same origin is fine
    r = c.post("/api/triangulate", headers={**h, "Origin": "http://testserver"}, json={"clicks": {}})
    assert r.status_code == 200
    # and every answer forbids framing and foreign scripts
    r = c.get("/")
    assert r.headers["x-frame-options"] == "DENY"
    assert "default-src 'self'" in r.headers["content-security-policy"]


def test_only_files_inside_the_capture_are_served(capture, studio_capture, client_for):
    _, truth = studio_capture
    c, tok = client_for(capture)
    h = {"X-Studio-Token": tok}
    assert c.get("/api/file", params={"path": "hand/template.json"}, headers=h).status_code == 200
    assert c.get("/api/file", params={"path": "manifest.json"}, headers=h).status_code == 200
    os.symlink(truth, capture / "truth")                 # a symlink out of the folder (to the truth, even)
    os.symlink(truth / "truth.json", capture / "hand" / "t.json")
    for bad in ["../hidden-truth/truth.json", "/etc/passwd", str(truth / "truth.json"), "truth/truth.json",
                "hand/t.json", "hand/../../hidden-truth/truth.json", "hand/nothing.json"]:
        r = c.get("/api/file", params={"path": bad}, headers=h)
        assert r.status_code in (400, 404), bad
        assert b"expressions" not in r.content
    # the static route too
    assert c.get("/static/app.js").status_code == 200
    for bad in ["/static/../server.py", "/static/%2e%2e/server.py", "/static/..%2fsession.py"]:
        r = c.get(bad)
        assert r.status_code == 404 and b"import" not in r.content, bad


def test_names_in_routes_cannot_reach_outside(capture, client_for):
    """Expression and camera names come from the manifest: a crafted one in a view, a save or a
    registration request is refused and writes nothing."""
    c, tok = client_for(capture)
    h = {"X-Studio-Token": tok}
    before = sorted(p.relative_to(capture).as_posix() for p in capture.rglob("*"))
    for url in ["/api/image/..%2F..%2Fetc/cam0.png", "/api/image/neutral/..%2Fcam0.png",
                "/api/image/%2Fetc%2Fpasswd/cam0.png", "/api/expression/..%2Fmanifest",
                "/api/proposals/..%2F..%2Fx"]:
        r = c.get(url + ("&" if "?" in url else "?") + f"token={tok}")
        assert r.status_code in (400, 404), url
    for name in ["..%2F..%2Fevil", "%2Ftmp%2Fevil", "neutral%2F..%2F..%2Fevil"]:
        r = c.put(f"/api/expression/{name}/hand", headers=h, json={"version": "x", "state": {}})
        assert r.status_code in (400, 404), name
        assert c.post(f"/api/register/{name}", headers=h).status_code in (400, 404), name
    assert sorted(p.relative_to(capture).as_posix() for p in capture.rglob("*")) == before


def test_a_cross_site_form_post_without_the_token_is_refused(capture, client_for):
    """A form another page submits (no custom header possible, so no token; text/plain body) changes nothing."""
    c, _ = client_for(capture)
    before = (capture / "hand" / "coarse_points.json").read_bytes()
    r = c.post("/api/expression/smile/hand", content=b'{"version": "x", "state": {}}',
               headers={"Content-Type": "text/plain", "Sec-Fetch-Site": "same-site"})
    assert r.status_code == 401
    r = c.post("/api/expression/smile/hand", content=b"state=x",
               headers={"Content-Type": "application/x-www-form-urlencoded", "Origin": "http://127.0.0.1.evil.example"})
    assert r.status_code == 403
    assert (capture / "hand" / "coarse_points.json").read_bytes() == before
