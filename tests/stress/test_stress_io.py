"""Input-side stress: decompression bombs in every format, memory-aware refusal, disparity ranges, CLI.

Complements tests/test_io.py (truncated and corrupt files, NaN/Inf, channel counts, missing
paths, atomic writes) and tests/test_fuzz_regressions.py (inputs found by fuzzing).
"""

import os
import resource
import signal
import struct
import subprocess
import sys
import zlib
from pathlib import Path

import bokehray_kernels
import numpy as np
import pytest

import bokehray
import bokehray as br
from bokehray.app import cli
from bokehray.errors import InputError, ResourceError
from bokehray.photo import read as rd


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _png_bomb(path, w, h):
    ihdr = struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0)
    idat = zlib.compress(b"\0" * 64)  # a few bytes of "pixel data"
    chunks = b""
    for tag, body in ((b"IHDR", ihdr), (b"IDAT", idat), (b"IEND", b"")):
        chunks += struct.pack(">I", len(body)) + tag + body + struct.pack(">I", zlib.crc32(tag + body))
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunks)


def _tiff_bomb(path, w, h):
    """A little-endian baseline TIFF whose IFD declares w x h 8-bit grey pixels in one 8-byte strip."""
    entries = [(256, 4, 1, w), (257, 4, 1, h), (258, 3, 1, 8), (259, 3, 1, 1), (262, 3, 1, 1), (273, 4, 1, 8),
               (277, 3, 1, 1), (278, 4, 1, h), (279, 4, 1, 8)]
    ifd = struct.pack("<H", len(entries))
    for tag, typ, count, value in entries:
        ifd += struct.pack("<HHII", tag, typ, count, value) if typ == 4 else struct.pack("<HHIHH", tag, typ, count,
                                                                                          value, 0)
    ifd += struct.pack("<I", 0)
    path.write_bytes(b"II*\x00" + struct.pack("<I", 16) + b"\0" * 8 + ifd)


def _exr_bomb(path, tmp_path, w, h):
    """A valid small EXR whose header's dataWindow is patched to w x h."""
    small = br.write_image(tmp_path / "small.exr", np.zeros((4, 4, 3), np.float32))
    data = bytearray(small.read_bytes())
    for name in (b"dataWindow\0box2i\0", b"displayWindow\0box2i\0"):
        i = data.index(name) + len(name) + 4  # skip the attribute size
        data[i : i + 16] = struct.pack("<iiii", 0, 0, w - 1, h - 1)
    path.write_bytes(bytes(data))


def _jpeg_bomb(path, tmp_path, w, h):
    """A valid small JPEG whose SOF0 frame header is patched to w x h."""
    small = br.write_image(tmp_path / "small.jpg", np.zeros((8, 8, 3), np.float32))
    data = bytearray(small.read_bytes())
    i = data.index(b"\xff\xc0") + 5  # marker, length (2), precision (1), then height and width
    data[i : i + 4] = struct.pack(">HH", h, w)
    path.write_bytes(bytes(data))


def _npy_bomb(path, w, h):
    header = repr({"descr": "<f4", "fortran_order": False, "shape": (h, w)}).encode()
    header += b" " * (63 - (10 + len(header)) % 64) + b"\n"
    path.write_bytes(b"\x93NUMPY\x01\x00" + struct.pack("<H", len(header)) + header + b"\0" * 64)


BOMBS = {
    "png": lambda p, t, w, h: _png_bomb(p, w, h),
    "tif": lambda p, t, w, h: _tiff_bomb(p, w, h),
    "exr": lambda p, t, w, h: _exr_bomb(p, t, w, h),
    "jpg": lambda p, t, w, h: _jpeg_bomb(p, t, w, h),
    "npy": lambda p, t, w, h: _npy_bomb(p, w, h),
}
READERS = {"png": [br.read_image, br.read_disparity], "tif": [br.read_image, br.read_disparity, br.read_depth],
           "exr": [br.read_image, br.read_disparity, br.read_depth], "jpg": [br.read_image],
           "npy": [br.read_disparity, br.read_depth]}


@pytest.mark.parametrize("ext", sorted(BOMBS))
def test_decompression_bombs_are_refused_from_the_header(tmp_path, ext):
    """A few hundred bytes declaring 60 000 x 60 000 pixels: refused naming the file, nothing allocated."""
    p = tmp_path / f"bomb.{ext}"
    BOMBS[ext](p, tmp_path, 60_000, 60_000)
    assert p.stat().st_size < 2000
    before = _peak_rss_mb()
    for read in READERS[ext]:
        with pytest.raises(InputError) as e:
            read(p)
        assert str(p) in str(e.value)
        assert any(s in str(e.value) for s in ("60000 x 60000", "decompression bomb")), str(e.value)
    assert _peak_rss_mb() - before < 200  # a decoded bomb would take 3.6 GB and more


@pytest.mark.parametrize("ext", ["png", "tif", "exr", "npy"])
def test_header_that_does_not_fit_in_memory_is_refused_before_decoding(tmp_path, ext, monkeypatch):
    """Within MAX_PIXELS but beyond the memory available (here: pretend 50 MB): a ResourceError naming the file."""
    p = tmp_path / f"big.{ext}"
    BOMBS[ext](p, tmp_path, 4000, 3000)  # 12 MP: about 480 MB to decode
    monkeypatch.setattr(rd, "available_bytes", lambda: 50 << 20)
    for read in READERS[ext]:
        with pytest.raises(ResourceError, match=rf"{p}: decoding 4000 x 3000 pixels needs about 457 MB, but only 50 MB"):
            read(p)


def test_out_of_memory_inside_a_decoder_becomes_a_resource_error(tmp_path, monkeypatch):
    p = br.write_image(tmp_path / "a.png", np.zeros((4, 4, 3), np.float32))

    def oom(*args, **kwargs):
        raise MemoryError

    monkeypatch.setattr(rd, "decode_pil", oom)
    with pytest.raises(ResourceError, match=rf"{p}: ran out of memory while decoding it as PNG"):
        br.read_image(p)


@pytest.mark.parametrize("ext", ["npy", "exr", "tif"])
@pytest.mark.parametrize("value", [-0.25, 1.5, -0.0])
def test_float_disparity_range_is_checked_naming_the_file(tmp_path, ext, value):
    d = np.full((6, 8), 0.5, np.float32)
    d[2, 3] = value
    p = br.write_disparity(tmp_path / f"d.{ext}", d)
    assert br.read_disparity(p)[2, 3] == value  # unchecked by default (callers may normalise)
    if value == -0.0:
        assert br.read_disparity(p, check_range=True)[2, 3] == 0.0  # -0 is 0
        return
    with pytest.raises(InputError, match=rf"{p}: expected disparity in \[0, 1\] .* got {value:g} at \(y, x\) = \(2, 3\)"):
        br.read_disparity(p, check_range=True)


def test_16_bit_disparity_is_always_in_range(tmp_path):
    p = br.write_disparity(tmp_path / "d.png", np.array([[0.0, 1.0], [0.5, 1e-5]], np.float32))
    d = br.read_disparity(p, check_range=True)
    assert d.min() == 0.0 and d.max() == 1.0 and d.dtype == np.float32


@pytest.mark.parametrize("case", ["negative", "nan_tif", "bomb_png", "bomb_exr", "mismatch", "dir", "missing"])
def test_cli_bad_disparity_inputs_exit_2_with_one_line_naming_the_file(tmp_path, capsys, case):
    img = br.write_image(tmp_path / "img.png", np.random.default_rng(0).random((12, 16, 3)).astype(np.float32))
    d = np.full((12, 16), 0.5, np.float32)
    if case == "negative":
        d[3, 4] = -1.0
        src = br.write_disparity(tmp_path / "d.npy", d)
    elif case == "nan_tif":
        d[3, 4] = np.nan
        src = tmp_path / "d.tif"
        import tifffile

        tifffile.imwrite(src, d)
    elif case == "bomb_png":
        src = tmp_path / "d.png"
        _png_bomb(src, 100_000, 100_000)
    elif case == "bomb_exr":
        src = tmp_path / "d.exr"
        _exr_bomb(src, tmp_path, 100_000, 100_000)
    elif case == "mismatch":
        src = br.write_disparity(tmp_path / "d.exr", np.full((5, 7), 0.5, np.float32))
    elif case == "dir":
        src = tmp_path / "folder.png"
        src.mkdir()
    else:
        src = tmp_path / "nothing.exr"
    out = tmp_path / "out.png"
    rc = cli.main(["render", str(img), "--disparity", str(src), "-o", str(out), "--blur", "4", "--focus", "0.5"])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and not out.exists()
    assert len(err.splitlines()) == 1 and err.startswith("bokehray: error: ") and str(src) in err, err
    assert "Traceback" not in err


def test_exr_whose_unpremultiplied_colour_overflows_is_refused(tmp_path):
    """Found by fuzzing: premultiplied colour 1e30 over alpha 1e-22 is 1e52 straight, beyond float32."""
    import OpenEXR

    chans = {n: np.full((3, 4), v, np.float32) for n, v in zip("RGBA", (0.5, 0.5, -1e30, 1e-22))}
    p = tmp_path / "tiny-alpha.exr"
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}, chans) as f:
        f.write(str(p))
    with pytest.raises(InputError, match=rf"{p}: colour / alpha .* overflows float32: -Inf at \(y, x\) = \(0, 0\)"):
        br.read_image(p)
    chans = {n: np.full((3, 4), v, np.float32) for n, v in zip("RGBA", (0.5, 0.5, 0.25, 1e-22))}
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}, chans) as f:
        f.write(str(p))
    np.testing.assert_allclose(br.read_image(p)[0, 0], [5e21, 5e21, 2.5e21, 1e-22], rtol=1e-6)  # finite: kept


# --------------------------------------------------------------------------- the CLI in a real process
# (a traceback, a warning or a native library's line reaches the real stderr only outside pytest's capture)


_PATHS = os.pathsep.join(dict.fromkeys(str(Path(m.__file__).resolve().parents[1]) for m in (bokehray, bokehray_kernels)))


def _cli(args, *, prelude: str = "", wait: bool = True, timeout: float = 120):
    """Run ``bokehray ARGS`` in a fresh interpreter (after ``prelude``); the finished process, or the running one."""
    code = f"{prelude}\nimport sys\nfrom bokehray.app.cli import main\nsys.exit(main(sys.argv[1:]))\n"
    env = {**os.environ, "PYTHONPATH": _PATHS + os.pathsep + os.environ.get("PYTHONPATH", "")}
    env.pop("PYTHONWARNINGS", None)
    if wait:
        return subprocess.run([sys.executable, "-c", code, *map(str, args)], capture_output=True, text=True, env=env,
                              timeout=timeout, check=False)
    # SIGHUP at its default, whatever this test run inherited (under nohup it is ignored, and so would the CLI's be:
    # it keeps an ignored SIGHUP ignored on purpose)
    return subprocess.Popen([sys.executable, "-c", code, *map(str, args)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env,
                            preexec_fn=lambda: signal.signal(signal.SIGHUP, signal.SIG_DFL))


@pytest.fixture
def inputs(tmp_path):
    img = br.write_image(tmp_path / "in.png", np.random.default_rng(0).random((96, 128, 3)).astype(np.float32))
    disp = br.write_disparity(tmp_path / "d.png", np.tile(np.linspace(0, 1, 128, dtype=np.float32), (96, 1)))
    return img, disp


def _one_error_line(proc) -> str:
    err = proc.stderr.strip()
    assert proc.returncode == 2 and len(err.splitlines()) == 1 and err.startswith("bokehray: error: "), proc.stderr
    return err


@pytest.fixture
def full_disk(tmp_path):
    """A 4 KB tmpfs (smaller than every output here) (root only), else None: the tests then patch the writers to fail as a full disk does."""
    folder = tmp_path / "full"
    folder.mkdir()
    mounted = os.geteuid() == 0 and subprocess.run(["mount", "-t", "tmpfs", "-o", "size=4k", "tmpfs", str(folder)],
                                                   capture_output=True, check=False).returncode == 0
    yield folder, mounted
    if mounted:
        subprocess.run(["umount", str(folder)], check=False)


_ENOSPC_WRITERS = """
import errno, os, OpenEXR, tifffile
from PIL import Image
def _exr(self, target):
    open(target, "wb").write(b"partial")
    raise RuntimeError(f'Failed to write pixel data to image file "{target}". No space left on device.')
def _enospc(*a, **k):
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
OpenEXR.File.write, tifffile.imwrite, Image.Image.save = _exr, _enospc, _enospc
"""


@pytest.mark.slow
@pytest.mark.parametrize("ext", ["exr", "png", "tif", "jpg"])
def test_disk_full_while_writing_is_one_line_naming_the_output(inputs, full_disk, ext):
    """Regression: a full disk during the EXR write was a traceback with exit 1; PNG/TIFF named no file."""
    (img, disp), (folder, mounted) = inputs, full_disk
    out = folder / f"o.{ext}"
    proc = _cli(["render", img, "--disparity", disp, "-o", out, "--blur", 4, "--focus", 0.5],
                prelude="" if mounted else _ENOSPC_WRITERS)
    assert _one_error_line(proc) == f"bokehray: error: cannot write {out}: No space left on device"
    assert sorted(os.listdir(folder)) == []


@pytest.mark.slow
def test_a_demo_on_a_full_disk_leaves_no_folder(full_disk):
    """Regression: ``bokehray demo`` on a full disk said so in one line but left its (empty) output folder behind."""
    folder, mounted = full_disk
    out = folder / "demo"
    proc = _cli(["demo", "-o", out, "--size", "96,64", "--quiet"], prelude="" if mounted else _ENOSPC_WRITERS)
    assert _one_error_line(proc) == f"bokehray: error: cannot write {out / 'input.png'}: No space left on device"
    assert sorted(os.listdir(folder)) == []


def _slow_writer(marker: str) -> str:
    """A prelude whose PNG encoder writes part of the file, says so on stdout, then hangs (until a signal)."""
    return f"""
import time
from pathlib import Path
from bokehray.output import write as wr
def _slow(tmp, codes, fmt, **k):
    Path(tmp).write_bytes(b"partial" * 4096)
    print("{marker}", flush=True)
    time.sleep(60)
wr.encode_pil = _slow
"""


def _start_and_signal(args, sig):
    proc = _cli(args, prelude=_slow_writer("WRITING"), wait=False)
    try:
        assert proc.stdout.readline().strip() == "WRITING", proc.stderr.read()
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    return proc.returncode, err


@pytest.mark.parametrize("sig,code,words", [(signal.SIGTERM, 143, "terminated (SIGTERM)"),
                                            (signal.SIGINT, 130, "interrupted"),
                                            (signal.SIGHUP, 129, "terminated (SIGHUP)")])
def test_a_signal_while_writing_removes_the_temporary_file(inputs, tmp_path, sig, code, words):
    """Regression: SIGTERM used to kill the process mid-write, leaving ``.o.png.XXXX.png`` beside the output; SIGHUP
    (the terminal closed) did before."""
    img, disp = inputs
    out = tmp_path / "o.png"
    rc, err = _start_and_signal(["render", img, "--disparity", disp, "-o", out, "--blur", 4, "--focus", 0.5], sig)
    assert rc == code, err
    assert err.strip() == f"bokehray: {words}; no partial output was left"
    assert sorted(os.listdir(tmp_path)) == ["d.png", "in.png"]


def test_an_ignored_sighup_stays_ignored_so_a_nohup_render_outlives_its_terminal(inputs, tmp_path):
    """Under ``nohup`` (SIGHUP ignored) the render does not take SIGHUP as a reason to stop: it writes its output."""
    img, disp = inputs
    out = tmp_path / "o.png"
    prelude = """
import os, signal, sys
signal.signal(signal.SIGHUP, signal.SIG_IGN)
import bokehray.output.write as wr
_encode = wr.encode_pil
def _hup_then_encode(*a, **k):
    os.kill(os.getpid(), signal.SIGHUP)  # mid-write, as a terminal closing would
    return _encode(*a, **k)
wr.encode_pil = _hup_then_encode
"""
    proc = _cli(["render", img, "--disparity", disp, "-o", out, "--blur", 4, "--focus", 0.5], prelude=prelude)
    assert proc.returncode == 0 and proc.stderr == "", proc.stderr
    assert br.read_image(out).shape == (96, 128, 3)


@pytest.mark.slow
def test_stale_temporary_of_a_killed_write_is_removed_by_the_next_write(inputs, tmp_path):
    """SIGKILL cannot be handled: its temporary file stays until the next write to that path removes it."""
    img, disp = inputs
    out = tmp_path / "o.png"
    args = ["render", img, "--disparity", disp, "-o", out, "--blur", 4, "--focus", 0.5]
    rc, _ = _start_and_signal(args, signal.SIGKILL)
    assert rc == -signal.SIGKILL
    stale = [n for n in os.listdir(tmp_path) if n.startswith(".o.png.tmp-")]
    assert len(stale) == 1 and (tmp_path / stale[0]).stat().st_size > 0
    proc = _cli(args)
    assert proc.returncode == 0 and proc.stderr == "", proc.stderr
    assert sorted(os.listdir(tmp_path)) == ["d.png", "in.png", "o.png"]
    assert br.read_image(out).shape == (96, 128, 3)


def test_sigterm_during_the_render_exits_143_without_output(inputs, tmp_path):
    """SIGTERM before the write (here during a slow stand-in for the render): exit 143, one line, nothing written."""
    img, disp = inputs
    out = tmp_path / "o.png"
    prelude = """
import sys, time
import bokehray.pipeline as r
def _slow(*a, **k):
    print("RENDERING", flush=True)
    time.sleep(60)
r.render_handed_over = _slow
"""
    proc = _cli(["render", img, "--disparity", disp, "-o", out, "--blur", 4, "--focus", 0.5], prelude=prelude,
                wait=False)
    try:
        assert proc.stdout.readline().strip() == "RENDERING", proc.stderr.read()
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 143 and err.strip() == "bokehray: terminated (SIGTERM); no partial output was left"
    assert not out.exists()


@pytest.mark.slow
def test_overflow_cases_are_one_line_with_no_warnings(inputs, tmp_path):
    """Regression: overflow warnings leaked onto stderr (3 to 5 lines), and 1e300 was reported as "+Inf"."""
    img, disp = inputs
    out = tmp_path / "o.png"
    base = ["--blur", 4, "--focus", 0.5, "-o", out]
    err = _one_error_line(_cli(["render", img, "--disparity", disp, "--highlight-boost", "1e39", *base]))
    assert err == "bokehray: error: highlight_boost: expected a value within float32's range (3.4e38), got 1e+39"
    bright = br.write_image(tmp_path / "bright.exr", np.full((96, 128, 3), 3e38, np.float32))
    err = _one_error_line(_cli(["render", bright, "--disparity", disp, *base]))  # every level's radiance limit
    assert err == f"bokehray: error: {bright}: radiance up to 3e+38; renders sum values in float32 and need them " \
                  "within +-1e+36 (scale the image down)"
    bright = br.write_image(tmp_path / "bright.exr", np.full((96, 128, 3), 5e35, np.float32))
    err = _one_error_line(_cli(["render", bright, "--disparity", disp, "--highlight-boost", 4, *base]))
    assert "highlight_boost: expected a boost that keeps radiance within +-1e+36" in err
    assert "from 5e+35 to 2.5e+36" in err
    d = np.full((96, 128), 0.5)
    d[5, 6] = 1e300
    np.save(tmp_path / "d64.npy", d)
    err = _one_error_line(_cli(["render", img, "--disparity", tmp_path / "d64.npy", *base]))
    assert err.endswith("d64.npy: expected values within float32's range (+-3.4e38), got 1e+300 at (y, x) = (5, 6)")
    assert not out.exists()


@pytest.mark.slow
def test_cuda_without_a_driver_is_one_line(inputs, tmp_path):
    """Warp printed two native ``Warp CUDA error`` lines before the one-line error on a machine without a driver."""
    import warp as wp

    if wp.is_cuda_available():
        pytest.skip("this machine has CUDA: the request succeeds")
    img, disp = inputs
    proc = _cli(["render", img, "--disparity", disp, "-o", tmp_path / "o.png", "--blur", 4, "--focus", 0.5,
                 "--device", "cuda"])
    assert "device: 'cuda' is not available here" in _one_error_line(proc)


def test_size_mismatch_is_found_from_the_headers_before_decoding(inputs, tmp_path, monkeypatch, capsys):
    """A 64 MP PNG was decoded (5 s) before its size mismatch with the disparity map was reported."""
    img, _ = inputs
    small = br.write_disparity(tmp_path / "small.npy", np.full((12, 16), 0.5, np.float32))
    monkeypatch.setattr(rd, "load_samples", lambda *a, **k: pytest.fail("decoded pixels before comparing the headers"))
    rc = cli.main(["render", str(img), "--disparity", str(small), "-o", str(tmp_path / "o.png"), "--blur", "4",
                   "--focus", "0.5"])
    err = capsys.readouterr().err
    assert rc == 2 and err == f"bokehray: error: {small}: map is 16x12, image is 128x96; pass --resize-disparity to " \
                              "resize it\n"


_FUZZ = sorted(p for p in (Path(__file__).parents[1] / "data" / "fuzz").rglob("*") if p.suffix in (".png", ".jpg", ".tif",
                                                                                                   ".exr", ".npy"))


@pytest.mark.parametrize("path", _FUZZ, ids=lambda p: f"{p.parent.name}/{p.name}")
def test_read_size_agrees_with_the_readers_on_the_fuzz_files(path, monkeypatch, capfd):
    """The header-only size is what every reader that decodes the file finds, or a clear error naming it."""
    monkeypatch.setattr(rd, "MAX_PIXELS", 2_000_000)
    try:
        size = rd.read_size(path)
    except (InputError, ResourceError) as e:
        assert str(path) in str(e)
        size = None
    readers = READERS[{".tif": "tif", ".exr": "exr", ".png": "png", ".jpg": "jpg", ".npy": "npy"}[path.suffix]]
    for read in readers:
        try:
            a = read(path)
        except (InputError, ResourceError):
            continue
        assert a.shape[:2] == size
    out, err = capfd.readouterr()
    assert out == "" and err == "", (out + err)[:300]
