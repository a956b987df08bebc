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
from .session import MAX_BODY_BYTES, ViewSession, export_choice, json_integer
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


def _blob(data: bytes, media: str, headers: dict | None = None):
    from starlette.responses import Response

    return Response(data, media_type=media, headers={**_SECURITY_HEADERS, **(headers or {})})


def _json(content, status: int = 200, headers: dict | None = None):
    from starlette.responses import JSONResponse

    return JSONResponse(content, status_code=status, headers=headers or _SECURITY_HEADERS)


def _check_json_request(request) -> None:
    """A page of another site can make the browser POST here ("simple" requests need no CORS preflight), but not with
    a JSON content type, and the browser names its origin: both are checked, and the declared size."""
    if request.headers.get("content-type", "").split(";")[0].strip().lower() != "application/json":
        raise _Refused(415, "request body: expected Content-Type: application/json")
    origin = request.headers.get("origin")
    if origin is not None and origin != f"{request.url.scheme}://{request.headers.get('host', '')}":
        raise _Refused(403, f"request from another origin ({origin}) refused")
    declared = request.headers.get("content-length")
    if declared is not None and (not declared.isdigit() or int(declared) > MAX_BODY_BYTES):
        raise _TooLarge()


async def _read_body(request) -> bytes:
    """The request's body, at most :data:`MAX_BODY_BYTES`. A body that stops half-way held a connection slot for good
    and held up Ctrl-C until uvicorn cancelled the handler (a traceback): it has :data:`BODY_TIMEOUT_S` to arrive."""
    from starlette.requests import ClientDisconnect

    body = b""
    try:
        async with asyncio.timeout(BODY_TIMEOUT_S):
            async for chunk in request.stream():
                body += chunk
                if len(body) > MAX_BODY_BYTES:
                    raise _TooLarge()
    except ClientDisconnect:  # the answer goes nowhere, but it is an answer: no traceback on the console
        raise _Refused(400, "request body: the client disconnected before sending all of it") from None
    except TimeoutError:
        raise _Refused(408, f"request body: not all of it arrived within {BODY_TIMEOUT_S:g} s") from None
    return body


async def _read_json(request):
    _check_json_request(request)
    body = await _read_body(request)
    try:
        return json.loads(body)
    except (ValueError, UnicodeDecodeError) as e:
        raise InputError(f"request body: expected JSON ({e})") from None
    except RecursionError:  # nested deeper than Python's parser goes (1000 levels fit in the 4096 bytes)
        raise InputError("request body: JSON nested too deeply") from None


def _render_request(session: ViewSession, body) -> tuple:
    """The parameters, stage and long side of a ``/api/render`` body (:class:`InputError` for a bad one)."""
    p = session.parse(body)
    stage = body.get("stage", "preview")
    if not isinstance(stage, str) or stage not in ("preview", "focus", "full"):
        raise InputError(f"stage: expected 'preview', 'focus' or 'full', got {stage!r}"[:200])
    long_side = body.get("long_side")
    if long_side is not None:
        long_side = json_integer(long_side, "long_side")
        if long_side < 16:
            raise InputError(f"long_side: expected at least 16 pixels, got {long_side}")
    return p, stage, long_side


def _export_request(session: ViewSession, body) -> tuple:
    """The parameters, format and bit depth of an ``/api/export`` body (:class:`InputError` for a bad one)."""
    if not isinstance(body, dict) or set(body) - {"params", "format", "bit_depth"}:
        raise InputError("export: expected {\"params\": {...}, \"format\": ..., \"bit_depth\": ...}")
    p = session.parse(body.get("params", {}))
    fmt, bits = export_choice(body)
    return p, fmt, bits


def _render_headers(session: ViewSession, p, stage: str, meta: dict, seconds: float, t0: float, command: str) -> dict:
    return {
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


class _Api:
    """The page's routes over one session and its render worker; ``stats`` counts requests and refusals."""

    def __init__(self, session: ViewSession, worker: RenderWorker) -> None:
        self.session, self.worker = session, worker
        self.stats = {"requests": 0, "rejected": 0}

    def error(self, status: int, message: str):
        self.stats["rejected"] += status >= 400 and status != 409
        headers = {**_SECURITY_HEADERS, "Connection": "close"} if status == 408 else _SECURITY_HEADERS
        return _json({"error": message}, status, headers)

    def refusal(self, e: Exception):
        """The answer to a request refused before its work started (``None``: not a refusal)."""
        if isinstance(e, _TooLarge):
            return self.error(413, f"request body: larger than {MAX_BODY_BYTES} bytes")
        if isinstance(e, _Refused):
            return self.error(e.status, str(e))
        if isinstance(e, Busy):
            return self.error(429, str(e))
        if isinstance(e, Stopped):
            return self.error(503, "the server is stopping")
        if isinstance(e, BokehrayError):
            return self.error(400, str(e))
        return None

    async def page(self, request):
        return _blob(_static("index.html"), _STATIC["index.html"])

    async def static(self, request):
        name = request.path_params["name"]
        if name not in _STATIC:  # a fixed list: no path from the client reaches the file system
            return self.error(404, f"no such file: {name!r}")
        return _blob(_static(name), _STATIC[name])

    async def info(self, request):
        return _json(self.session.info())

    async def photo(self, request):
        return _blob(await asyncio.to_thread(self.session.photo_jpeg), "image/jpeg")

    async def depth(self, request):
        return _blob(await asyncio.to_thread(self.session.depth_png), "image/png")

    async def disparity16(self, request):
        return _blob(await asyncio.to_thread(self.session.disparity16_png), "image/png")

    async def render(self, request):
        self.stats["requests"] += 1
        try:
            body = await _read_json(request)
            p, stage, long_side = _render_request(self.session, body)
            command = self.session.shown_command(p, body)  # -o OUTPUT.<the export's format>
        except (_TooLarge, _Refused, BokehrayError) as e:
            return self.refusal(e)
        t0 = time.perf_counter()
        session = self.session

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
            data, meta, seconds = await asyncio.wrap_future(
                self.worker.submit(job, "preview" if stage == "preview" else "full"))
        except Superseded:
            return _json({"superseded": True}, 409)
        except (Stopped, BokehrayError) as e:
            return self.refusal(e)
        return _blob(data, "image/jpeg", _render_headers(session, p, stage, meta, seconds, t0, command))

    async def export(self, request):
        try:
            p, fmt, bits = _export_request(self.session, await _read_json(request))
            fut = self.worker.submit_export(lambda check: self.session.export(p, fmt, bits, check))
        except (_TooLarge, _Refused, Busy, Stopped, BokehrayError) as e:
            return self.refusal(e)
        t0 = time.perf_counter()
        try:
            path, command = await asyncio.wrap_future(fut)
        except Stopped:
            return self.error(503, "export abandoned: the server is stopping")
        except BokehrayError as e:
            return self.error(400, str(e))
        except OSError as e:
            return self.error(500, f"export: {e}")
        return _json({"path": str(path), "command": command, "seconds": round(time.perf_counter() - t0, 3)})

    async def progress(self, request):
        return _json(self.worker.progress())

    async def status(self, request):
        return _json({"worker": dict(self.worker.counts), "queued": self.worker.queued(), **self.stats})

    def routes(self) -> list:
        from starlette.routing import Route

        return [
            Route("/", self.page), Route("/static/{name}", self.static), Route("/api/info", self.info),
            Route("/api/photo.jpg", self.photo), Route("/api/depth.png", self.depth),
            Route("/api/disparity16.png", self.disparity16),
            Route("/api/render", self.render, methods=["POST"]), Route("/api/export", self.export, methods=["POST"]),
            Route("/api/status", self.status), Route("/api/progress", self.progress),
        ]


def create_app(session: ViewSession, worker: RenderWorker | None = None, allowed_hosts: tuple[str, ...] = (),
               any_address: bool = False):
    """The Starlette app over ``session``; ``worker`` defaults to a new :class:`RenderWorker`. With ``allowed_hosts``
    only requests whose ``Host`` is one of them (or, with ``any_address``, an IP address) are answered."""
    from starlette.applications import Starlette
    from starlette.middleware import Middleware

    api = _Api(session, worker or RenderWorker())
    middleware = [Middleware(_HeaderSize)]
    if allowed_hosts:
        # a page on another site cannot reach this server through DNS rebinding: the Host must be ours
        middleware.append(Middleware(_HostCheck, names=allowed_hosts, addresses=any_address))
    app = Starlette(routes=api.routes(), middleware=middleware)
    app.state.worker = api.worker
    app.state.stats = api.stats
    return app


MAX_HEADER_BYTES = 16384
"""The most bytes a request's line and headers may hold (uvicorn's ``h11_max_incomplete_event_size`` is the same
figure, but h11 applies it only to headers still arriving: 100 kB of them in one packet were taken)."""


def _host_name(host: str) -> str:
    """The name or address of a ``Host`` header: lower case, without the port or an IPv6 address's brackets (``''``
    for an empty header or one that is only a port)."""
    host = host.strip().lower()
    return host[1:].partition("]")[0] if host.startswith("[") else host.partition(":")[0]


def _listed_name(name: str) -> str:
    """A name or address of this server as listed (no port): lower case, an IPv6 address without brackets."""
    name = name.strip().lower()
    return name[1:].partition("]")[0] if name.startswith("[") else name


class _HeaderSize:
    """Answers 431 to a request whose line and headers hold more than :data:`MAX_HEADER_BYTES`."""

    def __init__(self, app) -> None:
        self.app = app

    async def __call__(self, scope, receive, send) -> None:
        if scope["type"] == "http":
            size = len(scope.get("raw_path") or b"") + len(scope.get("query_string") or b"")
            size += sum(len(k) + len(v) + 4 for k, v in scope["headers"])
            if size > MAX_HEADER_BYTES:
                await _json({"error": f"request line and headers: {size} bytes, more than the {MAX_HEADER_BYTES} "
                                      "taken"}, 431, {**_SECURITY_HEADERS, "Connection": "close"})(scope, receive, send)
                return
        await self.app(scope, receive, send)


class _HostCheck:
    """Answers only requests whose ``Host`` is one of ``names`` or, with ``addresses``, an IP address: a page of another
    site reaches this server through DNS rebinding only under a name of its own, and an address cannot be rebound. A
    request without a Host name (none, empty, only a port) is refused."""

    def __init__(self, app, names: tuple[str, ...], addresses: bool = False) -> None:
        self.app, self.addresses = app, addresses
        self.names = {_listed_name(n) for n in names} - {""}

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
                await _json({"error": f"Host {host[:100]!r} refused: not a name of this server"},
                            400)(scope, receive, send)
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
        view = self
        self.stop_signal: int | None = None
        """The signal that stopped the server (None: none did): the command exits with 128 plus its number."""

        class _Server(uvicorn.Server):
            def handle_exit(self, sig, frame) -> None:
                # Ctrl-C / SIGTERM: the running render (an export too) stops at its next check and every waiting
                # request is answered, so uvicorn's graceful shutdown has nothing left to wait for
                view.stop_signal = view.stop_signal or int(sig)
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
        """From here on Ctrl-C, SIGTERM and SIGHUP (the terminal closed) ask the server to stop (uvicorn's own
        handler, installed early), instead of raising wherever they land: one landing before uvicorn's loop has
        started (under load, inside the event loop's constructor, which then failed in its ``__del__``) is then the
        normal stop too, and a SIGHUP landing inside a request's handler no longer raises there (a traceback, and
        the server served on). An ignored SIGHUP (``nohup``) stays ignored. The previous handlers come back on exit.
        Main thread only (signals are delivered there)."""
        if threading.current_thread() is not threading.main_thread():
            yield
            return
        sigs = [signal.SIGINT, signal.SIGTERM]
        if signal.getsignal(signal.SIGHUP) is not signal.SIG_IGN:
            sigs.append(signal.SIGHUP)
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
