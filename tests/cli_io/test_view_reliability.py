"""bokehray view under abuse: malformed values answer 400 (not 500), an export stops with the server (Ctrl-C,
SIGTERM) and does not hold previews back while it runs, and no native Warp line reaches stderr."""

from __future__ import annotations

import json
import logging
import os
import signal
import socket
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request

import pytest

pytest.importorskip("starlette", reason="bokehray view needs the 'view' extra (starlette, uvicorn)")
pytest.importorskip("uvicorn", reason="bokehray view needs the 'view' extra (starlette, uvicorn)")

from tolerances import HANG_S

import bokehray as br
from bokehray.app.demo import build_demo_scene
from bokehray.app.view.server import ViewServer
from bokehray.app.view.session import ViewSession

CLI = "import sys; from bokehray.app.cli import main; sys.exit(main())"


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("view-rel")
    sc = build_demo_scene(width=240, height=160)
    br.write_image(d / "img.png", sc.image)
    br.write_disparity(d / "d.png", sc.disparity)
    return d


def post(url: str, data: bytes, timeout: float = HANG_S):
    req = urllib.request.Request(url, data=data, headers={"Content-Type": "application/json"}, method="POST")
    try:
        with urllib.request.urlopen(req, timeout=timeout) as r:
            return r.status, r.read()
    except urllib.error.HTTPError as e:
        return e.code, e.read()


MALFORMED = [
    ("api/render", b'{"blur": ' + str(10**30).encode() + b"}"),
    ("api/render", b'{"blur": ' + str(10**400).encode() + b"}"),
    ("api/render", b'{"amount": ' + str(10**400).encode() + b"}"),
    ("api/render", b'{"focus_at": [' + str(10**400).encode() + b", 3]}"),
    ("api/render", b'{"blades": ' + str(10**400).encode() + b', "aperture": "polygon"}'),
    ("api/render", b"[" * 1000 + b"]" * 1000),
    ("api/render", b'{"blur": 5, "stage": ["full"]}'),
    ("api/render", b'{"blur": 5, "stage": "full", "long_side": 1e400}'),
    ("api/render", b'{"blur": 5, "quality": {}}'),
    ("api/render", b'{"blur": 5, "aperture": []}'),
    ("api/export", b'{"params": {"blur": 5}, "format": ["png"]}'),
    ("api/export", b'{"params": {"blur": 5}, "format": {}}'),
    ("api/export", b'{"params": {"blur": 5}, "format": "png", "bit_depth": {}}'),
    ("api/export", b'{"params": {"blur": ' + str(10**400).encode() + b"}}"),
    ("api/export", b'{"params": ' + b"[" * 1000 + b"]" * 1000 + b"}"),
]


@pytest.fixture(scope="module")
def server(files):
    s = ViewSession.from_files(str(files / "img.png"), disparity=str(files / "d.png"), export_dir=files,
                               proxy_long_side=64, display_long_side=120)
    with ViewServer(s) as srv:
        yield srv


@pytest.mark.parametrize(("path", "body"), MALFORMED, ids=[f"{p}-{i}" for i, (p, _) in enumerate(MALFORMED)])
def test_malformed_values_are_400_with_one_line(server, path, body):
    assert len(body) <= 4096
    status, answer = post(server.url + path, body)
    assert status == 400, answer
    message = json.loads(answer)["error"]
    assert "\n" not in message and len(message) < 400



class _Records(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.ERROR)
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)


@pytest.mark.parametrize("path", ["api/render", "api/export"])
def test_a_client_gone_before_its_body_ends_leaves_no_traceback(server, path):
    """A client that closes after half of its body (a browser tab closed, a killed script) made Starlette raise
    ClientDisconnect out of the handler: uvicorn's "Exception in ASGI application" and a traceback on the console."""
    records = _Records()
    logger = logging.getLogger("uvicorn.error")
    logger.addHandler(records)
    try:
        rejected = server.app.state.stats["rejected"]
        with socket.create_connection(("127.0.0.1", server.port), timeout=HANG_S) as s:
            s.sendall(f"POST /{path} HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\n"
                      f"Content-Length: 100\r\n\r\n{{\"blur\": ".encode())
        deadline = time.monotonic() + HANG_S  # until the server has handled the disconnect, one way or the other
        while not records.records and server.app.state.stats["rejected"] == rejected and time.monotonic() < deadline:
            time.sleep(0.02)
    finally:
        logger.removeHandler(records)
    assert not records.records, records.records[0].getMessage()
    assert server.app.state.stats["rejected"] == rejected + 1
    with urllib.request.urlopen(server.url + "api/info", timeout=HANG_S) as r:
        assert r.status == 200


def test_a_malformed_request_is_answered_without_a_line_on_the_console(server):
    """uvicorn printed "WARNING: Invalid HTTP request received." on the user's console for any client's garbage."""
    records = _Records()
    records.setLevel(logging.WARNING)
    logger = logging.getLogger("uvicorn.error")
    logger.addHandler(records)
    try:
        with socket.create_connection(("127.0.0.1", server.port), timeout=HANG_S) as s:
            s.sendall(b"NOT HTTP AT ALL\x00\r\n\r\n")
            answer = s.recv(4096)
    finally:
        logger.removeHandler(records)
    assert answer.startswith(b"HTTP/1.1 400"), answer
    assert not records.records, records.records[0].getMessage()


def _half_a_body(port: int, path: str = "api/render") -> socket.socket:
    s = socket.create_connection(("127.0.0.1", port), timeout=HANG_S)
    s.sendall(f"POST /{path} HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\n"
              f"Content-Length: 100\r\n\r\n{{\"blur\": ".encode())
    return s


def _answer(s: socket.socket) -> bytes:
    data = b""
    while chunk := s.recv(65536):  # until the server closes the connection
        data += chunk
    return data


def test_a_body_that_stops_half_way_is_answered_408_and_the_connection_closed(server, monkeypatch):
    """A client that sent half of its body and then nothing held its connection (one of uvicorn's 64) for as long
    as it stayed open: 64 of them and every other request was refused with 503."""
    import bokehray.app.view.server as view_server

    monkeypatch.setattr(view_server, "BODY_TIMEOUT_S", 0.2, raising=False)
    with _half_a_body(server.port) as s:
        head, _, body = _answer(s).partition(b"\r\n\r\n")
    assert head.startswith(b"HTTP/1.1 408 "), head
    assert json.loads(body) == {"error": "request body: not all of it arrived within 0.2 s"}


def _response(s: socket.socket) -> bytes:
    """One whole response on a connection the server keeps open (its Content-Length says where it ends)."""
    data = b""
    while b"\r\n\r\n" not in data:
        data += s.recv(65536)
    head, _, body = data.partition(b"\r\n\r\n")
    length = next(int(line.split(b":")[1]) for line in head.split(b"\r\n") if line.lower().startswith(b"content-length:"))
    while len(body) < length:
        body += s.recv(65536)
    return head


def test_connections_that_never_finish_their_headers_are_closed_and_the_server_answers_again(server, monkeypatch):
    """Regression: a connection that sent nothing, or half of its request headers, was never timed out;
    64 of them (uvicorn's concurrency limit) and every other request was answered 503 until they closed. Each has
    HEADER_TIMEOUT_S now: half a request is answered 408, a silent connection closed; so is a kept-alive connection
    that starts its next request and stops. Outcomes only; HANG_S is a hang detector."""
    import bokehray.app.view.server as view_server

    monkeypatch.setattr(view_server, "HEADER_TIMEOUT_S", 0.2, raising=False)
    stalled = []
    try:
        for i in range(70):  # more than uvicorn's 64
            s = socket.create_connection(("127.0.0.1", server.port), timeout=HANG_S)
            if i % 2:
                s.sendall(b"GET /api/info HTTP/1.1\r\nHost: 127.0.0.1\r\nAccept: ")
            stalled.append(s)
        answers = [_answer(s) for s in stalled]  # each returns once the server has closed its connection
    finally:
        for s in stalled:
            s.close()
    assert answers[::2] == [b""] * 35
    for a in answers[1::2]:
        head, _, body = a.partition(b"\r\n\r\n")
        assert head.startswith(b"HTTP/1.1 408 "), a
        assert json.loads(body) == {"error": "request headers: not all of them arrived within 0.2 s"}
    with socket.create_connection(("127.0.0.1", server.port), timeout=HANG_S) as s:
        s.sendall(b"GET /api/info HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
        assert _response(s).startswith(b"HTTP/1.1 200 ")  # kept alive; then the next request stops half-way
        s.sendall(b"GET /api/info HTTP/1.1\r\nHost: 127.0.0.1\r\nAcc")
        assert _answer(s).startswith(b"HTTP/1.1 408 ")
    with urllib.request.urlopen(server.url + "api/info", timeout=HANG_S) as r:
        assert r.status == 200


def _get(url: str, host: str):
    req = urllib.request.Request(url, headers={"Host": host})
    try:
        with urllib.request.urlopen(req, timeout=HANG_S) as r:
            return r.status, r.read()
    except urllib.error.HTTPError as e:
        return e.code, e.read()


def test_a_server_on_another_address_refuses_another_sites_name(server):
    """``--host`` other than the loopback names turned the Host check off: a page of any site, its name rebound to
    this machine's address (DNS rebinding), read the photo and made exports. Off loopback, the Host must now be an
    address or a name of this machine."""
    from bokehray.errors import InputError

    try:
        other = ViewServer(server.session, host="127.0.0.2")
    except InputError as e:  # 127.0.0.2 is loopback on Linux, not everywhere
        pytest.skip(str(e))
    with other.start():
        port = other.port
        status, answer = _get(other.url + "api/photo.jpg", f"rebound.attacker.example:{port}")
        assert status == 400 and "rebound.attacker.example" in json.loads(answer)["error"]
        for host in (f"127.0.0.2:{port}", f"localhost:{port}", f"{socket.gethostname()}:{port}", "[::1]"):
            status, answer = _get(other.url + "api/info", host)
            assert status == 200, (host, answer)
    status, answer = _get(server.url + "api/info", "127.0.0.2")  # on loopback: only the loopback names
    assert status == 400


def _raw(port: int, request: bytes, family: int = socket.AF_INET, host: str = "127.0.0.1") -> bytes:
    with socket.socket(family, socket.SOCK_STREAM) as s:
        s.settimeout(HANG_S)
        s.connect((host, port))
        s.sendall(request)
        data = b""
        while chunk := s.recv(65536):
            data += chunk
            if b"\r\n\r\n" in data:
                head, _, body = data.partition(b"\r\n\r\n")
                length = [int(line.split(b":")[1]) for line in head.split(b"\r\n")
                          if line.lower().startswith(b"content-length:")]
                if length and len(body) >= length[0]:
                    break
        return data


def test_a_request_without_a_host_name_is_refused(server):
    """An empty Host, one that is only a port, and none at all (HTTP/1.0) were answered: the allow-list held ``''``
    (``::1`` read as a name and a port)."""
    for host in (b"Host: \r\n", b"Host: :80\r\n", b""):
        answer = _raw(server.port, b"GET /api/info HTTP/1.0\r\n" + host + b"\r\n")
        assert answer.startswith(b"HTTP/1.1 400 ") and b"refused" in answer, (host, answer)
    assert _raw(server.port, b"GET /api/info HTTP/1.0\r\nHost: 127.0.0.1\r\n\r\n").startswith(b"HTTP/1.1 200 ")


def test_a_server_on_the_ipv6_loopback_answers_its_own_url(server):
    """``view --host ::1`` printed ``http://[::1]:PORT/`` and answered every request from it 400: its Host
    ``[::1]:PORT`` was checked against ``''``, not ``::1``."""
    from bokehray.errors import InputError

    try:
        six = ViewServer(server.session, host="::1")
    except InputError as e:  # a machine without IPv6
        pytest.skip(str(e))
    with six.start():
        assert six.url == f"http://[::1]:{six.port}/"
        answer = _raw(six.port, f"GET /api/info HTTP/1.1\r\nHost: [::1]:{six.port}\r\nConnection: close\r\n\r\n"
                      .encode(), socket.AF_INET6, "::1")
        assert answer.startswith(b"HTTP/1.1 200 "), answer
        answer = _raw(six.port, b"GET /api/info HTTP/1.1\r\nHost: evil.example\r\nConnection: close\r\n\r\n",
                      socket.AF_INET6, "::1")
        assert answer.startswith(b"HTTP/1.1 400 "), answer


def test_request_headers_beyond_the_limit_are_refused_431(server):
    """A 100 kB header line arriving in one packet was answered 200: h11 bounds only headers still arriving."""
    from bokehray.app.view.server import MAX_HEADER_BYTES

    big = b"x" * 100_000
    answer = _raw(server.port, b"GET /api/info HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Big: " + big + b"\r\n\r\n")
    assert answer.startswith(b"HTTP/1.1 431 "), answer[:200]
    fits = b"x" * (MAX_HEADER_BYTES - 200)
    answer = _raw(server.port, b"GET /api/info HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\nX-Big: " + fits
                  + b"\r\n\r\n")
    assert answer.startswith(b"HTTP/1.1 200 "), answer[:200]


# an export long enough to be interrupted: every full-resolution layer (the photo is 240 x 160; the page's proxies
# and screen renders are smaller) takes a second longer, and the export's progress check runs between layers
SLOW_LAYERS = """
import time
import bokehray.levels.preview as pv
_render = pv.render_layer
def _slow(layer, arrays, scatter, *kept):
    y0, y1, x0, x1 = layer.bbox
    if (y1 - y0) * (x1 - x0) > 200 * 140:
        time.sleep(1.0)
    return _render(layer, arrays, scatter, *kept)
pv.render_layer = _slow
"""


HUP_DEFAULT = "import signal; signal.signal(signal.SIGHUP, signal.SIG_DFL)\n"
"""A server started from a test run under ``nohup`` inherits SIGHUP ignored, and an ignored SIGHUP stays ignored (by
design): it starts with the disposition of a terminal's session instead, whatever the test run's."""


def _start_view(files, *extra, prelude=""):
    proc = subprocess.Popen([sys.executable, "-c", HUP_DEFAULT + prelude + CLI, "view", str(files / "img.png"), "--disparity",
                             str(files / "d.png"), "--export-dir", str(files), *extra], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"})
    line = proc.stdout.readline()
    assert line.startswith("bokehray view: http://127.0.0.1:"), line + proc.stderr.read()
    return proc, line.split()[2]


def _progress(url: str) -> dict:
    return json.loads(urllib.request.urlopen(url + "api/progress", timeout=HANG_S).read())


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM, signal.SIGHUP])
def test_a_long_export_stops_with_the_server_and_previews_pass_it(files, sig):
    """The issue: a long export (ray-traced, 4096 rays per pixel; the page now exports the preview level only) held
    the server past Ctrl-C (a second Ctrl-C exited after a CancelledError traceback, the request got a 500) and
    previews queued behind it. SIGHUP (the terminal closed) raised inside the request's handler: a traceback, and
    the server often served on and finished the export; it stops the server as SIGTERM does now."""
    proc, url = _start_view(files, prelude=SLOW_LAYERS)
    answers: dict[str, tuple] = {}
    try:
        body = json.dumps({"params": {"amount": 100}, "format": "exr"})

        def export():
            answers["export"] = post(url + "api/export", body.encode())

        t = threading.Thread(target=export, daemon=True)
        t.start()
        deadline = time.monotonic() + HANG_S  # a hang detector, not a time bound
        while not any(j["kind"] == "export" for j in _progress(url)["running"]):
            assert time.monotonic() < deadline and t.is_alive(), answers
            time.sleep(0.05)
        # a preview while the export runs: answered, and the export is still running after it
        status, data = post(url + "api/render", json.dumps({"stage": "preview"}).encode())
        assert status == 200 and data[:2] == b"\xff\xd8"
        running = _progress(url)["running"]
        assert running and running[0]["kind"] == "export" and t.is_alive()
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=HANG_S)
        t.join(HANG_S)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 128 + int(sig), err  # 130, 143, 129: as `render` and batches exit on a signal
    assert "Traceback" not in err and "CancelledError" not in err and "stopped" in err
    status, data = answers["export"]
    assert status == 503 and "stopping" in json.loads(data)["error"]
    assert not list(files.glob("img-bokeh-*.exr"))  # nothing half-written


@pytest.mark.slow
def test_view_errors_are_one_line_and_start_has_no_native_warp_line(files):
    """The issue: `view` printed Warp's native "CUDA driver not found" line on every start, so every error was two
    lines; `render` already hides it."""
    r = subprocess.run([sys.executable, "-c", CLI, "view", str(files / "missing.png"), "--disparity",
                        str(files / "d.png")], capture_output=True, text=True, timeout=HANG_S)
    assert r.returncode == 2
    assert len(r.stderr.strip().splitlines()) == 1 and "missing.png" in r.stderr, r.stderr
    proc, _url = _start_view(files)
    try:
        proc.send_signal(signal.SIGINT)
        _out, err = proc.communicate(timeout=HANG_S)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 130 and "CUDA" not in err and "Warp" not in err, err
    assert err.strip() == "bokehray view: stopped"


@pytest.mark.slow
def test_a_ctrl_c_before_the_server_loop_starts_is_a_clean_stop(files):
    """Under load a Ctrl-C can land between the printed URL and uvicorn's event loop: its serve() coroutine was then
    never awaited and Python's RuntimeWarning became a second line on stderr."""
    prelude = """
import uvicorn
def _interrupted_run(self, sockets=None):
    coroutine = self.serve(sockets=sockets)  # made, never awaited: as when SIGINT lands before asyncio.run awaits
    raise KeyboardInterrupt
uvicorn.Server.run = _interrupted_run
"""
    proc, _ = _start_view(files, prelude=prelude)
    _out, err = proc.communicate(timeout=HANG_S)
    assert proc.returncode == 130 and err.strip() == "bokehray view: stopped", err


@pytest.mark.slow
def test_a_ctrl_c_right_after_the_printed_url_is_a_clean_stop(files):
    """The URL is printed, then a line on the defaults, then uvicorn starts: a Ctrl-C landing in between (under load
    the suite saw it) was an "interrupted" exit 130 instead of the server's normal stop."""
    prelude = """
from bokehray.photo import subject
def _interrupted(self):
    raise KeyboardInterrupt  # as SIGINT landing while the defaults line is written
subject.Subject.describe = _interrupted
"""
    proc, _ = _start_view(files, prelude=prelude)
    _, err = proc.communicate(timeout=HANG_S)
    assert proc.returncode == 130 and err.strip() == "bokehray view: stopped", err


@pytest.mark.slow
def test_a_ctrl_c_while_a_body_is_half_sent_is_a_clean_stop(files):
    """Ctrl-C while a request's body was half-way: the handler waited for the rest, uvicorn's graceful shutdown gave
    up after 10 s and cancelled it, and a CancelledError traceback was printed before "stopped"."""
    proc, url = _start_view(files)
    try:
        with _half_a_body(int(url.rstrip("/").rsplit(":", 1)[1])) as s:
            urllib.request.urlopen(url + "api/status", timeout=HANG_S).read()  # the server has the half body by now
            proc.send_signal(signal.SIGINT)
            _, err = proc.communicate(timeout=HANG_S)
            answer = _answer(s)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 130 and err.strip() == "bokehray view: stopped", err
    assert answer.startswith(b"HTTP/1.1 408 "), answer
