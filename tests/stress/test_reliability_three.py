"""The command line's stderr holds bokehray's own lines only, and a batch stops on SIGTERM
as a single render does (items 7, 11 and 12 of the adversarial run; docs/robustness.md, "Batches, sweeps and Dask").

Each test failed before its fix. The readers' half (tifffile's log, libpng's warnings) is checked in-process with
``capfd``, which sees file descriptor 2; the CLI's guard for every command needs a real process.
"""

from __future__ import annotations

import os
import signal
import struct
import subprocess
import sys
import zlib
from pathlib import Path

import imagecodecs
import numpy as np
import pytest
import tifffile
from tolerances import HANG_S

import bokehray as br
from bokehray.colour import srgb_icc

_PATHS = os.pathsep.join(dict.fromkeys(str(Path(m.__file__).resolve().parents[1])
                                       for m in (br, __import__("bokehray_kernels"))))
H, W = 32, 48


def _cli(args, *, prelude: str = "", wait: bool = True):
    code = f"{prelude}\nimport sys\nfrom bokehray.app.cli import main\nsys.exit(main(sys.argv[1:]))\n"
    env = {**os.environ, "PYTHONPATH": _PATHS + os.pathsep + os.environ.get("PYTHONPATH", "")}
    env.pop("PYTHONWARNINGS", None)
    cmd = [sys.executable, "-c", code, *map(str, args)]
    if wait:
        return subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=HANG_S * 2, check=False)
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)


def _tiff_with_orientation(path: Path, value: int) -> Path:
    img = (np.random.default_rng(value).random((H, W, 3)) * 255).astype(np.uint8)
    tifffile.imwrite(path, img, photometric="rgb", extratags=[(274, "H", 1, value, True)])
    return path


def _png16_with_iccp(path: Path, body: bytes) -> Path:
    """A 16-bit RGB PNG with an iCCP chunk holding ``body`` (profile name, NUL, method, zlib data)."""
    codes = (np.random.default_rng(1).random((H, W, 3)) * 65535).astype(np.uint16)
    data = imagecodecs.png_encode(codes)
    chunk = struct.pack(">I", len(body)) + b"iCCP" + body + struct.pack(">I", zlib.crc32(b"iCCP" + body))
    end_ihdr = 8 + 8 + 13 + 4
    path.write_bytes(data[:end_ihdr] + chunk + data[end_ihdr:])
    return path


def _profile_of(space: bytes) -> bytes:
    icc = bytearray(srgb_icc())
    icc[16:20] = space  # the header's data colour space: libpng refuses Lab and CMYK in an RGB PNG
    return b"p\x00\x00" + zlib.compress(bytes(icc))


ODD_FILES = {
    "tiff-orientation-0": lambda p: _tiff_with_orientation(p / "o0.tif", 0),
    "tiff-orientation-9": lambda p: _tiff_with_orientation(p / "o9.tif", 9),
    "png16-iccp-lab": lambda p: _png16_with_iccp(p / "lab.png", _profile_of(b"Lab ")),
    "png16-iccp-cmyk": lambda p: _png16_with_iccp(p / "cmyk.png", _profile_of(b"CMYK")),
    "png16-iccp-bad-zlib": lambda p: _png16_with_iccp(p / "zlib.png", b"p\x00\x00\x78\x9cgarbage-not-deflate"),
}


@pytest.mark.parametrize("case", sorted(ODD_FILES))
def test_the_readers_keep_library_lines_off_stderr(case, tmp_path, capfd, caplog):
    """Items 11 and 12: tifffile logged five lines for an Orientation of 0 or 9 (JPEG's reader says nothing), and
    libpng printed ``PNG warning: iCCP: ...``; the image reads (upright, its codes as stored) all the same."""
    import ctypes

    from bokehray.photo.highlights import is_display_referred
    from bokehray.photo.read import read_size

    path = ODD_FILES[case](tmp_path)
    capfd.readouterr()
    img = br.read_image(path)
    assert read_size(path) == (H, W) and is_display_referred(path)
    ctypes.CDLL(None).fflush(None)  # anything native code buffered on its C stderr
    out, err = capfd.readouterr()
    assert img.shape == (H, W, 3) and np.isfinite(img).all()
    assert (out, err) == ("", "")
    # tifffile and imagecodecs (libpng's warnings) log them: pytest's handler takes the records that logging's last
    # resort prints on stderr outside a test
    assert [r.getMessage() for r in caplog.records if r.name.split(".")[0] in ("tifffile", "imagecodecs")] == []


@pytest.mark.slow
@pytest.mark.parametrize("case", sorted(ODD_FILES))
def test_a_render_of_an_odd_but_readable_file_prints_nothing_on_stderr(case, tmp_path):
    path = ODD_FILES[case](tmp_path)
    disp = br.write_disparity(tmp_path / "d.png", np.tile(np.linspace(0, 1, W, dtype=np.float32), (H, 1)))
    proc = _cli(["render", path, "--disparity", disp, "-o", tmp_path / "o.png", "--blur", 4, "--focus", 0.5,
                 "--quiet"])
    assert proc.returncode == 0 and proc.stderr == "", proc.stderr
    assert br.read_image(tmp_path / "o.png").shape == (H, W, 3)


_NATIVE_CHATTER = """
import os
import bokehray.pipeline as r
_render = r.render_handed_over
def _chatty(*a, **k):
    os.write(2, b"some C library: a warning straight to descriptor 2\\n")  # what libpng, Warp or a worker would do
    return _render(*a, **k)
r.render_handed_over = _chatty
"""


@pytest.mark.slow
def test_the_cli_drops_native_lines_and_keeps_its_own(tmp_path):
    """One guard for every command (bokehray._quiet.command_stderr): a native write to descriptor 2 during the
    command goes nowhere, bokehray's own warning and error lines arrive, and --debug shows everything."""
    img = br.write_image(tmp_path / "p.png", np.full((H, W, 3), 0.5, np.float32))
    disp = br.write_disparity(tmp_path / "d.png", np.tile(np.linspace(1, 0, W, dtype=np.float32), (H, 1)))
    args = ["render", img, "--disparity", disp, "-o", tmp_path / "o.png", "--blur", 4, "--focus", 0.5]
    proc = _cli(args, prelude=_NATIVE_CHATTER)
    assert proc.returncode == 0 and "descriptor 2" not in proc.stderr, proc.stderr
    proc = _cli([*args, "--debug"], prelude=_NATIVE_CHATTER)
    assert proc.returncode == 0 and "some C library: a warning straight to descriptor 2" in proc.stderr
    proc = _cli([*args[:-4], "--blur", 4, "--focus", 2], prelude=_NATIVE_CHATTER)  # an error after the chatter
    assert proc.returncode == 2 and proc.stderr.startswith("bokehray: error: focus disparity"), proc.stderr
    assert proc.stderr.count("\n") == 1


_SLOW_SECOND_RENDER = """
import sys, time
import bokehray.pipeline as r
_render, _calls = r.render_handed_over, []
def _slow(*a, **k):
    _calls.append(1)
    if len(_calls) == 2:
        print("RENDERING", flush=True)
        time.sleep(HANG)
    return _render(*a, **k)
r.render_handed_over = _slow
"""


@pytest.mark.slow
def test_sigterm_stops_a_batch_with_143(tmp_path):
    """Item 7: a batch answered SIGTERM with Ctrl-C's 130 "interrupted"; the documented answer is 143."""
    img = br.write_image(tmp_path / "p.png", np.full((H, W, 3), 0.5, np.float32))
    disp = br.write_disparity(tmp_path / "d.png", np.tile(np.linspace(0, 1, W, dtype=np.float32), (H, 1)))
    proc = _cli(["render", img, "--disparity", disp, "-o", tmp_path / "out", "--blur", 4, "--focus", "0.2,0.5,0.8",
                 "--workers", 1, "--quiet"], prelude=_SLOW_SECOND_RENDER.replace("HANG", repr(HANG_S)), wait=False)
    try:
        assert proc.stdout.readline().strip() == "RENDERING", proc.stderr.read()
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=HANG_S)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 143, err
    assert err.strip() == (f"bokehray: terminated (SIGTERM) after 1 of 3 renders; they are complete in "
                           f"{tmp_path / 'out'}, run the same command again to render the rest")
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["bokehray-batch.json", "p_focus_0.200.png"]
