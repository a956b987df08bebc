"""bokehray view in a real browser: headless Chromium from the system packages, driven by Selenium.

Loads the page, clicks the subject, checks the focus moved there and a new image arrived, drags the blur
slider, shows the in-focus overlay, exports. Nothing is downloaded: the test uses /usr/bin/chromium and its
chromedriver (Debian ``chromium`` + ``chromium-driver``, installed by ``.ci/run``) and skips, saying so,
where they are missing. ``BOKEHRAY_VIEW_SCREENSHOT=FILE`` saves a screenshot of the page (docs/img/view.png).
"""

from __future__ import annotations

import os
import shlex
import shutil
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("starlette", reason="bokehray view needs the 'view' extra (starlette, uvicorn)")
pytest.importorskip("uvicorn", reason="bokehray view needs the 'view' extra (starlette, uvicorn)")
pytest.importorskip("selenium", reason="the browser test needs selenium (the 'test-browser' extra)")

import bokehray as br
from bokehray.app.demo import build_demo_scene
from bokehray.app.view.server import ViewServer
from bokehray.app.view.session import ViewSession

CHROMIUM = next((p for p in map(shutil.which, ("chromium", "chromium-browser")) if p), None)
DRIVER = shutil.which("chromedriver")
if CHROMIUM is None or DRIVER is None:
    pytest.skip("headless Chromium is not installed here (apt-get install chromium chromium-driver; .ci/run "
                "does it on a machine where apt works)", allow_module_level=True)

from selenium import webdriver  # noqa: E402
from selenium.webdriver.chrome.options import Options  # noqa: E402
from selenium.webdriver.chrome.service import Service  # noqa: E402
from selenium.webdriver.common.action_chains import ActionChains  # noqa: E402
from selenium.webdriver.common.by import By  # noqa: E402
from selenium.webdriver.support.ui import WebDriverWait  # noqa: E402
from tolerances import HANG_S  # noqa: E402

pytestmark = pytest.mark.slow  # processes, signals, a browser: seconds each


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    d = tmp_path_factory.mktemp("view-browser")
    sc = build_demo_scene(width=960, height=640)
    img, disp = d / "photo.png", d / "disparity.png"
    br.write_image(img, sc.image)
    br.write_disparity(disp, sc.disparity)
    (d / "exports").mkdir()
    session = ViewSession.from_files(str(img), disparity=str(disp), export_dir=d / "exports", proxy_long_side=480)
    with ViewServer(session) as server:
        yield server, session


@pytest.fixture(scope="module")
def browser():
    opts = Options()
    opts.binary_location = CHROMIUM
    for a in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage", "--window-size=1400,1100",
              "--force-device-scale-factor=1", "--disable-extensions", "--no-first-run"):
        opts.add_argument(a)
    drv = webdriver.Chrome(service=Service(DRIVER), options=opts)
    drv.set_page_load_timeout(30)
    yield drv
    drv.quit()


def body(drv, name: str) -> str | None:
    return drv.find_element(By.TAG_NAME, "body").get_attribute(f"data-{name}")


def count(drv, name: str) -> int:
    return int(body(drv, name) or 0)


def wait(drv, cond) -> None:
    WebDriverWait(drv, HANG_S).until(cond)  # a hang detector: a loaded machine may take long, never fails for it


def wait_sharp(drv) -> None:
    """Until the sharp version of the latest state is on screen."""
    wait(drv, lambda d: body(d, "state") == "idle" and body(d, "stage") == "full"
         and body(d, "shown-version") == body(d, "version"))


def canvas_sum(drv) -> list[int]:
    return drv.execute_script(
        "const c = document.getElementById('view'); const a = c.getContext('2d').getImageData(0, 0, c.width, "
        "c.height).data; const s = [0, 0, 0]; for (let i = 0; i < a.length; i += 4) { s[0] += a[i]; "
        "s[1] += a[i + 1]; s[2] += a[i + 2]; } return s;")


def test_click_drag_export_in_chromium(served, browser):
    server, session = served
    drv = browser
    drv.get(server.url)
    wait(drv, lambda d: count(d, "previews") >= 1)  # a proxy first
    wait_sharp(drv)
    assert drv.find_element(By.ID, "error").text == ""
    # the start is what `bokehray render` does with the same inputs: amount 50, the subject, reconstruction
    d_before = float(body(drv, "focus-disparity"))
    assert d_before == session.subject.d_f
    command = drv.find_element(By.ID, "command").text
    assert "--blur" not in command and "--focus" not in command and "--no-highlight" not in command

    # click on the cat (disparity 0.92 at its centre): a proxy of the new state, then the sharp version
    ys, xs = np.nonzero(np.abs(session.disparity - 0.92) < 0.004)
    x, y = int(np.median(xs)), int(np.median(ys))
    canvas = drv.find_element(By.ID, "view")
    cw, ch = drv.execute_script("const c = arguments[0]; return [c.clientWidth, c.clientHeight];", canvas)
    drv.execute_script("document.getElementById('show').value = 'render';")
    before, n_prev = canvas_sum(drv), count(drv, "previews")
    ActionChains(drv).move_to_element_with_offset(canvas, int((x + 0.5) / session.w * cw - cw / 2),
                                                  int((y + 0.5) / session.h * ch - ch / 2)).click().perform()
    wait(drv, lambda d: count(d, "previews") > n_prev)
    assert canvas_sum(drv) != before  # the picture changed with the proxy
    wait_sharp(drv)
    cx, cy = (int(v) for v in body(drv, "focus-at").split(","))
    assert abs(cx - x) <= 2 and abs(cy - y) <= 2
    d_after = float(body(drv, "focus-disparity"))
    assert d_after == pytest.approx(br.focus_at(session.disparity, cx, cy), abs=1e-12)
    assert abs(d_after - 0.92) < 0.01
    assert f"--focus-at {cx},{cy}" in drv.find_element(By.ID, "command").text

    # drag the blur amount: previews while dragging, then the sharp version
    slider = drv.find_element(By.ID, "amount")
    a_before = float(slider.get_attribute("value"))
    n_prev = count(drv, "previews")
    ActionChains(drv).click_and_hold(slider).move_by_offset(40, 0).move_by_offset(20, 0).release().perform()
    wait(drv, lambda d: count(d, "previews") > n_prev)
    wait_sharp(drv)
    a_after = float(slider.get_attribute("value"))
    assert a_after > a_before
    assert f"--amount {float(a_after)!r}" in drv.find_element(By.ID, "command").text
    k_after = float(body(drv, "k"))

    # the in-focus region: drawn where the CoC is below one pixel, i.e. on the cat
    drv.find_element(By.ID, "infocus").click()
    covered = drv.execute_script(
        "const o = document.getElementById('overlay'); const a = o.getContext('2d').getImageData(0, 0, o.width, "
        "o.height).data; let n = 0; for (let i = 3; i < a.length; i += 4) n += a[i] > 0; return n / (a.length / 4);")
    inside = np.mean(np.abs(session.disparity - d_after) * k_after < 1.0)
    assert covered == pytest.approx(inside, abs=0.02) and covered > 0.01

    # a bladed aperture (a select, then the rotation slider): a proxy, then the sharp version again
    n_prev = count(drv, "previews")
    drv.execute_script("const a = document.getElementById('aperture'); a.value = 'polygon'; "
                       "a.dispatchEvent(new Event('change'));")
    ActionChains(drv).click_and_hold(drv.find_element(By.ID, "rotation")).move_by_offset(12, 0).release().perform()
    wait(drv, lambda d: count(d, "previews") > n_prev)
    wait_sharp(drv)
    assert "--aperture polygon --blades 6" in drv.find_element(By.ID, "command").text
    assert drv.find_element(By.ID, "error").text == ""

    # every sharp version shown followed the preview of its own state (the full never came first)
    shown = drv.execute_script("return window.bokehrayShown;")
    previews = {v for stage, v in shown if stage == "preview"}
    seen = set()
    for stage, v in shown:
        if stage == "full":
            assert v in previews and v in seen, shown
        seen.add(v)
    # the sharp version was rendered at the size the canvas shows, not at the photo's
    long_side = drv.execute_script("const c = document.getElementById('view'); return Math.round(Math.max("
                                   f"{session.w}, {session.h}) * Math.min(1, c.clientWidth * devicePixelRatio / "
                                   f"{session.w}));")
    assert int(body(drv, "factor")) == session.screen_factor(max(16, long_side))

    # export a 16-bit PNG; the page shows the path and the command that writes the same file
    drv.execute_script("const f = document.getElementById('format'); f.value = 'png'; "
                       "f.dispatchEvent(new Event('change'));")
    drv.execute_script("document.getElementById('bit_depth').value = '16';")
    drv.find_element(By.ID, "export").click()
    wait(drv, lambda d: body(d, "exported"))
    path = Path(body(drv, "exported"))
    assert path.parent == session.export_dir and path.exists()
    command = drv.find_element(By.ID, "export-command").text
    argv = shlex.split(command)
    assert argv[argv.index("-o") + 1] == str(path) and "--bit-depth" in argv and "--focus-at" in argv
    assert argv[argv.index("--aperture") + 1] == "polygon"
    from bokehray.app.cli import main

    again = path.with_name("again.png")
    argv[argv.index("-o") + 1] = str(again)
    assert main(argv[1:] + ["--quiet"]) == 0
    assert again.read_bytes() == path.read_bytes()  # the shown command writes the same file, byte for byte
    again.unlink()
    assert drv.find_element(By.ID, "error").text == ""

    shot = os.environ.get("BOKEHRAY_VIEW_SCREENSHOT")
    if shot:
        drv.save_screenshot(shot)


def test_metric_depth_offers_the_lens_in_chromium(tmp_path, browser):
    """With a metric --depth map the page offers f-number and focus distance; the command says them."""
    drv = browser
    sc = build_demo_scene(width=480, height=320)
    br.write_image(tmp_path / "photo.exr", sc.image)
    br.write_image(tmp_path / "depth.exr", (1.0 / (0.2 + sc.disparity)).astype(np.float32)[..., None])
    session = ViewSession.from_files(str(tmp_path / "photo.exr"), depth=str(tmp_path / "depth.exr"),
                                     export_dir=tmp_path, proxy_long_side=240)
    with ViewServer(session) as server:
        drv.get(server.url)
        wait_sharp(drv)
        assert drv.find_element(By.ID, "lens-controls").is_displayed()
        assert " m" in drv.find_element(By.ID, "files").text  # the depth range in metres
        n_prev = count(drv, "previews")
        drv.execute_script("const m = document.getElementById('blur-mode'); m.value = 'lens'; "
                           "m.dispatchEvent(new Event('change'));")
        wait(drv, lambda d: count(d, "previews") > n_prev)
        wait_sharp(drv)
        argv = shlex.split(drv.find_element(By.ID, "command").text)
        assert argv[argv.index("--f-number") + 1] == "1.8" and argv[argv.index("--focal-length") + 1] == "50.0"
        z = float(argv[argv.index("--focus-distance") + 1])
        assert z == pytest.approx(float(session.norm.depth(session.subject.d_f)))
        assert "m away" in drv.find_element(By.ID, "focus-where").text
        assert drv.find_element(By.ID, "error").text == ""


def test_focus_first_in_words_and_the_command_follows_the_format_in_chromium(tmp_path, browser):
    """A portrait: the focus is said in words (the eyes), the focused region at screen size lands between the proxy
    and the sharp version, choosing JPEG makes the shown command write a JPEG, and the export says its steps and
    shows its result in view."""
    import skimage.data

    drv = browser
    Image = pytest.importorskip("PIL.Image")
    Image.fromarray(skimage.data.astronaut()).save(tmp_path / "photo.png")
    disp = np.full((512, 512), 0.1, np.float32)
    disp[200:, 20:370] = 0.859
    disp[10:200, 150:305] = 0.839
    br.write_disparity(tmp_path / "disp.png", disp)
    session = ViewSession.from_files(str(tmp_path / "photo.png"), disparity=str(tmp_path / "disp.png"),
                                     export_dir=tmp_path, proxy_long_side=128)
    with ViewServer(session) as server:
        drv.get(server.url)
        wait_sharp(drv)
        assert drv.find_element(By.ID, "focus-where").text == "the eyes of the nearest face (near)"
        assert drv.find_element(By.ID, "subject").text == "Focus on the eyes of the nearest face"
        assert count(drv, "focus-crops") >= 1
        x0, y0, x1, y1 = (int(v) for v in body(drv, "focus-crop").split(","))
        assert x0 <= session.subject.x < x1 and y0 <= session.subject.y < y1
        assert " -o OUTPUT.png" in drv.find_element(By.ID, "command").text
        n_prev = count(drv, "previews")
        drv.execute_script("const f = document.getElementById('format'); f.value = 'jpg'; "
                           "f.dispatchEvent(new Event('change'));")
        wait(drv, lambda d: count(d, "previews") > n_prev)
        wait_sharp(drv)
        assert " -o OUTPUT.jpg" in drv.find_element(By.ID, "command").text
        drv.execute_script("window.scrollTo(0, 0);")
        drv.find_element(By.ID, "export").click()
        wait(drv, lambda d: body(d, "exported"))
        assert drv.find_element(By.ID, "export-out").text.startswith("wrote ")
        assert drv.find_element(By.ID, "export-command").text.split(" -o ")[1].split()[0].endswith(".jpg")
        in_view = drv.execute_script("const r = document.getElementById('export-command').getBoundingClientRect(); "
                                     "return r.top >= 0 && r.bottom <= window.innerHeight;")
        assert in_view
        assert drv.find_element(By.ID, "error").text == ""
    # the focus crop came after the preview of its state and before the sharp version of it
    shown = drv.execute_script("return window.bokehrayShown;")
    focused = [v for stage, v in shown if stage == "focus"]
    assert focused, shown
    for v in focused:
        at = shown.index(["focus", v])
        assert ["preview", v] in shown[:at] and ["full", v] not in shown[:at], shown
