"""Regression tests for broken promises of the render core (docs/robustness.md).

Each test states the promise; each failed before its fix (the adversarial run's cases).

The IO items of the same issue (1, 2, 6 and the questionable inputs) are fixed and tested in
tests/cli_io/test_io.py, tests/stress/test_stress_io.py and tests/cli_io/test_cli.py.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from tolerances import HANG_S

import bokehray as br
from bokehray.errors import BokehrayError, InputError, ResourceError

pytestmark = pytest.mark.slow  # processes, signals, a browser: seconds each

_PATHS = os.pathsep.join(dict.fromkeys(str(Path(m.__file__).resolve().parents[1])
                                       for m in (br, __import__("bokehray_kernels"))))


def _python(code: str, *args, wait: bool = True, timeout: float = 120):
    env = {**os.environ, "PYTHONPATH": _PATHS + os.pathsep + os.environ.get("PYTHONPATH", "")}
    cmd = [sys.executable, "-c", code, *map(str, args)]
    if wait:
        return subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=timeout, check=False)
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)


def _rays(quality: str):
    return br.RaytraceOptions(max_spp=4) if quality == "raytrace" else None


def _scene(h: int = 32, w: int = 32):
    rng = np.random.default_rng(18)
    img = (rng.random((h, w, 3)) * 0.8).astype(np.float32)
    d = np.tile(np.linspace(0, 1, w, dtype=np.float32), (h, 1))
    return img, d


# --------------------------------------------------------------------------- 3: radiance near float32's maximum


@pytest.mark.parametrize("quality", ["preview", "raytrace"])
def test_radiance_near_float32_max_is_rendered_or_refused_up_front(quality):
    img, d = _scene()
    img[10:14, 10:14] = 3.4e38
    try:
        out = br.render(img, d, br.BlurParams(4, 0.5), quality=quality, options=_rays(quality))
    except InputError as e:
        # refused up front: then every level refuses, with the same reason, and none points at another level
        assert "preview takes them" not in str(e), str(e)
        with pytest.raises(InputError):
            other = "preview" if quality == "raytrace" else "raytrace"
            br.render(img, d, br.BlurParams(4, 0.5), quality=other, options=_rays(other))
        return
    assert np.isfinite(out).all()


def test_cli_refuses_or_renders_radiance_near_float32_max_naming_the_file(tmp_path, capsys):
    from bokehray.app.cli import main

    img, d = _scene()
    img[10:14, 10:14] = 3.4e38
    src = br.write_image(tmp_path / "bright.exr", img)
    disp = br.write_disparity(tmp_path / "d.exr", d)
    rc = main(["render", str(src), "--disparity", str(disp), "-o", str(tmp_path / "o.exr"), "--blur", "4",
               "--focus", "0.5"])
    err = capsys.readouterr().err
    assert rc == 0 or (rc == 2 and str(src) in err and "NaN/Inf" not in err), err


# --------------------------------------------------------------------------- 4: refine's tile search with huge K


class _Alarm:
    """Raise TimeoutError if the block runs longer than ``seconds`` (a hang detector, not a speed target)."""

    def __init__(self, seconds: int) -> None:
        self.seconds = seconds

    def __enter__(self):
        def fire(signum, frame):
            raise TimeoutError(f"still running after {self.seconds} s")

        self.previous = signal.signal(signal.SIGALRM, fire)
        signal.alarm(self.seconds)

    def __exit__(self, *exc):
        signal.alarm(0)
        signal.signal(signal.SIGALRM, self.previous)


def test_refine_tile_search_is_bounded_by_the_image_not_the_blur():
    refine = pytest.importorskip("bokehray_refiner.refine")
    d = np.zeros((64, 64), np.float32)
    d[:, 32:] = 1.0  # one depth edge; at K = 1e5 its CoC jump reaches every tile
    coc = br.BlurParams(1e5, 0.0).signed_coc(d)
    with _Alarm(10):  # capped, it takes milliseconds; uncapped, hours
        need = refine.tiles_to_refine(coc, 16, 1.0)
    assert need.shape == (4, 4) and need.all()


# --------------------------------------------------------------------------- 5: Ctrl-C during the ray tracer


def test_ctrl_c_stops_the_ray_tracer(tmp_path):
    """The command that ray traces (bokehray synth: exact renders of layer stacks) stops at Ctrl-C mid-trace and
    leaves no scene behind."""
    # announce the ray-tracing kernel's first launch (SIGINT during the Python work around it is handled at once)
    prelude = """
import sys
import warp as wp
import bokehray_kernels as bk
_launch, _told = wp.launch, []
def _announce(kernel, *a, **k):
    if kernel is bk.raytrace_kernel and not _told:
        _told.append(True)
        print("TRACING", flush=True)
    return _launch(kernel, *a, **k)
wp.launch = _announce
from bokehray.app.cli import main
sys.exit(main(sys.argv[1:]))
"""
    proc = _python(prelude, "synth", "-n", 1, "-o", tmp_path / "synth", "--size", 384, "--blur-levels", 40,
                   "--max-spp", 1024, "--workers", 1, wait=False)
    try:
        assert proc.stdout.readline().strip() == "TRACING", proc.stderr.read()
        time.sleep(0.3)
        proc.send_signal(signal.SIGINT)
        try:
            proc.communicate(timeout=HANG_S)
        except subprocess.TimeoutExpired:
            pytest.fail(f"still tracing {HANG_S:g} s after SIGINT")
        assert proc.returncode == 130
        assert not list((tmp_path / "synth").glob("scene_*/bokeh_*"))
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


# --------------------------------------------------------------------------- 7: huge requests at the public API


def test_huge_request_is_refused_at_the_public_api_before_allocating():
    code = """
import resource, sys
resource.setrlimit(resource.RLIMIT_AS, (8 << 30, 8 << 30))  # whatever happens, this process cannot take the machine
import numpy as np, bokehray as br
img = np.broadcast_to(np.float32(0.5), (100_000, 100_000, 3))
d = np.broadcast_to(np.float32(0.5), (100_000, 100_000))
try:
    br.render(img, d, br.BlurParams(4, 0.5))
except br.ResourceError as e:
    print("ResourceError", e)
except BaseException as e:
    print(type(e).__name__, e)
"""
    proc = _python(code)
    assert proc.stdout.startswith("ResourceError") and "100000 x 100000" in proc.stdout, proc.stdout + proc.stderr


# --------------------------------------------------------------------------- 8: wrong argument types


def _img_d():
    return _scene(16, 16)


_BAD_CALLS = {
    "options as a dict": ("options", lambda i, d: br.render(i, d, br.BlurParams(4, 0.5), options={"max_layers": 4})),
    "ray tracer options as a dict": ("options", lambda i, d: br.render(
        i, d, br.BlurParams(4, 0.5), quality="raytrace", options={"max_spp": 4})),
    "layers as a dict": ("layers", lambda i, d: br.render(i, d, br.BlurParams(4, 0.5), layers={"max_layers": 4})),
    "highlight_boost as a string": ("highlight_boost", lambda i, d: br.render(i, d, br.BlurParams(4, 0.5),
                                                                              highlight_boost="4")),
    "highlight_boost None": ("highlight_boost", lambda i, d: br.render(i, d, br.BlurParams(4, 0.5),
                                                                       highlight_boost=None)),
    "refine=1": ("refine", lambda i, d: br.render(i, d, br.BlurParams(4, 0.5), refine=1)),
    "focus_at with float pixels": ("focus", lambda i, d: br.focus_at(d, 1.5, 2.7)),
    "focus_at on a 1-D array": ("disparity", lambda i, d: br.focus_at(d[0], 1, 0)),
    "RaytraceOptions(max_spp=2.5)": ("max_spp", lambda i, d: br.RaytraceOptions(max_spp=2.5)),
    "BlurParams(True, 0.5)": ("K", lambda i, d: br.BlurParams(True, 0.5)),
}


@pytest.mark.parametrize("case", sorted(_BAD_CALLS))
def test_wrong_argument_types_raise_the_projects_error_naming_the_argument(case):
    name, call = _BAD_CALLS[case]
    img, d = _img_d()
    with pytest.raises(BokehrayError) as info:
        call(img, d)
    assert name.lower() in str(info.value).lower(), str(info.value)


def test_the_right_types_still_work():
    """The counterpart of the cases above, so that a fix that refuses everything is caught."""
    img, d = _img_d()
    out = br.render(img, d, br.BlurParams(4.0, 0.5), layers=br.LayerOptions(max_layers=4), highlight_boost=0.0)
    assert out.shape == img.shape and np.isfinite(out).all()
    assert br.focus_at(d, 1, 2) == pytest.approx(float(np.median(d[0:7, 0:6])))
    assert br.RaytraceOptions(max_spp=3).max_spp == 3 and br.BlurParams(4, 0.5).k_px == 4.0
    assert issubclass(ResourceError, MemoryError)


@pytest.mark.slow
def test_ctrl_c_stops_the_preview_while_layers_are_in_flight(tmp_path):
    """Regression, the preview: Ctrl-C arrived in the main thread but the pool of layer renders was waited for
    (2.96 s on a 13 MP render; up to a layer's whole render). A layer render that takes 60 s stands in here."""
    import signal
    import subprocess
    import sys

    img, d = _scene(64, 64)
    br.write_image(tmp_path / "i.exr", img)
    br.write_disparity(tmp_path / "d.png", d)
    code = (
        "import sys, time\n"
        "import bokehray.levels.preview as pv\n"
        "def slow(*a, **k):\n"
        "    sys.stdout.write('LAYER\\n')\n"  # one write: two workers' lines never interleave
        "    sys.stdout.flush()\n"
        "    time.sleep(60)\n"
        "pv.render_layer = slow\n"
        "from bokehray.app.cli import main\n"
        "sys.exit(main())\n"
    )
    out = tmp_path / "o.png"
    proc = subprocess.Popen([sys.executable, "-c", code, "render", str(tmp_path / "i.exr"), "--disparity",
                             str(tmp_path / "d.png"), "-o", str(out), "--blur", "8", "--focus", "0.5", "--quiet"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "LAYER", proc.stderr.read()
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=HANG_S)  # a layer sleeps 60 s: a waited-for pool would exceed this
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 130, err
    assert err.strip() == "bokehray: interrupted; no partial output was left" and not out.exists()
