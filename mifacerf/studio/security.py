"""What keeps the studio's local web server from being used by anything but the user's own tab.

A server that can rewrite a capture is an attack surface; every request passes :class:`Guard`:

* **Host** must be the address the server is bound to (``127.0.0.1:PORT``, ``localhost:PORT``, or the
  ``--host`` given) — a page on another site that re-points its own DNS name at 127.0.0.1 (DNS
  rebinding) sends its own name as Host and is refused (421).
* **Origin**, when the browser sends one, must be this server's own origin — a cross-site form or
  ``fetch`` posting edits is refused (403).
* **Token**: every ``/api/`` request carries the random per-launch token printed in the start URL
  (header ``X-Studio-Token``, or ``?token=`` for images an ``<img>`` loads) — 401 otherwise.
  Another page in the same browser cannot read it.
* Files are served only from inside the capture folder (:func:`safe_path`): absolute paths, ``..``,
  and symlinks resolving outside are refused.

Responses carry ``Content-Security-Policy: default-src 'self'``, ``X-Frame-Options: DENY`` (no
framing: no clickjacking), ``Referrer-Policy: no-referrer`` and ``X-Content-Type-Options: nosniff``.
"""
from __future__ import annotations

import hmac
import secrets
from pathlib import Path, PurePosixPath
from urllib.parse import parse_qs

from starlette.responses import PlainTextResponse

TOKEN_HEADER = "x-studio-token"
SECURITY_HEADERS = [
    (b"content-security-policy", b"default-src 'self'; img-src 'self' data: blob:; frame-ancestors 'none'"),
    (b"x-frame-options", b"DENY"),
    (b"referrer-policy", b"no-referrer"),
    (b"x-content-type-options", b"nosniff"),
    (b"cross-origin-resource-policy", b"same-origin"),
]


def new_token() -> str:
    return secrets.token_urlsafe(24)


class UnsafePath(ValueError):
    """A path that would leave the folder it must stay in."""


def safe_path(root: str | Path, rel: str) -> Path:
    """``root / rel`` resolved, refusing absolute paths, ``..`` components, NUL bytes, backslashes and
    anything (a symlink included) that resolves outside ``root``."""
    if not isinstance(rel, str) or not rel or "\x00" in rel or "\\" in rel:
        raise UnsafePath(f"bad path {rel!r}")
    p = PurePosixPath(rel)
    if p.is_absolute() or rel.startswith("~") or any(part in ("..", "") for part in rel.split("/")) \
            or (len(rel) > 1 and rel[1] == ":"):
        raise UnsafePath(f"path {rel!r} leaves the folder")
    base = Path(root).resolve()
    full = (base / p).resolve()
    if full != base and base not in full.parents:
        raise UnsafePath(f"path {rel!r} resolves outside the folder")
    return full


def allowed_hosts(host: str, port: int) -> set[str]:
    names = {host}
    if host in ("127.0.0.1", "localhost"):
        names |= {"127.0.0.1", "localhost"}
    if host == "::1":
        names |= {"[::1]"}
    if host in ("0.0.0.0", "::"):          # every interface: the names this machine is reached by
        import socket

        names |= {"127.0.0.1", "localhost", socket.gethostname()}
    out = set()
    for n in names:
        out.add(f"{n}:{port}".lower())
        if port == 80:
            out.add(n.lower())
    return out


class Guard:
    """ASGI middleware: Host, Origin and token checks (module docstring), security headers."""

    def __init__(self, app, token: str, hosts: set[str], open_paths=("/", "/static/")):
        self.app = app
        self.token = token
        self.hosts = {h.lower() for h in hosts}
        self.open_paths = open_paths

    def _origin_ok(self, origin: str) -> bool:
        if origin in ("", "null"):
            return origin == ""
        for scheme in ("http://", "https://"):
            if origin.lower().startswith(scheme) and origin[len(scheme):].lower() in self.hosts:
                return True
        return False

    async def __call__(self, scope, receive, send):
        if scope["type"] not in ("http", "websocket"):
            return await self.app(scope, receive, send)
        headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope.get("headers", [])}
        path = scope.get("path", "/")
        reply = None
        if headers.get("host", "").lower() not in self.hosts:
            reply = PlainTextResponse("refused: unexpected Host header (DNS rebinding protection)", 421)
        elif "origin" in headers and not self._origin_ok(headers["origin"]):
            reply = PlainTextResponse("refused: cross-origin request", 403)
        elif (scope["type"] == "http" and headers.get("sec-fetch-site") == "cross-site"
              and scope.get("method", "GET") not in ("GET", "HEAD")):
            reply = PlainTextResponse("refused: cross-site request", 403)
        elif path.startswith("/api/"):
            given = headers.get(TOKEN_HEADER)
            if given is None:
                q = parse_qs(scope.get("query_string", b"").decode("latin-1"))
                given = (q.get("token") or [None])[0]
            if given is None or not hmac.compare_digest(given.encode(), self.token.encode()):
                reply = PlainTextResponse("refused: missing or wrong studio token (use the URL the server printed)",
                                          401)

        async def send_with_headers(message):
            if message["type"] == "http.response.start":
                message["headers"] = list(message.get("headers", [])) + SECURITY_HEADERS
            await send(message)
        return await (reply or self.app)(scope, receive, send_with_headers)
