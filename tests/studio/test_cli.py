"""``mifacerf studio`` as a user starts it: the printed URL, the loopback address, a port in use, Ctrl-C."""
import queue
import signal
import socket
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest

EXE = str(Path(sys.executable).parent / "mifacerf")


class Started:
    """``mifacerf studio ARGS`` in a subprocess; its output lines read in a thread."""

    def __init__(self, *args):
        self.p = subprocess.Popen([EXE, "studio", *map(str, args)], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                  text=True)
        self.lines = queue.Queue()
        threading.Thread(target=lambda: [self.lines.put(ln) for ln in self.p.stdout], daemon=True).start()
        self.out = []

    def wait_for(self, text, timeout=120.0):
        t0 = time.time()
        while time.time() - t0 < timeout:
            try:
                ln = self.lines.get(timeout=0.5)
            except queue.Empty:
                if self.p.poll() is not None and self.lines.empty():
                    break
                continue
            self.out.append(ln)
            if text in ln:
                return ln.strip()
        raise AssertionError(f"no {text!r} in the output: {''.join(self.out)}")

    def stop(self):
        if self.p.poll() is None:
            self.p.send_signal(signal.SIGINT)          # Ctrl-C
            try:
                self.p.wait(30)
            except subprocess.TimeoutExpired:
                self.p.kill()
                self.p.wait()
        time.sleep(0.2)
        while not self.lines.empty():
            self.out.append(self.lines.get())
        return self.p.returncode


def _get(url, token=None):
    req = urllib.request.Request(url, headers={"X-Studio-Token": token} if token else {})
    try:
        with urllib.request.urlopen(req, timeout=30) as r:
            return r.status
    except urllib.error.HTTPError as exc:
        return exc.code


def _up(port, timeout=60.0):
    """Wait until the server accepts connections (it prints the URL just before it listens)."""
    t0 = time.time()
    while time.time() - t0 < timeout:
        try:
            socket.create_connection(("127.0.0.1", port), timeout=2).close()
            return
        except OSError:
            time.sleep(0.2)
    raise AssertionError(f"nothing listens on port {port}")


def _port():
    from mifacerf.studio.server import free_port

    return free_port("127.0.0.1", 19100 + int(time.time() * 10) % 500, 50)


def _outward_address():
    """This machine's address on its outward interface, or None (no network, or only loopback)."""
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        s.connect(("192.0.2.1", 9))                    # TEST-NET: nothing is sent, only a route chosen
        a = s.getsockname()[0]
    except OSError:
        return None
    finally:
        s.close()
    return None if a.startswith("127.") else a


@pytest.mark.slow
def test_the_command_prints_the_url_serves_loopback_only_and_stops_on_ctrl_c(capture):
    port = _port()
    s = Started(capture, "--port", port)
    try:
        url = s.wait_for("open  http://").split()[-1]
        assert url.startswith(f"http://127.0.0.1:{port}/?token=")
        token = url.split("token=")[1]
        assert len(token) >= 24
        base = f"http://127.0.0.1:{port}"
        _up(port)
        assert _get(base + "/") == 200
        assert _get(base + "/api/session") == 401
        assert _get(base + "/api/session", token) == 200
        assert _get(f"http://localhost:{port}/api/session", token) == 200
        out = _outward_address()
        if out is not None:              # not reachable on this machine's other address
            with pytest.raises(OSError):
                socket.create_connection((out, port), timeout=3).close()
    finally:
        rc = s.stop()
    assert rc == 0, "".join(s.out)
    assert "Traceback" not in "".join(s.out)
    with pytest.raises(OSError):         # the port is free again
        socket.create_connection(("127.0.0.1", port), timeout=3).close()


@pytest.mark.slow
def test_a_port_in_use_takes_the_next_free_one_or_fails_in_one_line(capture):
    busy = socket.socket()
    busy.bind(("127.0.0.1", _port()))
    busy.listen()
    port = busy.getsockname()[1]
    try:
        s = Started(capture, "--port", port)
        try:
            said = s.wait_for("in use")
            url = s.wait_for("open  http://").split()[-1]
            nxt = int(url.split(":")[2].split("/")[0])
            assert f"port {port} is in use; using {nxt}" in said and nxt != port
            _up(nxt)
            assert _get(url.replace("/?token=", "/api/session?token=")) == 200
        finally:
            assert s.stop() == 0
        r = subprocess.run([EXE, "studio", str(capture), "--port", str(port), "--strict-port"],
                           capture_output=True, text=True, timeout=120)
        assert r.returncode == 1
        err = r.stderr.strip().splitlines()
        assert len(err) == 1 and f"port {port}" in err[0] and "in use" in err[0] and "--port" in err[0]
    finally:
        busy.close()


def test_another_address_only_when_asked_and_warned(capture, monkeypatch):
    """The default binds 127.0.0.1 without a warning; ``--host`` anything else warns (uvicorn not started)."""
    import uvicorn

    from mifacerf.studio.server import serve

    ran = []
    monkeypatch.setattr(uvicorn, "run", lambda app, host, port, **k: ran.append((host, port)))
    said = []

    def echo(msg, file=None):
        said.append((msg, file))
    serve(capture, port=_port(), echo=echo)
    assert ran[-1][0] == "127.0.0.1" and not [m for m, _ in said if "WARNING" in m]
    from click.testing import CliRunner

    from mifacerf.studio.cli import studio_cmd

    said.clear()
    serve(capture, host="0.0.0.0", port=_port(), echo=echo)
    assert ran[-1][0] == "0.0.0.0"
    warn = [(m, f) for m, f in said if "WARNING" in m]
    assert len(warn) == 1 and warn[0][1] is sys.stderr and "not the loopback address" in warn[0][0]
    r = CliRunner().invoke(studio_cmd, [str(capture), "--port", str(_port())])
    assert r.exit_code == 0 and ran[-1][0] == "127.0.0.1"
