"""bokehray view: parameter validation (the CLI's errors), the proxy, the worker, the HTTP server, export."""

from __future__ import annotations

import json
import shlex
import threading
import time
import urllib.error
import urllib.request
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("starlette", reason="bokehray view needs the 'view' extra (starlette, uvicorn)")
pytest.importorskip("uvicorn", reason="bokehray view needs the 'view' extra (starlette, uvicorn)")

import bokehray as br
from bokehray.app.cli import main
from bokehray.app.demo import build_demo_scene
from bokehray.app.view.server import ViewServer
from bokehray.app.view.session import ProxyLadder, ViewSession, box_reduce, parse_params
from bokehray.app.view.worker import RenderWorker, Superseded
from bokehray.errors import InputError


@pytest.fixture(scope="module")
def scene_files(tmp_path_factory):
    d = tmp_path_factory.mktemp("view")
    sc = build_demo_scene(width=480, height=320)
    img, disp = d / "photo.exr", d / "disp.exr"
    br.write_image(img, sc.image)
    br.write_image(disp, sc.disparity[..., None])
    return d, img, disp, sc


@pytest.fixture(scope="module")
def session(scene_files):
    d, img, disp, _ = scene_files
    out = d / "exports"
    out.mkdir()
    s = ViewSession.from_files(str(img), disparity=str(disp), export_dir=out, proxy_long_side=160,
                               display_long_side=240)
    s.ladder = ProxyLadder(1)  # the finest proxy only, whatever the load of the machine (the ladder: below)
    return s


def subject_pixel(disparity: np.ndarray) -> tuple[int, int]:
    """Centre of the demo's cat (disparity 0.92 at its centre)."""
    ys, xs = np.nonzero(np.abs(disparity - 0.92) < 0.004)
    return int(np.median(xs)), int(np.median(ys))


# --- validation: the same messages as `bokehray render` ------------------------------------------------
BAD = [
    ({"blur": -1.0, "focus": 0.5}, ["--blur", "-1", "--focus", "0.5"]),
    ({"blur": 2e5, "focus": 0.5}, ["--blur", "200000", "--focus", "0.5"]),
    ({"blur": 10.0, "focus": 1.5}, ["--blur", "10", "--focus", "1.5"]),
    ({"blur": 10.0, "focus_at": [480, 3]}, ["--blur", "10", "--focus-at", "480,3"]),
    ({"blur": 10.0, "focus_at": [-1, 3]}, ["--blur", "10", "--focus-at=-1,3"]),
    ({"blur": 10.0, "focus": 0.5, "focus_at": [1, 1]}, ["--blur", "10", "--focus", "0.5", "--focus-at", "1,1"]),
    ({"blur": 10.0, "focus": 0.5, "aperture": "polygon", "blades": 40},
     ["--blur", "10", "--focus", "0.5", "--aperture", "polygon", "--blades", "40"]),
    ({"blur": 10.0, "focus": 0.5, "aperture": "polygon", "blades": 2},
     ["--blur", "10", "--focus", "0.5", "--aperture", "polygon", "--blades", "2"]),
    ({"blur": 10.0, "focus": 0.5, "aperture": "polygon", "curvature": 1.5},
     ["--blur", "10", "--focus", "0.5", "--aperture", "polygon", "--curvature", "1.5"]),
    ({"blur": 10.0, "focus": 0.5, "quality": "raytrace"}, ["--blur", "10", "--focus", "0.5", "--quality", "raytrace"]),
    ({"blur": 10.0, "focus": 0.5, "highlight_boost": -1.0},
     ["--blur", "10", "--focus", "0.5", "--highlight-boost", "-1"]),
]


@pytest.mark.parametrize("body,argv", BAD, ids=[str(i) for i in range(len(BAD))])
def test_bad_parameters_read_as_the_cli_says_them(session, scene_files, tmp_path, capsys, body, argv):
    with pytest.raises(InputError) as e:
        parse_params(body, session.disparity)
    _, img, disp, _ = scene_files
    rc = main(["render", str(img), "--disparity", str(disp), "-o", str(tmp_path / "o.png"), *argv])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and err == f"bokehray: error: {e.value}"
    assert not (tmp_path / "o.png").exists()


@pytest.mark.parametrize("body", [None, [], {"blur": "10", "focus": 0.5}, {"blur": True, "focus": 0.5},
                                  {"blur": 10, "focus": 0.5, "path": "/etc/passwd"},
                                  {"blur": 10, "focus_at": [1.5, 2]}, {"blur": 10, "focus": float("nan")},
                                  {"blur": 10, "focus": 0.5, "quality": "ultra"},
                                  {"blur": 10, "focus": 0.5, "blades": 6.5, "aperture": "polygon"}])
def test_malformed_parameters_are_input_errors(session, body):
    with pytest.raises(InputError):
        parse_params(body, session.disparity)


def test_click_focus_is_the_clis_focus_at(session):
    x, y = subject_pixel(session.disparity)
    p = parse_params({"blur": 10, "focus_at": [x, y]}, session.disparity)
    assert p.blur.focus_disparity == br.focus_at(session.disparity, x, y)
    assert abs(p.blur.focus_disparity - 0.92) < 0.01


# --- the proxy ---------------------------------------------------------------------------------------
def box_reduce_reference(a: np.ndarray, f: int) -> np.ndarray:
    h, w = a.shape[:2]
    out = np.zeros((-(-h // f), -(-w // f)) + a.shape[2:], np.float64)
    for i in range(out.shape[0]):
        for j in range(out.shape[1]):
            acc = 0.0
            for y in range(i * f, i * f + f):
                for x in range(j * f, j * f + f):
                    acc = acc + a[min(y, h - 1), min(x, w - 1)]
            out[i, j] = acc / (f * f)
    return out


@pytest.mark.parametrize("shape,f", [((7, 5), 1), ((7, 5), 2), ((9, 13, 3), 4), ((6, 6, 1), 3), ((5, 3, 3), 7),
                                     ((17, 11, 4), 3), ((1, 9), 4)])
def test_box_reduce_matches_the_loop(shape, f):
    a = np.random.default_rng(1).random(shape).astype(np.float32)
    got = box_reduce(a, f)
    assert got.dtype == np.float32 and got.flags.c_contiguous
    np.testing.assert_allclose(got, box_reduce_reference(a, f), rtol=1e-5, atol=1e-6)


def test_box_reduce_of_a_strided_hdr_view():
    """A crop of the photo (a strided view) with lights 1e4 times the rest: the block means as the loop's."""
    a = np.random.default_rng(2).random((40, 50, 3)).astype(np.float32)
    a[::7, ::5] *= 1e4
    view = a[3:38, 5:47]
    np.testing.assert_allclose(box_reduce(view, 4), box_reduce_reference(view, 4), rtol=1e-5, atol=1e-6)


def test_proxy_preview_approximates_the_reduced_full_render(scene_files):
    """The proxy renders with K / f: close to the full render reduced by f, far from it with K unscaled."""
    _, _, _, sc = scene_files
    s = ViewSession(sc.image, sc.disparity, proxy_long_side=160)  # f = 3
    f = s.proxy_factor
    assert f == 3
    blur = br.BlurParams(24.0, sc.focus_near)
    full = box_reduce(br.render(sc.image, sc.disparity, blur), f)
    proxy = br.render(s.proxy_image, s.proxy_disparity, br.BlurParams(24.0 / f, sc.focus_near))
    unscaled = br.render(s.proxy_image, s.proxy_disparity, blur)

    def psnr(a, b):
        return 10 * np.log10(1.0 / np.mean((np.clip(a, 0, 1) - np.clip(b, 0, 1)) ** 2))

    assert psnr(proxy, full) > 28.0
    assert psnr(proxy, full) > psnr(unscaled, full) + 6.0


def test_proxy_ladder_steps_coarser_when_slow_and_back_when_fast():
    lad = ProxyLadder(3, budget_s=0.2, step_up=0.45)
    assert [lad.report(t) for t in (0.1, 0.3, 0.3, 0.3, 0.15, 0.12, 0.05, 0.05, 0.05)] == [0, 1, 2, 2, 2, 2, 1, 0, 0]
    assert ProxyLadder(1).report(10.0) == 0
    # the loaded machine: 0.79 s at the finest proxy against 0.19 s steps three levels at once
    assert ProxyLadder(5, budget_s=0.19).report(0.79) == 3
    assert ProxyLadder(5, budget_s=0.19).report(30.0) == 4


def test_preview_renders_at_the_ladders_proxy(scene_files):
    _, _, _, sc = scene_files
    s = ViewSession(sc.image, sc.disparity, proxy_long_side=160)
    assert [f for f, _, _ in s.proxies] == [3, 4, 6, 8, 10]
    p = parse_params({"blur": 20.0, "focus": 0.5}, s.disparity)
    s.ladder = ProxyLadder(5, budget_s=-1.0)  # every render is "slow": one level coarser each time
    import io

    from PIL import Image

    for f in (3, 4, 6, 8, 10, 10):
        data, meta = s.render_preview(p)
        assert meta["factor"] == f and Image.open(io.BytesIO(data)).size == (-(-480 // f), -(-320 // f))


# --- the worker --------------------------------------------------------------------------------------
def test_worker_newest_wins_and_abandons_the_running_job():
    w = RenderWorker()
    started = threading.Event()
    try:
        def slow(check):
            started.set()
            for _ in range(500):  # a render checking between layers
                time.sleep(0.01)
                check()
            return "slow"

        first = w.submit(slow)
        assert started.wait(5)
        queued = [w.submit(lambda check, i=i: i) for i in range(20)]
        assert queued[-1].result(5) == 19
        # handed over without the abandoned job's traceback (its frames hold the render's arrays)
        assert isinstance(first.exception(5), Superseded) and first.exception().__traceback__ is None
        with pytest.raises(Superseded):
            first.result(5)
        for fut in queued[:-1]:
            with pytest.raises(Superseded):
                fut.result(0)
        assert w.counts["abandoned"] == 1 and w.counts["superseded"] == 19 and w.counts["max_held"] <= 2
    finally:
        w.close()


def test_worker_exports_are_not_abandoned():
    w = RenderWorker(max_exports=1)
    try:
        gate = threading.Event()

        def export(check):
            gate.wait(5)
            check()  # a no-op for exports
            return "written"

        fut = w.submit_export(export)
        from bokehray.app.view.worker import Busy

        with pytest.raises(Busy):
            for _ in range(3):
                w.submit_export(export)
        w.submit(lambda check: 1)
        gate.set()
        assert fut.result(5) == "written"
    finally:
        w.close()


# --- the server --------------------------------------------------------------------------------------
def post(url: str, body, timeout: float = 60.0):
    data = body if isinstance(body, bytes) else json.dumps(body).encode()
    req = urllib.request.Request(url, data=data, headers={"Content-Type": "application/json"}, method="POST")
    try:
        with urllib.request.urlopen(req, timeout=timeout) as r:
            return r.status, dict(r.headers), r.read()
    except urllib.error.HTTPError as e:
        return e.code, dict(e.headers), e.read()


@pytest.fixture(scope="module")
def server(session):
    with ViewServer(session) as s:
        yield s


def test_server_binds_loopback_and_serves_the_page(server):
    assert server.sock.getsockname()[0] == "127.0.0.1"
    with urllib.request.urlopen(server.url, timeout=10) as r:
        html = r.read().decode()
    assert "/static/app.js" in html and "http" not in html.replace("http-equiv", "")  # nothing external
    for name in ("app.js", "style.css"):
        with urllib.request.urlopen(server.url + "static/" + name, timeout=10) as r:
            text = r.read().decode()
        assert "http://" not in text and "https://" not in text
    info = json.loads(urllib.request.urlopen(server.url + "api/info", timeout=10).read())
    assert (info["width"], info["height"], info["proxy"]["factor"]) == (480, 320, 3)


def test_render_preview_and_full(server, session):
    x, y = subject_pixel(session.disparity)
    st, h, data = post(server.url + "api/render", {"blur": 20, "focus_at": [x, y], "stage": "preview"})
    assert st == 200 and data[:2] == b"\xff\xd8" and h["x-bokehray-factor"] == "3"
    assert float(h["x-bokehray-focus-disparity"]) == br.focus_at(session.disparity, x, y)
    import io

    from PIL import Image

    assert Image.open(io.BytesIO(data)).size == (160, 107)
    st, h, data = post(server.url + "api/render", {"blur": 20, "focus_at": [x, y], "stage": "full"})
    assert st == 200 and Image.open(io.BytesIO(data)).size == (240, 160) and h["x-bokehray-factor"] == "2"


@pytest.mark.parametrize("path", ["static/../cli.py", "static/%2e%2e%2fcli.py", "static/session.py", "api/nope"])
def test_no_file_is_served_but_the_page(server, path):
    with pytest.raises(urllib.error.HTTPError) as e:
        urllib.request.urlopen(server.url + path, timeout=10)
    assert e.value.code == 404


def test_requests_are_validated(server):
    st, _, body = post(server.url + "api/render", b"x" * 5000)
    assert st == 413
    st, _, body = post(server.url + "api/render", b"{not json")
    assert st == 400 and "JSON" in json.loads(body)["error"]
    st, _, body = post(server.url + "api/render", {"blur": 10, "focus": 0.5, "aperture": "polygon", "blades": 40})
    assert st == 400 and json.loads(body)["error"] == "aperture blades: expected 0 (disc) or 3..32, got 40"
    st, _, body = post(server.url + "api/export", {"params": {"blur": 10, "focus": 0.5}, "format": "png",
                                                    "path": "/tmp/x.png"})
    assert st == 400
    st, _, body = post(server.url + "api/export", {"params": {"blur": 10, "focus": 0.5}, "format": "bmp"})
    assert st == 400 and "export format" in json.loads(body)["error"]
    st, _, body = post(server.url + "api/export", {"params": {"blur": 10, "focus": 0.5}, "format": "jpg",
                                                    "bit_depth": 16})
    assert st == 400
    # what a page of another site can send from the user's browser: refused before anything renders
    req = urllib.request.Request(server.url + "api/export", method="POST", headers={"Content-Type": "text/plain"},
                                 data=json.dumps({"params": {"blur": 10, "focus": 0.5}}).encode())
    with pytest.raises(urllib.error.HTTPError) as e:
        urllib.request.urlopen(req, timeout=10)
    assert e.value.code == 415
    req = urllib.request.Request(server.url + "api/render", method="POST", data=b'{"blur": 10, "focus": 0.5}',
                                 headers={"Content-Type": "application/json", "Origin": "http://attacker.example"})
    with pytest.raises(urllib.error.HTTPError) as e:
        urllib.request.urlopen(req, timeout=10)
    assert e.value.code == 403
    req = urllib.request.Request(server.url + "api/info", headers={"Host": "attacker.example"})
    with pytest.raises(urllib.error.HTTPError) as e:  # DNS rebinding: only our own Host is answered
        urllib.request.urlopen(req, timeout=10)
    assert e.value.code == 400


def test_export_writes_what_the_shown_command_writes(server, session, tmp_path, capsys):
    x, y = subject_pixel(session.disparity)
    params = {"blur": 17.5, "focus_at": [x, y], "aperture": "polygon", "blades": 7, "rotation": 12.0,
              "curvature": 0.25, "highlight_boost": 2.0}
    st, _, body = post(server.url + "api/export", {"params": params, "format": "exr", "bit_depth": 32})
    assert st == 200, body
    out = json.loads(body)
    path = out["path"]
    assert path.startswith(str(session.export_dir)) and path.endswith(".exr")
    argv = shlex.split(out["command"])
    assert argv[:2] == ["bokehray", "render"] and argv[argv.index("-o") + 1] == path
    again = tmp_path / "again.exr"
    argv[argv.index("-o") + 1] = str(again)
    assert main(argv[1:] + ["--quiet"]) == 0
    np.testing.assert_array_equal(br.read_image(path), br.read_image(again))
    # a second export never overwrites the first
    st, _, body = post(server.url + "api/export", {"params": params, "format": "png", "bit_depth": 16})
    assert st == 200 and json.loads(body)["path"] != path


@pytest.mark.parametrize("rotation", [-1e-05, -1e16, -12.5, 3e-07, 0.0])
def test_the_shown_command_parses_back_to_its_rotation(session, rotation):
    """A rotation of -1e-05 (or -1e16) was shown as ``--rotation -1e-05``, which argparse takes for an option: the
    shown command did not run."""
    from bokehray.app.cli import build_parser

    p = parse_params({"blur": 10.0, "focus": 0.5, "aperture": "polygon", "rotation": rotation}, session.disparity)
    argv = shlex.split(session.command(p, "out.png"))
    args = build_parser().parse_args(argv[1:])
    assert args.rotation == rotation and args.blades == p.blades


def rss_mb() -> float:
    from bokehray.app.bench.machine import status_kb

    return (status_kb("VmRSS") or 0) / 1024


def test_rapid_requests_stay_bounded(server, session):
    """Fire requests as fast as 8 clients can; the worker never holds more than one running and one pending
    interactive job, superseded answers come back at once, the newest request gets its image, and memory
    does not grow with the number of requests."""
    x, y = subject_pixel(session.disparity)
    worker = server.worker

    def storm(n: int, offset: int) -> list[int]:
        def one(i: int) -> int:
            stage = "full" if i % 5 == 0 else "preview"
            body = {"blur": 5 + (i % 30), "focus": ((i + offset) % 97) / 96, "stage": stage}
            return post(server.url + "api/render", body)[0]

        with ThreadPoolExecutor(8) as pool:
            return list(pool.map(one, range(n)))

    storm(40, 0)  # warm up: the arrays and pools of one render are allocated
    counts0 = dict(worker.counts)
    statuses = storm(200, 1)
    after_200 = rss_mb()
    statuses += storm(400, 2)
    grown = rss_mb() - after_200  # twice the requests again: memory must not follow their number
    assert set(statuses) <= {200, 409} and statuses.count(409) > 0
    started = worker.counts["started"] - counts0["started"]
    assert started < 300, worker.counts  # most requests were superseded before they started
    assert worker.counts["max_held"] <= 3, worker.counts  # one running + one pending (+ an earlier export)
    st, h, _ = post(server.url + "api/render", {"blur": 12, "focus_at": [x, y], "stage": "preview"})
    assert st == 200 and float(h["x-bokehray-k"]) == 12.0
    assert worker.queued() == 0
    assert grown < 40, f"RSS grew {grown:.0f} MB over the last 400 requests ({worker.counts})"


# --- the command line --------------------------------------------------------------------------------
def test_cli_bad_inputs_are_one_line(scene_files, tmp_path, capsys):
    _, img, disp, _ = scene_files
    for argv in (["view", str(tmp_path / "missing.png"), "--disparity", str(disp)],
                 ["view", str(img), "--disparity", str(disp), "--port", "70000"],
                 ["view", str(img), "--disparity", str(disp), "--export-dir", str(tmp_path / "nope")],
                 ["view", str(img), "--disparity", str(disp), "--proxy-size", "4"]):
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert err.startswith("bokehray: error: ") and err.count("\n") == 1 and "Traceback" not in err


def test_cli_port_in_use_is_one_line(scene_files, server, capsys):
    _, img, disp, _ = scene_files
    assert main(["view", str(img), "--disparity", str(disp), "--port", str(server.port)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"bokehray: error: --port {server.port}: cannot listen") and err.count("\n") == 1


def test_the_page_offers_no_ray_tracer_for_photos(server):
    """On photos the ray tracer is slower than the preview and not more accurate (docs/raytracer.md): the page
    offers the preview alone, and a ray-traced export is refused with the pointer the command line gives."""
    info = json.loads(urllib.request.urlopen(server.url + "api/info", timeout=10).read())
    assert info["qualities"] == ["preview"]
    st, _, body = post(server.url + "api/export", {"params": {"blur": 8.0, "focus": 0.5, "quality": "raytrace"},
                                                   "format": "exr"})
    assert st == 400 and "--quality raytrace: on photos the ray tracer is slower" in json.loads(body)["error"]


def test_depth_map_session_and_its_command(scene_files, tmp_path):
    """--depth: the same min-max normalisation as `bokehray render --depth`, and a command that says --depth."""
    _, img, _, sc = scene_files
    depth = (1.0 / (0.2 + sc.disparity)).astype(np.float32)  # metres; nearer = larger disparity
    dpath = tmp_path / "depth.exr"
    br.write_image(dpath, depth[..., None])
    out_dir = tmp_path / "exports"
    out_dir.mkdir()
    s = ViewSession.from_files(str(img), depth=str(dpath), export_dir=out_dir, proxy_long_side=160)
    expected, _ = br.disparity_from_depth(br.read_depth(dpath))
    np.testing.assert_array_equal(s.disparity, expected)
    p = parse_params({"blur": 12.0, "focus_at": list(subject_pixel(sc.disparity))}, s.disparity)
    path, command = s.export(p, "exr", 32)
    argv = shlex.split(command)
    assert argv[argv.index("--depth") + 1] == str(dpath.resolve())
    again = tmp_path / "again.exr"
    argv[argv.index("-o") + 1] = str(again)
    assert main(argv[1:] + ["--quiet"]) == 0
    np.testing.assert_array_equal(br.read_image(path), br.read_image(again))


def test_info_of_a_depth_map_with_sky_is_json(scene_files, tmp_path):
    """A metric depth map with sky (+Inf, which `render --depth` takes) made /api/info a 500: its farthest depth and
    the normalisation's far end are infinite, and JSON has no infinity. They are null now (the page: Infinity)."""
    _, img, _, sc = scene_files
    depth = (1.0 / (0.2 + sc.disparity)).astype(np.float32)
    depth[:20] = np.inf  # the sky
    dpath = tmp_path / "depth.npy"
    np.save(dpath, depth)
    s = ViewSession.from_files(str(img), depth=str(dpath), export_dir=tmp_path, proxy_long_side=64)
    with ViewServer(s) as server, urllib.request.urlopen(server.url + "api/info", timeout=60) as r:
        metric = json.loads(r.read())["metric"]
    assert metric["farthest_m"] is None and metric["z_far_m"] is None
    assert metric["nearest_m"] == pytest.approx(float(depth.min()))

@pytest.mark.slow
def test_cli_serves_until_interrupted(scene_files, tmp_path):
    """`bokehray view` prints its 127.0.0.1 URL, serves the page, and stops cleanly on Ctrl-C (SIGINT)."""
    import os
    import signal
    import subprocess
    import sys

    _, img, disp, _ = scene_files
    code = "import sys; from bokehray.app.cli import main; sys.exit(main())"
    proc = subprocess.Popen([sys.executable, "-c", code, "view", str(img), "--disparity", str(disp),
                             "--export-dir", str(tmp_path)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        line = proc.stdout.readline()
        assert line.startswith("bokehray view: http://127.0.0.1:"), line
        url = line.split()[2]
        info = json.loads(urllib.request.urlopen(url + "api/info", timeout=30).read())
        assert info["width"] == 480 and info["export_dir"] == str(tmp_path.resolve())
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 130, err  # stopped by Ctrl-C: 128 + SIGINT, as `render` exits
    assert "Traceback" not in err and "stopped" in err


def test_an_export_whose_name_another_process_takes_meanwhile_writes_the_next_free_name(session, monkeypatch):
    """Two views exporting to one folder both choose the first free name; the one that finishes second writes the
    next free name instead of replacing the other's file."""
    fmt = "png"
    taken = session.export_path(fmt)
    render_full = session.render_full

    def render_while_another_exports(p, check=None):
        taken.write_bytes(b"the other view's export")
        return render_full(p, check)

    monkeypatch.setattr(session, "render_full", render_while_another_exports)
    written, command = session.export(parse_params({"blur": 6.0}, session.disparity), fmt, None)
    assert taken.read_bytes() == b"the other view's export"
    assert Path(written) != taken and Path(written).parent == taken.parent and str(written) in command
    assert br.read_image(written).shape[:2] == session.image.shape[:2]


def test_the_next_export_name_skips_a_dangling_link(session):
    first = session.export_path("tif")
    first.symlink_to(first.parent / "gone.tif")
    try:
        assert session.export_path("tif") not in (first,) and not session.export_path("tif").is_symlink()
    finally:
        first.unlink()
