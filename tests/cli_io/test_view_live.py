"""bokehray view stays live and speaks render's language: the worker's order (a preview is never cancelled by a
refinement; an export serves the page between its layers), the sharp version at the screen's size, the proxy
ladder's timings, and the page's defaults and exports equal to `bokehray render`'s (EXIF included)."""

from __future__ import annotations

import io
import json
import shlex
import threading
import urllib.error
import urllib.request

import numpy as np
import pytest

pytest.importorskip("starlette", reason="bokehray view needs the 'view' extra (starlette, uvicorn)")
pytest.importorskip("uvicorn", reason="bokehray view needs the 'view' extra (starlette, uvicorn)")

from tolerances import HANG_S

import bokehray as br
from bokehray.app.cli import main
from bokehray.app.demo import build_demo_scene
from bokehray.app.view.server import ViewServer
from bokehray.app.view.session import ProxyLadder, ViewSession
from bokehray.app.view.worker import RenderWorker, Superseded


# --- the worker's order --------------------------------------------------------------------------------
def _gated(gate: threading.Event, started: threading.Event, value):
    def job(check):
        started.set()
        while not gate.wait(0.01):
            check()
        check()
        return value
    return job


def test_a_refinement_never_cancels_a_running_preview():
    w = RenderWorker()
    try:
        gate, started = threading.Event(), threading.Event()
        prev = w.submit(_gated(gate, started, "preview"), "preview")
        assert started.wait(HANG_S)
        full = w.submit(lambda check: "full", "full")
        gate.set()
        assert prev.result(HANG_S) == "preview" and full.result(HANG_S) == "full"
        assert w.counts["abandoned"] == 0
    finally:
        w.close()


def test_a_preview_supersedes_the_running_and_pending_refinement_and_runs_first():
    w = RenderWorker()
    try:
        gate, started = threading.Event(), threading.Event()
        full = w.submit(_gated(gate, started, "full"), "full")
        assert started.wait(HANG_S)
        order = []
        prev = w.submit(lambda check: order.append("preview") or "p", "preview")
        assert prev.result(HANG_S) == "p"
        with pytest.raises(Superseded):
            full.result(HANG_S)
        # a pending refinement is dropped by a newer preview (it belongs to an older state)
        gate2, started2 = threading.Event(), threading.Event()
        blocker = w.submit(_gated(gate2, started2, "b"), "preview")
        assert started2.wait(HANG_S)
        stale_full = w.submit(lambda check: "stale", "full")
        newer = w.submit(lambda check: "newer", "preview")  # supersedes the running preview and the pending full
        gate2.set()
        with pytest.raises(Superseded):
            stale_full.result(HANG_S)
        with pytest.raises(Superseded):
            blocker.result(HANG_S)
        assert newer.result(HANG_S) == "newer"
    finally:
        w.close()


def test_an_export_serves_previews_at_its_checks_and_is_not_abandoned():
    w = RenderWorker()
    try:
        gate, started = threading.Event(), threading.Event()
        export = w.submit_export(_gated(gate, started, "written"))
        assert started.wait(HANG_S)
        prev = w.submit(lambda check: "preview", "preview")
        assert prev.result(HANG_S) == "preview"  # answered while the export still runs
        assert not export.done() and w.progress()["running"][0]["kind"] == "export"
        gate.set()
        assert export.result(HANG_S) == "written" and w.counts["inline"] == 1
    finally:
        w.close()


def test_the_ladder_learns_from_a_slow_abandoned_preview(tmp_path):
    sc = build_demo_scene(width=240, height=160)
    s = ViewSession(sc.image, sc.disparity, proxy_long_side=120)
    s.ladder = ProxyLadder(len(s.proxies), budget_s=-1.0)  # every render is over the budget

    def abandon(done=None, total=None):
        if done is not None:
            raise Superseded()

    with pytest.raises(Superseded):
        s.render_preview(s.parse({}), abandon)
    assert s.ladder.level == 1  # the abandoned render's time moved the ladder


# --- the sharp version at the screen's size -----------------------------------------------------------
@pytest.fixture(scope="module")
def photo(tmp_path_factory):
    """A JPEG as a phone writes it: EXIF orientation 6 and a camera make; the map painted upright."""
    from PIL import Image

    d = tmp_path_factory.mktemp("view-live")
    sc = build_demo_scene(width=240, height=160)
    upright = (np.clip(sc.image, 0, 1) ** (1 / 2.2) * 255 + 0.5).astype(np.uint8)
    stored = np.ascontiguousarray(np.rot90(upright, 1))  # orientation 6: the reader turns it clockwise
    exif = Image.Exif()
    exif[0x0112] = 6
    exif[0x010F] = "TestCam"
    Image.fromarray(stored).save(d / "phone.jpg", quality=92, exif=exif.tobytes())
    br.write_disparity(d / "d.png", sc.disparity)
    (d / "exports").mkdir()
    return d


@pytest.fixture(scope="module")
def served(photo):
    s = ViewSession.from_files(str(photo / "phone.jpg"), disparity=str(photo / "d.png"),
                               export_dir=photo / "exports", proxy_long_side=80, display_long_side=200)
    s.ladder = ProxyLadder(1)
    with ViewServer(s) as srv:
        yield srv, s


def post(url: str, body: dict):
    req = urllib.request.Request(url, data=json.dumps(body).encode(), headers={"Content-Type": "application/json"},
                                 method="POST")
    try:
        with urllib.request.urlopen(req, timeout=HANG_S) as r:
            return r.status, dict(r.headers), r.read()
    except urllib.error.HTTPError as e:
        return e.code, dict(e.headers), e.read()


def test_the_sharp_version_is_rendered_at_the_size_the_screen_shows(served):
    from PIL import Image

    server, s = served
    for long_side, factor in ((60, 4), (120, 2), (200, 2), (240, 1), (10**6, 1)):
        st, h, data = post(server.url + "api/render", {"stage": "full", "long_side": long_side})
        assert st == 200 and int(h["x-bokehray-factor"]) == factor == s.screen_factor(long_side)
        assert Image.open(io.BytesIO(data)).size == (-(-240 // factor), -(-160 // factor))
    # the CoC scales with it: the reduced sharp version approximates the full render reduced alike
    p = s.parse({})
    full = s.render_full(p)
    from bokehray.app.view.session import box_reduce, encode_jpeg, to_srgb8  # noqa: F401

    data, _meta = s.full_display(p, None, 120)
    got = np.asarray(Image.open(io.BytesIO(data)), np.float32) / 255
    want = to_srgb8(box_reduce(full, 2)).astype(np.float32) / 255
    psnr = -10 * np.log10(np.mean((got - want) ** 2))
    assert psnr > 28, psnr


def test_the_page_starts_from_what_render_does(served, tmp_path, capsys):
    server, s = served
    info = json.loads(urllib.request.urlopen(server.url + "api/info", timeout=HANG_S).read())
    assert info["defaults"]["amount"] == 50 and info["defaults"]["reconstruct"] is True  # a JPEG: display-referred
    assert info["defaults"]["focus"] == s.subject.d_f
    st, h, _ = post(server.url + "api/render", {"stage": "preview"})
    assert st == 200 and float(h["x-bokehray-focus-disparity"]) == s.subject.d_f
    assert float(h["x-bokehray-amount"]) == 50
    # render with only the files says the same focus and blur
    assert main(["render", str(s.image_path), "--disparity", str(s.disparity_path), "-o", str(tmp_path / "r.png")]) == 0
    out = capsys.readouterr().out
    assert f"d_f = {s.subject.d_f:.4f}" in out and f"K = {float(h['x-bokehray-k']):.3f} px" in out


@pytest.mark.parametrize("params", [{}, {"amount": 80, "focus_at": [100, 60], "reconstruct": False},
                                    {"blur": 7.5, "focus": 0.4, "highlight_boost": 2.0}])
def test_a_jpeg_export_is_the_printed_commands_file_byte_for_byte(served, tmp_path, params):
    """EXIF included: the issue's page dropped the camera EXIF that `render` keeps."""
    from PIL import Image

    server, _s = served
    st, _, body = post(server.url + "api/export", {"params": params, "format": "jpg"})
    assert st == 200, body
    out = json.loads(body)
    argv = shlex.split(out["command"])
    if not params:  # render's defaults: nothing to say
        assert not {"--blur", "--amount", "--focus", "--focus-at", "--no-highlight-reconstruction"} & set(argv)
    again = tmp_path / "again.jpg"
    argv[argv.index("-o") + 1] = str(again)
    assert main(argv[1:] + ["--quiet"]) == 0
    assert again.read_bytes() == open(out["path"], "rb").read()
    with Image.open(out["path"]) as im:
        assert im.getexif().get(0x010F) == "TestCam" and im.getexif().get(0x0112, 1) == 1


# --- metric depth: the photographer's lens -----------------------------------------------------------
@pytest.fixture(scope="module")
def metric(tmp_path_factory):
    d = tmp_path_factory.mktemp("view-metric")
    sc = build_demo_scene(width=240, height=160)
    br.write_image(d / "photo.exr", sc.image)
    depth = (1.0 / (0.2 + sc.disparity)).astype(np.float32)  # 0.9 .. 5 m; nearer = larger disparity
    br.write_image(d / "depth.exr", depth[..., None])
    (d / "exports").mkdir()
    s = ViewSession.from_files(str(d / "photo.exr"), depth=str(d / "depth.exr"), export_dir=d / "exports",
                               proxy_long_side=80, display_long_side=200)
    return s, depth


@pytest.mark.parametrize("params", [
    {"lens": {"focal_length": 50, "f_number": 1.8, "focus_distance": 1.1}},
    {"lens": {"focal_length": 85, "f_number": 2.8, "sensor_width": 24}, "focus_at": [150, 70]},
])
def test_a_metric_session_offers_a_lens_and_exports_what_its_command_writes(metric, tmp_path, params):
    s, depth = metric
    info = s.info()
    assert info["metric"]["nearest_m"] == pytest.approx(float(depth.min()), rel=1e-4)
    assert info["metric"]["farthest_m"] == pytest.approx(float(depth.max()), rel=1e-4)
    p = s.parse(params)
    want_z = params["lens"].get("focus_distance") or float(s.norm.depth(br.focus_at(s.disparity, 150, 70)))
    assert p.thin_lens.focus_distance_m == pytest.approx(want_z)
    assert float(s.norm.depth(p.blur.focus_disparity)) == pytest.approx(want_z, rel=1e-5)
    path, command = s.export(p, "exr", 32)
    argv = shlex.split(command)
    assert "--f-number" in argv and "--blur" not in argv and "--amount" not in argv
    again = tmp_path / "again.exr"
    argv[argv.index("-o") + 1] = str(again)
    assert main(argv[1:] + ["--quiet"]) == 0
    assert again.read_bytes() == path.read_bytes()


def test_a_lens_without_metric_depth_is_refused_as_render_refuses_it(served, metric):
    from bokehray.errors import InputError

    _, s = served
    with pytest.raises(InputError, match="needs metric depth"):
        s.parse({"lens": {"focal_length": 50, "f_number": 2, "focus_distance": 2}})
    m, _ = metric
    for bad, message in (({"lens": {"focal_length": 50, "f_number": 2}}, "--focus-distance or --focus-at"),
                         ({"lens": {"focal_length": 50, "f_number": 2, "focus_distance": 2}, "amount": 30},
                          "not both"),
                         ({"lens": {"f_number": 2, "focus_distance": 2}}, "both --focal-length and --f-number"),
                         ({"lens": {"focal_length": 50, "f_number": 2, "focus_distance": 0.01}}, "closer than")):
        with pytest.raises(InputError, match=message):
            m.parse(bad)


def test_a_preview_run_inside_an_export_leaves_the_export_as_its_command_writes_it(metric, tmp_path):
    """The preview renderer runs re-entrantly at an export's check; the export must come out byte for byte."""
    s, _ = metric
    w = RenderWorker()
    try:
        p = s.parse({"amount": 60, "focus_at": [150, 70]})
        started, submitted = threading.Event(), threading.Event()

        def export(check):
            def chk(done=None, total=None):
                check(done, total)
                started.set()
                if submitted.wait(HANG_S):
                    check()  # the preview submitted meanwhile runs here, inside the export's progress call
            return s.export(p, "exr", 32, chk)

        fut = w.submit_export(export)
        assert started.wait(HANG_S)
        prev = w.submit(lambda check: s.render_preview(s.parse({"amount": 20}), check), "preview")
        submitted.set()
        data, _meta = prev.result(HANG_S)
        assert data[:2] == b"\xff\xd8"
        path, command = fut.result(HANG_S)
        assert w.counts["inline"] == 1
    finally:
        w.close()
    argv = shlex.split(command)
    again = tmp_path / "again.exr"
    argv[argv.index("-o") + 1] = str(again)
    assert main(argv[1:] + ["--quiet"]) == 0
    assert again.read_bytes() == path.read_bytes()


def test_the_sharp_render_reports_its_progress(served):
    _, s = served
    w = RenderWorker()
    try:
        seen, gate, first = [], threading.Event(), threading.Event()

        def job(check):
            def chk(done=None, total=None):
                check(done, total)
                if done is not None:
                    seen.append((done, total))
                    if len(seen) == 1:
                        first.set()
                        gate.wait(HANG_S)
            return s.full_display(s.parse({"amount": 70}), chk, 120)

        fut = w.submit(job, "full")
        assert first.wait(HANG_S)  # the render reports after its first layer
        running = w.progress()["running"]
        assert running[0]["kind"] == "full" and running[0]["total"] > 0 and running[0]["done"] == seen[0][0]
        gate.set()
        fut.result(HANG_S)
        assert seen[-1][0] == seen[-1][1] and len(seen) > 1  # every layer reported, to the last
    finally:
        w.close()
