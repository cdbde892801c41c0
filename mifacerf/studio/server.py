"""The studio's web server: a Starlette app (:func:`create_app`) run by uvicorn (:func:`serve`).

Routes (all ``/api/`` routes need the per-launch token, :mod:`.security`):

==========================================  ==================================================================
``GET /``                                   the single-page app (``static/index.html``)
``GET /static/<file>``                      its scripts and styles (only files inside ``static/``)
``GET /api/session``                        cameras, expressions (status, counts), the template's structure
``GET /api/expression/<e>``                 the hand state, its version and the overlays' geometry
``PUT /api/expression/<e>/hand``            save the hand state (``{"version", "state"}``; 409 if stale)
``GET /api/image/<e>/<camera>.png``         a view: ``kind``, ``light``, ``exposure``, ``gamma``
``POST /api/triangulate``                   ``{"clicks": {camera: [u, v]}, "depth_from": [x, y, z]?}``
``GET /api/proposals/<e>``                  proposed hand state from the nearest registered expression
``POST /api/proposals/template``            propose a template from the neutral's images (``{"accept": bool}``)
``GET /api/template``                       ``hand/template.json`` for editing, its version, its projections
``PUT /api/template``                       save an edited template (``{"version", "template"}``; 409 if stale)
``POST /api/project``                       ``{"positions": [[x, y, z], ...]}`` → their pixels in every camera
``POST /api/register/<e>``                  register the expression in the background → a job
``GET /api/jobs/<id>``                      the job's state, step and progress
``GET /api/file?path=<relative path>``      a file inside the capture folder (hand inputs, reports)
==========================================  ==================================================================
"""
from __future__ import annotations

import json
import socket
import sys
from pathlib import Path

from starlette.applications import Starlette
from starlette.concurrency import run_in_threadpool
from starlette.responses import FileResponse, JSONResponse, PlainTextResponse, Response
from starlette.routing import Route

from .jobs import Jobs
from .security import Guard, UnsafePath, allowed_hosts, new_token, safe_path
from .session import Conflict, Session, StudioError

STATIC = Path(__file__).parent / "static"


def _err(msg: str, code: int = 400) -> JSONResponse:
    return JSONResponse({"error": str(msg).splitlines()[0] if str(msg) else "error"}, code,
                        headers={"cache-control": "no-store"})


def _json(obj, code: int = 200) -> JSONResponse:
    return JSONResponse(obj, code, headers={"cache-control": "no-store"})


async def _body(request) -> dict:
    try:
        d = json.loads(await request.body() or b"{}")
    except json.JSONDecodeError as exc:
        raise StudioError(f"request body is not JSON ({exc})") from exc
    if not isinstance(d, dict):
        raise StudioError("request body must be a JSON object")
    return d


def create_app(capture: str | Path | Session, token: str, hosts: set[str]) -> Starlette:
    """The ASGI app for one capture. ``hosts``: the Host header values accepted (:func:`.security.allowed_hosts`)."""
    session = capture if isinstance(capture, Session) else Session(capture)
    jobs = Jobs(session)

    def guarded(fn):
        async def handler(request):
            try:
                return await fn(request)
            except Conflict as exc:
                return _json({"error": str(exc), "conflict": True, "current": exc.current, "version": exc.version,
                              "kept": exc.kept}, 409)
            except (StudioError, UnsafePath) as exc:
                return _err(exc, 400)
            except (KeyError, ValueError, TypeError) as exc:
                return _err(f"bad request: {exc}", 400)
            except Exception as exc:  # noqa: BLE001 — the page gets one line, the terminal the trace
                import traceback

                traceback.print_exc()
                return _err(f"server error: {type(exc).__name__}: {exc}", 500)
        return handler

    async def index(request):
        return FileResponse(STATIC / "index.html", headers={"cache-control": "no-store"})

    async def static(request):
        try:
            path = safe_path(STATIC, request.path_params["path"])
        except UnsafePath:
            return PlainTextResponse("not found", 404)
        if not path.is_file():
            return PlainTextResponse("not found", 404)
        return FileResponse(path, headers={"cache-control": "no-store"})

    async def info(request):
        return _json(await run_in_threadpool(session.info))

    async def expression(request):
        name = session.check_expression(request.path_params["name"])

        def work():
            with session.lock:
                return {"name": name, "version": session.version(name), "state": session.hand_state(name),
                        "geometry": session.geometry(name)}
        return _json(await run_in_threadpool(work))

    async def save_hand(request):
        name = session.check_expression(request.path_params["name"])
        d = await _body(request)
        v = await run_in_threadpool(session.save_hand, name, d.get("state") or {}, d.get("version"))
        return _json({"version": v})

    async def image(request):
        p = request.path_params
        q = request.query_params
        try:
            light, exposure, gamma = int(q.get("light", 0)), float(q.get("exposure", 0)), float(q.get("gamma", 2.2))
        except ValueError:
            return _err("light, exposure and gamma must be numbers")
        png = await run_in_threadpool(session.png, p["name"], p["camera"], q.get("kind", "diffuse"), light,
                                      exposure, gamma)
        return Response(png, media_type="image/png", headers={"cache-control": "private, max-age=300"})

    async def triangulate(request):
        d = await _body(request)
        clicks = d.get("clicks") or {}
        if not isinstance(clicks, dict):
            raise StudioError("clicks must be {camera: [u, v]}")
        return _json(await run_in_threadpool(session.triangulate, clicks, d.get("depth_from")))

    async def proposals(request):
        from .proposals import propose_expression

        name = session.check_expression(request.path_params["name"])
        await run_in_threadpool(session.require_images, name)
        return _json(await run_in_threadpool(propose_expression, session, name))

    async def template_proposal(request):
        from .template_proposal import propose_template

        d = await _body(request)
        await run_in_threadpool(session.require_images, session.neutral)
        res = await run_in_threadpool(propose_template, session)
        if d.get("accept") and res.get("template") is not None:
            await run_in_threadpool(session.save_template, res["template"])
            res["accepted"] = True
        return _json(res)

    async def template_get(request):
        return _json(await run_in_threadpool(session.template_for_editing))

    async def template_put(request):
        d = await _body(request)
        res = await run_in_threadpool(session.save_template_edit, d.get("template"), d.get("version"),
                                      d.get("renumber"))
        return _json(res)

    async def project(request):
        d = await _body(request)
        return _json(await run_in_threadpool(session.project_all, d.get("positions") or []))

    async def register(request):
        name = session.check_expression(request.path_params["name"])
        if session.template() is None:
            raise StudioError("no usable hand/template.json: build or accept a template on the neutral first")
        await run_in_threadpool(session.require_images, name)
        if name != session.neutral and session.registered(session.neutral) is None:
            await run_in_threadpool(session.require_images, session.neutral)
        return _json(jobs.submit(name), 202)

    async def job(request):
        j = jobs.get(request.path_params["id"])
        return _json(j) if j is not None else _err("no such job", 404)

    async def file(request):
        rel = request.query_params.get("path", "")
        path = safe_path(session.root, rel)
        if rel.split("/")[0] == "truth" or not path.is_file():
            return _err("not found", 404)
        return FileResponse(path, headers={"cache-control": "no-store"})

    routes = [
        Route("/", index),
        Route("/static/{path:path}", static),
        Route("/favicon.ico", lambda request: Response(status_code=204)),
        Route("/api/session", guarded(info)),
        Route("/api/expression/{name}", guarded(expression)),
        Route("/api/expression/{name}/hand", guarded(save_hand), methods=["PUT", "POST"]),
        Route("/api/image/{name}/{camera}.png", guarded(image)),
        Route("/api/triangulate", guarded(triangulate), methods=["POST"]),
        Route("/api/proposals/template", guarded(template_proposal), methods=["POST"]),
        Route("/api/proposals/{name}", guarded(proposals)),
        Route("/api/template", guarded(template_get)),
        Route("/api/template", guarded(template_put), methods=["PUT"]),
        Route("/api/project", guarded(project), methods=["POST"]),
        Route("/api/register/{name}", guarded(register), methods=["POST"]),
        Route("/api/jobs/{id}", guarded(job)),
        Route("/api/file", guarded(file)),
    ]
    app = Starlette(routes=routes)
    app.state.session = session
    app.state.jobs = jobs
    return Guard(app, token, hosts)


def free_port(host: str, port: int, tries: int = 20) -> int | None:
    """``port`` if it can be bound on ``host``, else the next free one among ``tries``; None if none."""
    for p in range(port, port + tries):
        with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET, socket.SOCK_STREAM) as s:
            try:
                s.bind((host, p))
                return p
            except OSError:
                continue
    return None


def serve(capture: str | Path, host: str = "127.0.0.1", port: int = 8765, token: str | None = None,
          next_free: bool = True, echo=print) -> None:
    """Run the studio until Ctrl-C. Raises :class:`StudioError` (one line) when it cannot start."""
    import uvicorn

    session = Session(capture)
    if host not in ("127.0.0.1", "localhost", "::1"):
        echo(f"WARNING: serving on {host}, not the loopback address: anyone who can reach this machine and "
             "learns the URL can edit this capture", file=sys.stderr)
    chosen = free_port(host, port, 20 if next_free else 1)
    if chosen is None:
        raise StudioError(f"port {port} on {host} is in use" + (" (and the next 19)" if next_free else "")
                          + "; choose another with --port")
    if chosen != port:
        echo(f"port {port} is in use; using {chosen}")
    token = token or new_token()
    app = create_app(session, token, allowed_hosts(host, chosen))
    shown = "127.0.0.1" if host in ("0.0.0.0", "::") else host
    echo(f"mifacerf studio: {session.root}")
    echo(f"open  http://{shown if ':' not in shown else f'[{shown}]'}:{chosen}/?token={token}")
    echo("Ctrl-C stops the server")
    uvicorn.run(app, host=host, port=chosen, log_level="warning")
