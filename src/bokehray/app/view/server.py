"""The ASGI app of ``bokehray view`` (Starlette on uvicorn) and a server handle.

Endpoints (all answers come from the files given on the command line; the client
never names a path):

- ``GET /`` and ``/static/*``: the page (package data, no external resources).
- ``GET /api/info``: size, proxy and display factors, defaults and ranges.
- ``GET /api/photo.jpg``, ``/api/depth.png``, ``/api/disparity16.png``: computed once.
- ``POST /api/render`` with a JSON parameter set, ``"stage": "preview" | "full"`` and (full) ``"long_side"``,
  the pixels the screen shows: a JPEG, with the focus disparity, K, amount, time and the command line in
  ``X-Bokehray-*`` headers. 409 when a newer request superseded it, 400 with ``{"error": ...}`` for a bad
  parameter, 503 when the server stops.
- ``GET /api/progress``: what the render thread runs now and how far it is.
- ``POST /api/export`` with ``{"params": {...}, "format": "png|jpg|tif|exr", "bit_depth": N}``:
  writes the full-resolution render into the export folder; answers the path and the command.
"""

from __future__ import annotations

import asyncio
import contextlib
import ipaddress
import json
import signal
import socket
import threading
import time
import warnings
from importlib import resources
from typing import Self
from urllib.parse import quote

from ...errors import BokehrayError, InputError
from .session import EXPORT_FORMATS, MAX_BODY_BYTES, ViewSession, json_integer
from .worker import Busy, RenderWorker, Stopped, Superseded

__all__ = ["ViewServer", "create_app"]

_STATIC = {"index.html": "text/html; charset=utf-8", "app.js": "text/javascript; charset=utf-8",
           "style.css": "text/css; charset=utf-8"}
_SECURITY_HEADERS = {
    "Content-Security-Policy": "default-src 'self'; img-src 'self' blob: data:; object-src 'none'; "
                               "frame-ancestors 'none'; base-uri 'none'",
    "X-Content-Type-Options": "nosniff",
    "Cache-Control": "no-store",
}


BODY_TIMEOUT_S = 5.0
"""Seconds a request body (at most 4096 bytes, from this machine) has to arrive; then 408 and the connection closes."""

HEADER_TIMEOUT_S = 10.0
"""Seconds a connection has, from its opening or from its previous response, to finish its next request's headers
(a browser sends them in one packet): then half a request is answered 408, and a silent connection is closed.
uvicorn times out nothing before the headers are complete, so 64 stalled connections took every slot of its
``limit_concurrency`` and every other request was answered 503 until they closed."""


def _http_protocol() -> type:  # noqa: C901 - one small class, defined where uvicorn (an extra) is imported
    """uvicorn's h11 protocol with a deadline for the request headers (:data:`HEADER_TIMEOUT_S`).

    uvicorn has ``timeout_keep_alive`` (idle after a response) but no header timeout, and its h11 options limit a
    request's size, not its time. The deadline starts when the connection opens, and again when a response is
    complete (a kept-alive connection's next request: uvicorn's keep-alive timer stops at its first byte); it is
    cancelled once h11 has the whole request line and headers, and never reset by a byte that does not finish them
    (a client trickling a byte a second stays bounded)."""
    import h11
    from uvicorn.protocols.http.h11_impl import H11Protocol

    class _HeaderDeadlineH11(H11Protocol):
        _header_timer: asyncio.TimerHandle | None = None

        def connection_made(self, transport) -> None:
            super().connection_made(transport)
            self._watch_headers()

        def data_received(self, data: bytes) -> None:
            super().data_received(data)
            self._watch_headers()

        def on_response_complete(self) -> None:
            super().on_response_complete()
            self._watch_headers()

        def connection_lost(self, exc: Exception | None) -> None:
            self._stop_header_timer()
            super().connection_lost(exc)

        def _stop_header_timer(self) -> None:
            if self._header_timer is not None:
                self._header_timer.cancel()
                self._header_timer = None

        def _waiting_for_headers(self) -> bool:
            return self.conn.their_state is h11.IDLE and not self.transport.is_closing()

        def _watch_headers(self) -> None:
            if not self._waiting_for_headers():
                self._stop_header_timer()
            elif self._header_timer is None:
                self._header_timer = self.loop.call_later(HEADER_TIMEOUT_S, self._headers_timed_out)

        def _headers_timed_out(self) -> None:
            self._header_timer = None
            if not self._waiting_for_headers():
                return
            if self.conn.trailing_data[0]:  # half a request: say why it ends
                body = json.dumps({"error": f"request headers: not all of them arrived within {HEADER_TIMEOUT_S:g} "
                                            "s"}).encode()
                self.transport.write(b"HTTP/1.1 408 Request Timeout\r\ncontent-type: application/json\r\n"
                                     b"connection: close\r\ncontent-length: %d\r\n\r\n%s" % (len(body), body))
            self.transport.close()

    return _HeaderDeadlineH11


def _static(name: str) -> bytes:
    return resources.files("bokehray.app.view").joinpath("static", name).read_bytes()


def create_app(session: ViewSession, worker: RenderWorker | None = None, allowed_hosts: tuple[str, ...] = (),  # noqa: C901
               any_address: bool = False):
    """The Starlette app over ``session``; ``worker`` defaults to a new :class:`RenderWorker`. With ``allowed_hosts``
    only requests whose ``Host`` is one of them (or, with ``any_address``, an IP address) are answered."""
    from starlette.applications import Starlette
    from starlette.requests import ClientDisconnect, Request
    from starlette.responses import JSONResponse, Response
    from starlette.routing import Route

    worker = worker or RenderWorker()
    stats = {"requests": 0, "rejected": 0}

    def error(status: int, message: str) -> JSONResponse:
        stats["rejected"] += status >= 400 and status != 409
        headers = {**_SECURITY_HEADERS, "Connection": "close"} if status == 408 else _SECURITY_HEADERS
        return JSONResponse({"error": message}, status_code=status, headers=headers)

    def blob(data: bytes, media: str, headers: dict | None = None) -> Response:
        return Response(data, media_type=media, headers={**_SECURITY_HEADERS, **(headers or {})})

    async def read_json(request: Request):
        # A page of another site can make the browser POST here ("simple" requests need no CORS preflight),
        # but not with a JSON content type, and the browser names its origin: both are checked.
        if request.headers.get("content-type", "").split(";")[0].strip().lower() != "application/json":
            raise _Refused(415, "request body: expected Content-Type: application/json")
        origin = request.headers.get("origin")
        if origin is not None and origin != f"{request.url.scheme}://{request.headers.get('host', '')}":
            raise _Refused(403, f"request from another origin ({origin}) refused")
        declared = request.headers.get("content-length")
        if declared is not None and (not declared.isdigit() or int(declared) > MAX_BODY_BYTES):
            raise _TooLarge()
        body = b""
        try:
            # a body that stops half-way held a connection slot for good, and held up Ctrl-C until uvicorn cancelled
            # the handler (a traceback): it has BODY_TIMEOUT_S to arrive
            async with asyncio.timeout(BODY_TIMEOUT_S):
                async for chunk in request.stream():
                    body += chunk
                    if len(body) > MAX_BODY_BYTES:
                        raise _TooLarge()
        except ClientDisconnect:  # the answer goes nowhere, but it is an answer: no traceback on the console
            raise _Refused(400, "request body: the client disconnected before sending all of it") from None
        except TimeoutError:
            raise _Refused(408, f"request body: not all of it arrived within {BODY_TIMEOUT_S:g} s") from None
        try:
            return json.loads(body)
        except (ValueError, UnicodeDecodeError) as e:
            raise InputError(f"request body: expected JSON ({e})") from None
        except RecursionError:  # nested deeper than Python's parser goes (1000 levels fit in the 4096 bytes)
            raise InputError("request body: JSON nested too deeply") from None

    async def page(request: Request) -> Response:
        return blob(_static("index.html"), _STATIC["index.html"])

    async def static(request: Request) -> Response:
        name = request.path_params["name"]
        if name not in _STATIC:  # a fixed list: no path from the client reaches the file system
            return error(404, f"no such file: {name!r}")
        return blob(_static(name), _STATIC[name])

    async def info(request: Request) -> Response:
        return JSONResponse(session.info(), headers=_SECURITY_HEADERS)

    async def photo(request: Request) -> Response:
        return blob(await asyncio.to_thread(session.photo_jpeg), "image/jpeg")

    async def depth(request: Request) -> Response:
        return blob(await asyncio.to_thread(session.depth_png), "image/png")

    async def disparity16(request: Request) -> Response:
        return blob(await asyncio.to_thread(session.disparity16_png), "image/png")

    async def render(request: Request) -> Response:  # noqa: C901
        stats["requests"] += 1
        try:
            body = await read_json(request)
            p = session.parse(body)
            stage = body.get("stage", "preview")
            if not isinstance(stage, str) or stage not in ("preview", "focus", "full"):
                raise InputError(f"stage: expected 'preview', 'focus' or 'full', got {stage!r}"[:200])
            command = session.shown_command(p, body)  # -o OUTPUT.<the export's format>
            long_side = body.get("long_side")
            if long_side is not None:
                long_side = json_integer(long_side, "long_side")
                if long_side < 16:
                    raise InputError(f"long_side: expected at least 16 pixels, got {long_side}")
        except _TooLarge:
            return error(413, f"request body: larger than {MAX_BODY_BYTES} bytes")
        except _Refused as e:
            return error(e.status, str(e))
        except BokehrayError as e:
            return error(400, str(e))
        t0 = time.perf_counter()

        def job(check):
            t_start = time.perf_counter()
            if stage == "preview":
                data, meta = session.render_preview(p, check)
            elif stage == "focus":  # the focused region at screen size, before the whole frame
                data, meta = session.focus_crop(p, check, long_side)
            else:
                data, meta = session.full_display(p, check, long_side)
            return data, meta, time.perf_counter() - t_start

        try:
            data, meta, seconds = await asyncio.wrap_future(worker.submit(job, "preview" if stage == "preview" else "full"))
        except Superseded:
            return JSONResponse({"superseded": True}, status_code=409, headers=_SECURITY_HEADERS)
        except Stopped:
            return error(503, "the server is stopping")
        except BokehrayError as e:
            return error(400, str(e))
        headers = {
            "X-Bokehray-Stage": stage, "X-Bokehray-Factor": str(meta["factor"]),
            "X-Bokehray-Proxy-Level": str(meta.get("level", "")),
            "X-Bokehray-Focus-Disparity": repr(p.blur.focus_disparity), "X-Bokehray-K": repr(p.blur.k_px),
            "X-Bokehray-Render-Seconds": f"{seconds:.4f}",
            "X-Bokehray-Seconds": f"{time.perf_counter() - t0:.4f}",
            "X-Bokehray-Command": quote(command, safe=""),
            "X-Bokehray-Focus-Words": quote(session.focus_words(p), safe=""),
            "X-Bokehray-Crop": ",".join(map(str, meta.get("crop", ()))),
            "X-Bokehray-Amount": "" if p.amount is None else repr(p.amount),
            "X-Bokehray-Focus-M": "" if session.norm is None else repr(float(session.norm.depth(p.blur.focus_disparity))),
        }
        return blob(data, "image/jpeg", headers)

    async def export(request: Request) -> Response:  # noqa: C901
        try:
            body = await read_json(request)
            if not isinstance(body, dict) or set(body) - {"params", "format", "bit_depth"}:
                raise InputError("export: expected {\"params\": {...}, \"format\": ..., \"bit_depth\": ...}")
            p = session.parse(body.get("params", {}))
            fmt = body.get("format", "png")
            if not isinstance(fmt, str) or fmt not in EXPORT_FORMATS:
                raise InputError(f"export format: expected one of {', '.join(EXPORT_FORMATS)}, got {fmt!r}"[:200])
            bits = body.get("bit_depth")
            if bits is not None and (isinstance(bits, bool) or not isinstance(bits, int)
                                     or bits not in EXPORT_FORMATS[fmt]):
                raise InputError(f"argument --bit-depth: {fmt} takes {', '.join(map(str, EXPORT_FORMATS[fmt]))}, "
                                 f"got {bits!r}"[:200])
            fut = worker.submit_export(lambda check: session.export(p, fmt, bits, check))
        except _TooLarge:
            return error(413, f"request body: larger than {MAX_BODY_BYTES} bytes")
        except _Refused as e:
            return error(e.status, str(e))
        except Busy as e:
            return error(429, str(e))
        except Stopped:
            return error(503, "the server is stopping")
        except BokehrayError as e:
            return error(400, str(e))
        t0 = time.perf_counter()
        try:
            path, command = await asyncio.wrap_future(fut)
        except Stopped:
            return error(503, "export abandoned: the server is stopping")
        except BokehrayError as e:
            return error(400, str(e))
        except OSError as e:
            return error(500, f"export: {e}")
        return JSONResponse({"path": str(path), "command": command, "seconds": round(time.perf_counter() - t0, 3)},
                            headers=_SECURITY_HEADERS)

    async def progress(request: Request) -> Response:
        return JSONResponse(worker.progress(), headers=_SECURITY_HEADERS)

    async def status(request: Request) -> Response:
        return JSONResponse({"worker": dict(worker.counts), "queued": worker.queued(), **stats},
                            headers=_SECURITY_HEADERS)

    routes = [
        Route("/", page), Route("/static/{name}", static), Route("/api/info", info),
        Route("/api/photo.jpg", photo), Route("/api/depth.png", depth), Route("/api/disparity16.png", disparity16),
        Route("/api/render", render, methods=["POST"]), Route("/api/export", export, methods=["POST"]),
        Route("/api/status", status), Route("/api/progress", progress),
    ]
    middleware = []
    if allowed_hosts:
        # a page on another site cannot reach this server through DNS rebinding: the Host must be ours
        from starlette.middleware import Middleware

        middleware.append(Middleware(_HostCheck, names=allowed_hosts, addresses=any_address))
    app = Starlette(routes=routes, middleware=middleware)
    app.state.worker = worker
    app.state.stats = stats
    return app


def _host_name(host: str) -> str:
    """The name or address of a ``Host`` header: lower case, without the port or an IPv6 address's brackets."""
    host = host.strip().lower()
    return host[1:].partition("]")[0] if host.startswith("[") else host.partition(":")[0]


class _HostCheck:
    """Answers only requests whose ``Host`` is one of ``names`` or, with ``addresses``, an IP address: a page of another
    site reaches this server through DNS rebinding only under a name of its own, and an address cannot be rebound."""

    def __init__(self, app, names: tuple[str, ...], addresses: bool = False) -> None:
        self.app, self.names, self.addresses = app, {_host_name(n) for n in names}, addresses

    def allowed(self, host: str) -> bool:
        name = _host_name(host)
        if name in self.names:
            return True
        if not self.addresses:
            return False
        try:
            ipaddress.ip_address(name)
        except ValueError:
            return False
        return True

    async def __call__(self, scope, receive, send) -> None:
        if scope["type"] == "http":
            host = dict(scope["headers"]).get(b"host", b"").decode("latin-1")
            if not self.allowed(host):
                from starlette.responses import JSONResponse

                answer = JSONResponse({"error": f"Host {host[:100]!r} refused: not a name of this server"},
                                      status_code=400, headers=_SECURITY_HEADERS)
                await answer(scope, receive, send)
                return
        await self.app(scope, receive, send)


class _TooLarge(Exception):
    pass


class _Refused(Exception):
    def __init__(self, status: int, message: str) -> None:
        super().__init__(message)
        self.status = status


def bind(host: str, port: int) -> socket.socket:
    """A listening socket on ``host:port`` (0 = a free port), or one clear line saying why not."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind((host, port))
    except (socket.gaierror, UnicodeError) as e:
        sock.close()
        raise InputError(f"--host {host!r}: not an address of this machine ({e})") from None
    except OSError as e:
        sock.close()
        raise InputError(f"--port {port}: cannot listen on {host}:{port} ({e.strerror or e})") from None
    sock.listen(128)
    return sock


class ViewServer:
    """uvicorn serving :func:`create_app` on a bound socket; ``run()`` blocks, ``start()`` runs it in a thread."""

    def __init__(self, session: ViewSession, host: str = "127.0.0.1", port: int = 0) -> None:
        import uvicorn

        self.session = session
        self.sock = bind(host, port)
        self.host, self.port = host, self.sock.getsockname()[1]
        loopback = host in ("127.0.0.1", "localhost", "::1")
        # elsewhere the page is reached by any address of this machine, or by its name; never by another site's name
        hosts = ("127.0.0.1", "localhost", "::1") if loopback else ("localhost", host, socket.gethostname(),
                                                                   socket.gethostname() + ".local")
        self.worker = RenderWorker()
        self.app = create_app(session, self.worker, allowed_hosts=hosts, any_address=not loopback)
        # "error": a malformed request or one over the concurrency limit is answered (400, 503); uvicorn's warning
        # line about it on the user's console ("Invalid HTTP request received.") is noise, not theirs to act on
        config = uvicorn.Config(self.app, http=_http_protocol(), log_level="error", access_log=False,
                                lifespan="off", limit_concurrency=64, timeout_keep_alive=5,
                                h11_max_incomplete_event_size=16384, timeout_graceful_shutdown=10)
        worker = self.worker

        class _Server(uvicorn.Server):
            def handle_exit(self, sig, frame) -> None:
                # Ctrl-C / SIGTERM: the running render (an export too) stops at its next check and every waiting
                # request is answered, so uvicorn's graceful shutdown has nothing left to wait for
                worker.stop_soon()
                super().handle_exit(sig, frame)

        self.server = _Server(config)
        self._thread: threading.Thread | None = None

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.port}/"

    @contextlib.contextmanager
    def stopping_on_signals(self):
        """From here on Ctrl-C and SIGTERM ask the server to stop (uvicorn's own handler, installed early), instead
        of raising wherever they land: one landing before uvicorn's loop has started (under load, inside the event
        loop's constructor, which then failed in its ``__del__``) is then the normal stop too. The previous handlers
        come back on exit. Main thread only (signals are delivered there)."""
        if threading.current_thread() is not threading.main_thread():
            yield
            return
        sigs = (signal.SIGINT, signal.SIGTERM)
        previous = {sig: signal.signal(sig, self.server.handle_exit) for sig in sigs}
        try:
            yield
        finally:
            for sig, handler in previous.items():
                signal.signal(sig, handler)

    def run(self) -> None:
        interrupted = False
        try:
            with warnings.catch_warnings():
                # a Ctrl-C before uvicorn's loop has started leaves its serve() coroutine unawaited; it is collected
                # when the interrupt is handled here, and its RuntimeWarning would be a second line on stderr
                warnings.filterwarnings("ignore", r"coroutine .* was never awaited", RuntimeWarning)
                try:
                    self.server.run(sockets=[self.sock])
                except KeyboardInterrupt:
                    interrupted = True
        finally:
            self.close()
        if interrupted:
            raise KeyboardInterrupt

    def start(self) -> Self:
        self._thread = threading.Thread(target=self.server.run, kwargs={"sockets": [self.sock]}, daemon=True)
        self._thread.start()
        deadline = time.monotonic() + 10
        while not self.server.started and time.monotonic() < deadline:
            time.sleep(0.01)
        return self

    def close(self) -> None:
        self.server.should_exit = True
        if self._thread is not None:
            self._thread.join(10)
            self._thread = None
        self.worker.close()
        self.sock.close()

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()
