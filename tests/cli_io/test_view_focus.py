"""bokehray view in a photographer's words: the focused region at screen size before the rest, the focus said in
words (what, near / far, metres), the shown command following the export's format, an export of a photo with grain
equal to its command."""

from __future__ import annotations

import io
import json
import shlex
import urllib.error
import urllib.request
from urllib.parse import unquote

import numpy as np
import pytest

pytest.importorskip("starlette", reason="bokehray view needs the 'view' extra (starlette, uvicorn)")
pytest.importorskip("uvicorn", reason="bokehray view needs the 'view' extra (starlette, uvicorn)")

import skimage.data
from PIL import Image

import bokehray as br
from bokehray.app.cli import main
from bokehray.app.demo import build_demo_scene
from bokehray.app.view.server import ViewServer
from bokehray.app.view.session import ProxyLadder, ViewSession


def post(url: str, body):
    req = urllib.request.Request(url, data=json.dumps(body).encode(), headers={"Content-Type": "application/json"},
                                 method="POST")
    try:
        with urllib.request.urlopen(req, timeout=60) as r:
            return r.status, {k.lower(): v for k, v in r.headers.items()}, r.read()
    except urllib.error.HTTPError as e:
        return e.code, {}, e.read()


@pytest.fixture(scope="module")
def portrait(tmp_path_factory):
    """The astronaut (a face) as an 8-bit PNG with grain, a map with the head behind the chest, a session."""
    d = tmp_path_factory.mktemp("view-focus")
    codes = skimage.data.astronaut().astype(np.float64)
    codes = np.clip(np.round(codes + np.random.default_rng(0).normal(0, 1.5, codes.shape)), 0, 255)
    Image.fromarray(codes.astype(np.uint8)).save(d / "photo.png")
    disp = np.full((512, 512), 0.1, np.float32)
    disp[200:, 20:370] = 0.859
    disp[10:200, 150:305] = 0.839
    br.write_disparity(d / "disp.png", disp)
    (d / "exports").mkdir()
    s = ViewSession.from_files(str(d / "photo.png"), disparity=str(d / "disp.png"), export_dir=d / "exports",
                               proxy_long_side=128, display_long_side=256)
    s.ladder = ProxyLadder(1)
    return d, s


@pytest.fixture(scope="module")
def server(portrait):
    with ViewServer(portrait[1]) as s:
        yield s


def test_the_default_focus_is_the_eyes_and_said_so(portrait):
    _, s = portrait
    p = s.parse({})
    x, y = s.focus_point(p)
    assert abs(x - 224) <= 10 and abs(y - 101) <= 10  # between the astronaut's eyes
    assert p.blur.focus_disparity == pytest.approx(0.839, abs=1e-3)
    assert s.focus_words(p) == "the eyes of the nearest face (near)"
    assert s.info()["defaults"]["subject"]["words"] == "the eyes of the nearest face"
    assert s.focus_words(s.parse({"focus_at": [20, 20]})) == "the point you clicked (far)"


def test_the_focus_in_metres_for_a_metric_map(tmp_path):
    sc = build_demo_scene(width=240, height=160)
    br.write_image(tmp_path / "photo.exr", sc.image)
    br.write_image(tmp_path / "depth.exr", (1.0 / (0.2 + sc.disparity)).astype(np.float32)[..., None])
    s = ViewSession.from_files(str(tmp_path / "photo.exr"), depth=str(tmp_path / "depth.exr"), export_dir=tmp_path,
                               proxy_long_side=120)
    words = s.focus_words(s.parse({}))
    z = float(s.norm.depth(s.subject.d_f))
    assert words == f"the subject (near, {z:.3g} m away)"


def _detail(img: np.ndarray) -> float:
    g = img.mean(axis=2)
    return float(np.abs(np.diff(g, axis=0)).mean() + np.abs(np.diff(g, axis=1)).mean())


def test_the_focus_crop_shows_the_focused_region_as_sharp_as_the_sharp_version():
    """The crop is rendered at the sharp version's size on a window reaching the largest CoC beyond it, on its
    pixel grid: it has the sharp version's detail where the proxy the page stretches has lost it, and shows the
    same picture (a few codes apart: the window's own depth range slices its layers a little differently)."""
    sc = build_demo_scene(width=960, height=640)
    s = ViewSession(sc.image, sc.disparity, proxy_long_side=160, display_long_side=640)
    for body in ({}, {"focus_at": [200, 500], "amount": 80}, {"focus": 0.3}):
        p = s.parse(body)
        crop, meta = s.focus_crop(p, half=64)
        full, fmeta = s.full_display(p)
        preview, pmeta = s.render_preview(p)
        f = meta["factor"]
        assert f == fmeta["factor"] == 2 and pmeta["factor"] == 6
        x0, y0, x1, y1 = (v // f for v in meta["crop"])
        assert (x1 - x0, y1 - y0) == (128, 128)
        fx, fy = s.focus_point(p)
        assert meta["crop"][0] <= fx < meta["crop"][2] and meta["crop"][1] <= fy < meta["crop"][3]
        a = np.asarray(Image.open(io.BytesIO(crop)), np.float64)
        sharp = np.asarray(Image.open(io.BytesIO(full)), np.float64)
        b = sharp[y0:y1, x0:x1]
        dy = 8 if y1 + 8 <= sharp.shape[0] else -8
        dx = 8 if x1 + 8 <= sharp.shape[1] else -8
        shifted = sharp[y0 + dy : y1 + dy, x0 + dx : x1 + dx]  # the same region 8 px off
        diff = np.abs(a - b).mean()
        assert diff < 4.0 and diff < 0.5 * np.abs(a - shifted).mean(), (body, diff)
        stretched = np.asarray(Image.open(io.BytesIO(preview)).resize((sharp.shape[1], sharp.shape[0]),
                                                                       Image.BILINEAR), np.float64)[y0:y1, x0:x1]
        assert _detail(a) >= 0.9 * _detail(b), body
        if body.get("focus") is None:  # something is in focus there: the stretched proxy has lost its detail
            assert _detail(stretched) < 0.7 * _detail(b), body


def test_the_server_answers_the_focus_stage_with_where_it_goes(server, portrait):
    _, s = portrait
    st, h, data = post(server.url + "api/render", {"stage": "focus", "long_side": 256})
    assert st == 200 and data[:2] == b"\xff\xd8"
    x0, y0, x1, y1 = map(int, h["x-bokehray-crop"].split(","))
    assert 0 <= x0 < x1 <= s.w and 0 <= y0 < y1 <= s.h
    assert Image.open(io.BytesIO(data)).size == ((x1 - x0) // 2, (y1 - y0) // 2)
    assert unquote(h["x-bokehray-focus-words"]) == "the eyes of the nearest face (near)"


def test_the_shown_command_follows_the_chosen_export_format(server):
    st, h, _ = post(server.url + "api/render", {"stage": "preview"})
    assert st == 200 and " -o OUTPUT.png" in unquote(h["x-bokehray-command"])
    st, h, _ = post(server.url + "api/render", {"stage": "preview", "format": "jpg", "bit_depth": 8})
    command = unquote(h["x-bokehray-command"])
    assert st == 200 and " -o OUTPUT.jpg" in command and "--bit-depth 8" in command
    st, h, _ = post(server.url + "api/render", {"stage": "preview", "format": "tif", "bit_depth": 32})
    assert st == 200 and " -o OUTPUT.tif" in unquote(h["x-bokehray-command"])
    st, _, body = post(server.url + "api/render", {"stage": "preview", "format": "bmp"})
    assert st == 400 and "export format" in json.loads(body)["error"]
    st, _, body = post(server.url + "api/render", {"stage": "preview", "format": "jpg", "bit_depth": 16})
    assert st == 400 and "--bit-depth" in json.loads(body)["error"]


@pytest.mark.parametrize("fmt", ["jpg", "png"])
def test_an_export_with_grain_is_what_its_command_writes(server, portrait, tmp_path, fmt):
    """A display-referred photo: the export restores the grain as `render` does (seeded), eyes focus by default."""
    _, s = portrait
    st, _, body = post(server.url + "api/export", {"params": {"amount": 60}, "format": fmt, "bit_depth": 8})
    assert st == 200, body
    out = json.loads(body)
    argv = shlex.split(out["command"])
    assert "--no-grain" not in argv and "--focus" not in argv and "--focus-at" not in argv
    again = tmp_path / f"again.{fmt}"
    argv[argv.index("-o") + 1] = str(again)
    assert main(argv[1:] + ["--quiet"]) == 0
    np.testing.assert_array_equal(np.asarray(Image.open(out["path"])), np.asarray(Image.open(again)))
    with_grain = np.asarray(Image.open(out["path"]), np.float64)
    clean = s.render_full(s.parse({"amount": 60}))
    assert not np.array_equal(with_grain, np.round(br.colour.linear_to_srgb(np.clip(clean, 0, 1)) * 255))


def test_an_export_without_grain_says_no_grain_in_its_command(server, tmp_path):
    st, _, body = post(server.url + "api/export", {"params": {"amount": 60, "grain": False}, "format": "png",
                                                  "bit_depth": 8})
    assert st == 200, body
    out = json.loads(body)
    argv = shlex.split(out["command"])
    assert "--no-grain" in argv
    again = tmp_path / "again.png"
    argv[argv.index("-o") + 1] = str(again)
    assert main(argv[1:] + ["--quiet"]) == 0
    np.testing.assert_array_equal(np.asarray(Image.open(out["path"])), np.asarray(Image.open(again)))
    st, _, body = post(server.url + "api/render", {"stage": "preview", "grain": "yes"})
    assert st == 400 and "grain: expected true or false" in json.loads(body)["error"]


@pytest.mark.parametrize("f", [2, 3])
def test_a_first_focus_crop_reduces_its_window_alone_and_agrees_with_the_screen_arrays(portrait, f):
    """Before the sharp version has reduced the whole photo for the screen, the focus crop reduces only its window
    (a first click waited for the whole frame's reduction); block-aligned, the window equals that slice of the
    whole frame's reduction, the frame's last partial block included."""
    _, s = portrait
    s._screen = None
    h, w = -(-s.h // f), -(-s.w // f)
    box = (16, h, 32, w)  # reaching the frame's bottom and right edges
    alone = s._screen_window(f, False, box)
    assert s._screen is None  # the whole frame was not reduced for it
    whole = s._screen_window(f, False, (0, h, 0, w))  # the uncached path, on the whole frame
    s._screen_arrays(f, False)  # the sharp version's arrays, cached
    sliced = s._screen_window(f, False, box)
    for a, b, c in zip(alone, sliced, whole):
        np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-7)
        np.testing.assert_allclose(a, c[box[0]:, box[2]:], rtol=1e-6, atol=1e-7)
