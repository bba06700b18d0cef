"""The HTTP face of ``lasagna serve``: a Starlette app over one ``EditSession``.

Security (the editor can read and write a folder of the user's, so every request is checked):

* **Token.** Every request carries the random token printed in the URL: the ``X-Lasagna-Token`` header,
  the ``token`` query parameter, or the ``lasagna_token`` cookie the page sets (HttpOnly, SameSite=Strict).
  Compared in constant time. Without it: 403, one line.
* **Host.** The Host header must name this server (``127.0.0.1:PORT``, ``localhost:PORT``, …): a page on
  another site that rebinds its DNS name to 127.0.0.1 still sends its own name, and is refused (DNS
  rebinding).
* **Origin.** A state-changing request (POST) that carries an Origin must come from this server's
  origin; browsers send Origin on every cross-site POST.
* **Paths.** No route takes a path: the session knows its folder, layers are named by id, exports are
  downloads built in memory. Uploads are bytes, read under the CLI's image policy (size and pixel limits).
* **Slow requests.** A body must arrive within ``HttpLimits`` (pauses and a deadline: 408, the connection
  closed) and all bodies in flight share one byte budget (429); request heads and connections are bounded in
  ``lasagna.serve.server``.
* **Errors.** A ``LasagnaError`` is a 4xx with ``{"error": "<one line>"}`` (409 for a version conflict,
  413 for an oversized body); a malformed request is a 400 naming the field, what it expected and what it
  was given: bodies are parsed with bounded depth and digits and validated by strict models in one place
  (``lasagna.serve.bodies``) before any session method runs. Anything unexpected is a 500 whose body is one
  line without a traceback.
"""

from __future__ import annotations

import asyncio
import json
import secrets
import time
from dataclasses import dataclass
from importlib import resources
from typing import Any
from urllib.parse import quote

from starlette.applications import Starlette
from starlette.exceptions import HTTPException
from starlette.requests import ClientDisconnect, Request
from starlette.responses import JSONResponse, Response, StreamingResponse
from starlette.routing import Route

from lasagna.document.condition import NAMED_DIRECTIONS
from lasagna.errors import ConflictError, LasagnaError
from lasagna.limits import BudgetError
from lasagna.serve.bodies import Empty, RequestError, StartJob, parse_body, parse_change, parse_request_json
from lasagna.serve.session import EditSession
from lasagna.version import install_hint

TOKEN_HEADER = "x-lasagna-token"
TOKEN_COOKIE = "lasagna_token"
MAX_JSON_BYTES = 1 * 2**20
"""A change is a few hundred bytes of JSON; 1 MiB leaves room for long names and still refuses floods."""
MAX_UPLOAD_BYTES = 64 * 2**20
"""An uploaded image file (before decoding; the pixel limit is the CLI's ``--max-pixels``)."""
EVENT_INTERVAL_S = 0.1
"""How often a job's progress stream reports (10 Hz: smooth for a bar, negligible work)."""
STATIC_FILES = {"app.js": "text/javascript", "app.css": "text/css"}


class TooLarge(LasagnaError):
    """A request body over its limit: HTTP 413."""


def request_line(exc: HTTPException) -> str:
    if exc.status_code == 404:
        return "no such page or API route; expected one of the editor's routes (lasagna.serve.app)"
    return str(exc.detail)


def _error(status: int, message: str) -> JSONResponse:
    return JSONResponse({"error": " ".join(str(message).split())}, status_code=status)


def _static(name: str) -> bytes:
    return resources.files("lasagna.serve").joinpath("static", name).read_bytes()


class RequestTimeout(LasagnaError):
    """A request body that did not arrive in time: HTTP 408, and the connection is closed."""


class Busy(LasagnaError):
    """More upload bytes in flight than the server holds at once: HTTP 429 (try again)."""


@dataclass(frozen=True)
class HttpLimits:
    """How long a request may take to arrive and how much the server holds while it does (``serve`` and the
    app share them; ``lasagna.serve.server`` applies the connection-level ones)."""

    head_timeout_s: float = 10.0
    """A connection must send a complete request head within this of connecting (or of its last response)."""
    body_idle_s: float = 10.0
    """A body may pause this long between chunks (a browser sends a local file's bytes without pause)."""
    body_deadline_s: float = 120.0
    """A whole body must arrive within this: a 64 MiB upload at ~0.5 MiB/s, far slower than any LAN."""
    max_in_flight_bytes: int = 2 * MAX_UPLOAD_BYTES
    """Body bytes held across all requests at once: two full-size uploads (twelve stalled 60 MiB uploads
    held 750 MB before this bound)."""
    max_connections: int = 1024
    """Open connections at most (lowered to what the file-descriptor limit allows; the oldest connection
    still waiting for a request head is closed to make room)."""
    backlog: int = 128
    keep_alive_s: float = 5.0
    max_head_bytes: int = 64 * 2**10
    """Request line and headers (h11's incomplete-event limit): a long query string of opacity overrides
    fits; a flood does not."""


class BodyReader:
    """Reads request bodies under ``HttpLimits``: a size limit per route, a deadline, and one budget of
    bytes in flight for the whole server."""

    def __init__(self, limits: HttpLimits):
        self.limits = limits
        self.in_flight = 0

    async def read(self, request: Request, limit: int) -> bytes:
        declared = request.headers.get("content-length")
        if declared is not None and declared.isdigit() and int(declared) > limit:
            raise TooLarge(f"the request body is {int(declared)} bytes; expected at most {limit}", "body")
        held = 0
        try:
            if declared is not None and declared.isdigit():
                held = self._take(int(declared))
            chunks, size = [], 0
            deadline = time.monotonic() + self.limits.body_deadline_s
            stream = request.stream()
            while True:
                wait = min(self.limits.body_idle_s, deadline - time.monotonic())
                try:
                    chunk = await asyncio.wait_for(anext(stream), max(wait, 0.0))
                except StopAsyncIteration:
                    break
                except TimeoutError:
                    raise RequestTimeout(
                        f"the request body stopped after {size} bytes; expected it whole within "
                        f"{self.limits.body_deadline_s:g} s, with pauses under {self.limits.body_idle_s:g} s",
                        "body",
                    ) from None
                size += len(chunk)
                if size > limit:
                    raise TooLarge(f"the request body is over {limit} bytes; expected at most {limit}", "body")
                if size > held:
                    held += self._take(size - held)
                chunks.append(chunk)
            return b"".join(chunks)
        finally:
            self.in_flight -= held

    def _take(self, n: int) -> int:
        if self.in_flight + n > self.limits.max_in_flight_bytes:
            raise Busy(
                f"{self.in_flight} bytes of other requests are arriving; expected at most "
                f"{self.limits.max_in_flight_bytes} at once: try again when they are in",
                "body",
            )
        self.in_flight += n
        return n


def _attachment(name: str) -> str:
    """A download's Content-Disposition: an ASCII ``filename`` (headers are Latin-1) and the real, possibly
    Unicode, name as ``filename*`` (RFC 6266 / RFC 5987), which every current browser prefers."""
    fallback = "".join(c if c.isascii() and c.isprintable() and c not in '"\\' else "_" for c in name)
    if fallback == name:
        return f'attachment; filename="{name}"'
    return f"attachment; filename=\"{fallback}\"; filename*=UTF-8''{quote(name, safe='')}"


def create_app(session: EditSession, token: str, allowed_hosts: list[str], limits: HttpLimits = HttpLimits()) -> Guard:
    """The editor's app for ``session``; ``allowed_hosts`` are the Host header values that name this server
    (``host:port``); its origins are ``http://`` + each."""
    bodies = BodyReader(limits)

    async def _json(request: Request) -> dict[str, Any]:
        """The body as a JSON object, bounded in size, depth and digits (``bodies.parse_request_json``)."""
        return parse_request_json(await bodies.read(request, MAX_JSON_BYTES))

    async def run(fn, *args, **kwargs):
        """Session work off the event loop (it is CPU-bound torch): the loop keeps serving progress streams."""
        return await asyncio.to_thread(fn, *args, **kwargs)

    # ---- pages -------------------------------------------------------------------------------------

    async def index(request: Request) -> Response:
        page = _static("index.html")
        response = Response(page, media_type="text/html; charset=utf-8")
        response.set_cookie(TOKEN_COOKIE, token, httponly=True, samesite="strict")
        response.headers["Cache-Control"] = "no-store"
        return response

    async def static(request: Request) -> Response:
        name = request.path_params["name"]
        if name not in STATIC_FILES:
            return _error(404, f"no static file {name!r}; expected one of {', '.join(STATIC_FILES)}")
        return Response(_static(name), media_type=STATIC_FILES[name])

    # ---- reading -----------------------------------------------------------------------------------

    async def state(request: Request) -> Response:
        return JSONResponse(await run(session.state))

    async def presets(request: Request) -> Response:
        # The named lights with the presets: the compass draws a vocabulary of them (NAMED_DIRECTIONS, the one list).
        lights = {name: {"az": az, "el": el} for name, (az, el) in NAMED_DIRECTIONS.items()}
        return JSONResponse({"presets": await run(session.presets), "lights": lights})

    def _view_args(request: Request) -> dict[str, Any]:
        q = request.query_params
        try:
            level = int(q.get("level", "0"))
        except ValueError:
            raise RequestError(f"level is {q.get('level')!r}; expected an integer", "level") from None
        # Numeric overrides, LAYER:NUMBER each: an opacity slider's, a surface layer's relief, ambient, intensity,
        # gloss, shadows, shadow depth or occlusion slider's.
        numbers: dict[str, dict[str, float]] = {
            "opacity": {},
            "relief": {},
            "ambient": {},
            "intensity": {},
            "gloss": {},
            "shadows": {},
            "occlusion": {},
            "shadow_depth": {},
        }
        for name, given in numbers.items():
            for item in q.getlist(name):
                id, sep, value = item.rpartition(":")
                try:
                    given[id] = float(value)
                except ValueError:
                    sep = ""
                if not sep:
                    raise RequestError(f"{name} is {item!r}; expected LAYER:NUMBER", name)
        colours: dict[str, tuple[float, float, float]] = {}
        for item in q.getlist("color"):  # a surface layer's light colour while its picker is open: LAYER:#rrggbb
            id, sep, value = item.rpartition(":")
            if (
                not sep
                or len(value) != 7
                or value[0] != "#"
                or not all(c in "0123456789abcdef" for c in value[1:].lower())
            ):
                raise RequestError(f"color is {item!r}; expected LAYER:#rrggbb", "color")
            colours[id] = tuple(int(value[k : k + 2], 16) / 255.0 for k in (1, 3, 5))
        lights: dict[str, dict[str, str]] = {"light": {}, "source": {}}
        for name, given in lights.items():
            for item in q.getlist(name):  # a light's text holds no ':' (nor does an id)
                id, sep, text = item.partition(":")
                if not sep:
                    raise RequestError(
                        f"{name} is {item!r}; expected LAYER:LIGHT (a named light, az=A,el=E or x=X,y=Y,z=Z)", name
                    )
                given[id] = text
        return {
            "level": level,
            "opacity": numbers["opacity"],
            "light": lights["light"],
            "source": lights["source"],
            "relief": numbers["relief"],
            "ambient": numbers["ambient"],
            "color": colours,
            "intensity": numbers["intensity"],
            "gloss": numbers["gloss"],
            "shadows": numbers["shadows"],
            "occlusion": numbers["occlusion"],
            "shadow_depth": numbers["shadow_depth"],
            "solo": q.get("solo") or None,
            "upto": q.get("upto") or None,
        }

    async def view(request: Request) -> Response:
        args = _view_args(request)
        return _pixels(*await run(session.view, args.pop("level"), **args))

    def _pixels(data: bytes, w: int, h: int) -> Response:
        """A view's RGBA8 bytes, its size in headers (the page draws them with ``putImageData``)."""
        return Response(
            data,
            media_type="application/octet-stream",
            headers={"X-Width": str(w), "X-Height": str(h), "Cache-Control": "no-store"},
        )

    async def normal_map(request: Request) -> Response:
        level = _view_args(request)["level"]
        return _pixels(*await run(session.normal_map, request.path_params["id"], level))

    async def occlusion_map(request: Request) -> Response:
        level = _view_args(request)["level"]
        return _pixels(*await run(session.occlusion_map, request.path_params["id"], level))

    async def thumbnail(request: Request) -> Response:
        data = await run(session.thumbnail, request.path_params["id"])
        return Response(data, media_type="image/png", headers={"Cache-Control": "no-store"})

    async def export(request: Request) -> Response:
        q = request.query_params
        directx = q.get("directx", "0")
        if directx not in ("0", "1"):
            raise RequestError(f"directx is {directx!r}; expected 0 or 1", "directx")
        data, name, media = await run(session.export, request.path_params["kind"], q.get("id"), directx == "1")
        return Response(data, media_type=media, headers={"Content-Disposition": _attachment(name)})

    # ---- changes -----------------------------------------------------------------------------------

    async def change(request: Request) -> Response:
        body = parse_change(await _json(request))  # one model per op (lasagna.serve.bodies.CHANGES)
        return JSONResponse(await run(body.call, session))

    async def upload(request: Request) -> Response:
        q = request.query_params
        try:
            version = int(q.get("version", ""))
        except ValueError:
            raise RequestError("expected ?version=N, the version the upload is added to", "version") from None
        data = await bodies.read(request, MAX_UPLOAD_BYTES)
        if not data:
            raise RequestError("the upload is empty; expected an image file's bytes as the body", "body")
        kind = q.get("kind", "image")
        if kind == "normal-map":  # a normal map of one's own: a surface layer (``?directx=1``: +Y down)
            directx = q.get("directx", "0")
            if directx not in ("0", "1"):
                raise RequestError(f"directx is {directx!r}; expected 0 or 1", "directx")
            height = None
            if q.get("height"):  # a grey height map instead: white ``height`` pixels above black
                try:
                    height = float(q["height"])
                except ValueError:
                    raise RequestError(f"height is {q['height']!r}; expected a number of pixels", "height") from None
            args = (version, data, q.get("name"), directx == "1", height)
            return JSONResponse(await run(session.add_normal_map, *args))
        if kind != "image":
            raise RequestError(f"kind is {kind!r}; expected image or normal-map", "kind")
        return JSONResponse(await run(session.add_image, version, data, q.get("name")))

    async def reload(request: Request) -> Response:
        parse_body(Empty, await _json(request))
        return JSONResponse(await run(session.reload))

    async def start_job(request: Request) -> Response:
        body = parse_body(StartJob, await _json(request))
        job = await run(session.start_job, body.version, body.kind, body.id, body.steps)
        return JSONResponse(job.report())

    async def cancel_job(request: Request) -> Response:
        parse_body(Empty, await _json(request))
        return JSONResponse(await run(session.cancel_job, request.path_params["job"]))

    async def job_events(request: Request) -> Response:
        job = session.jobs.get(request.path_params["job"])
        if job is None:
            return _error(404, f"no job {request.path_params['job']!r}; expected the id a job was started with")

        async def events():
            last = None
            while True:
                report = job.report()
                key = (report["step"], report["state"])
                if key != last:
                    yield f"data: {json.dumps(report)}\n\n"
                    last = key
                if report["state"] != "running":
                    return
                await asyncio.sleep(EVENT_INTERVAL_S)

        return StreamingResponse(events(), media_type="text/event-stream", headers={"Cache-Control": "no-store"})

    async def favicon(request: Request) -> Response:
        return Response(status_code=204)

    routes = [
        Route("/", index),
        Route("/favicon.ico", favicon),
        Route("/static/{name}", static),
        Route("/api/state", state),
        Route("/api/presets", presets),
        Route("/api/view", view),
        Route("/api/layers/{id}/thumb.png", thumbnail),
        Route("/api/layers/{id}/normals", normal_map),
        Route("/api/layers/{id}/occlusion", occlusion_map),
        Route("/api/export/{kind}", export),
        Route("/api/change", change, methods=["POST"]),
        Route("/api/upload", upload, methods=["POST"]),
        Route("/api/reload", reload, methods=["POST"]),
        Route("/api/jobs", start_job, methods=["POST"]),
        Route("/api/jobs/{job}/cancel", cancel_job, methods=["POST"]),
        Route("/api/jobs/{job}/events", job_events),
    ]

    async def on_error(request: Request, exc: Exception) -> Response:
        return _response_for(exc)

    handlers = {HTTPException: on_error, LasagnaError: on_error, Exception: on_error}
    app = Starlette(routes=routes, exception_handlers=handlers)
    return Guard(app, token, allowed_hosts)


class Guard:
    """ASGI wrapper: the Host, token, Origin and method checks (module docstring) before any route."""

    def __init__(self, app, token: str, allowed_hosts: list[str]):
        self.app = app
        self.token = token.encode()
        self.allowed_hosts = list(allowed_hosts)
        self.origins = {f"http://{h}" for h in allowed_hosts}

    async def __call__(self, scope, receive, send) -> None:
        if scope["type"] == "http":
            refusal = self.check(Request(scope))
            if refusal is not None:
                await refusal(scope, receive, send)
                return
        await self.app(scope, receive, send)

    def check(self, request: Request) -> Response | None:
        host = request.headers.get("host", "")
        if host not in self.allowed_hosts:
            return _error(
                403,
                f"Host {host!r} is not this server; expected one of {', '.join(self.allowed_hosts)} "
                "(requests through another name are refused: DNS rebinding)",
            )
        given = (
            request.headers.get(TOKEN_HEADER)
            or request.query_params.get("token")
            or request.cookies.get(TOKEN_COOKIE)
            or ""
        )
        if not secrets.compare_digest(given.encode(), self.token):
            return _error(403, "missing or wrong token; expected the URL `lasagna serve` printed (it carries ?token=…)")
        if request.method not in ("GET", "HEAD", "POST"):
            return _error(405, f"method {request.method} is not used here; expected GET or POST")
        if request.method == "POST":
            origin = request.headers.get("origin")
            if origin is not None and origin not in self.origins:
                return _error(403, f"Origin {origin!r} is not this server; expected {', '.join(sorted(self.origins))}")
        return None


def _response_for(exc: Exception) -> Response:
    if isinstance(exc, HTTPException):  # Starlette's own: no such route (404), a method it does not take (405)
        return _error(exc.status_code, f"{request_line(exc)}")
    if isinstance(exc, TooLarge):
        return _error(413, str(exc))
    if isinstance(exc, RequestTimeout):  # the rest of the body may still be arriving: do not wait for it
        response = _error(408, str(exc))
        response.headers["Connection"] = "close"
        return response
    if isinstance(exc, Busy):  # as for 408: the body it refused may still be arriving
        response = _error(429, str(exc))
        response.headers["Retry-After"] = "5"
        response.headers["Connection"] = "close"
        return response
    if isinstance(exc, ClientDisconnect):  # nobody reads this answer; it is one line, not a 500
        return _error(400, "the client closed the connection before its request body was whole")
    if isinstance(exc, ConflictError):
        return _error(409, str(exc))
    if isinstance(exc, BudgetError):
        return _error(413, str(exc))
    if isinstance(exc, LasagnaError):
        return _error(400, str(exc))
    if isinstance(exc, ImportError):
        return _error(501, f"{exc}; expected the optional dependency installed ({install_hint('psd')})")
    return _error(500, f"internal error: {type(exc).__name__}: {exc}; please report it")


__all__ = ["Guard", "HttpLimits", "MAX_JSON_BYTES", "MAX_UPLOAD_BYTES", "create_app"]
