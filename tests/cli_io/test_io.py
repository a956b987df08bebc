"""Tests for the readers and writers (bokehray.photo.read, bokehray.output): format round trips, colour handling, error paths, atomic writes."""

from __future__ import annotations

import errno
import os
import re
import struct
import zlib
from pathlib import Path

import numpy as np
import OpenEXR
import pytest
import tifffile
from PIL import Image

import bokehray as br
from bokehray import _memory as memory
from bokehray import colour
from bokehray.errors import InputError
from bokehray.output import atomic as at
from bokehray.output import write as wr
from bokehray.photo import read as rd

RNG = np.random.default_rng(1234)


def _image(h: int = 24, w: int = 32, c: int = 3) -> np.ndarray:
    return RNG.uniform(0.0, 1.0, (h, w, c)).astype(np.float32)


def _smooth(h: int = 48, w: int = 64) -> np.ndarray:
    y, x = np.mgrid[0:h, 0:w] / np.array([h, w])[:, None, None]
    return np.stack([x, y, 0.5 * (x + y)], axis=-1).astype(np.float32) * 0.8 + 0.1


def _raises(path: Path, fragment: str):
    """pytest.raises for an InputError whose message names both ``path`` and the problem."""

    class _Ctx:
        def __enter__(self):
            self.ctx = pytest.raises(InputError, match=fragment)
            self.info = self.ctx.__enter__()
            return self.info

        def __exit__(self, *exc):
            handled = self.ctx.__exit__(*exc)
            assert str(path) in str(self.info.value), str(self.info.value)
            return handled

    return _Ctx()


def _png(path: Path, codes: np.ndarray, *, interlace: bool = False) -> None:
    """Independent minimal 16-bit PNG encoder (filter 0, optional Adam7) for reader tests."""
    codes = codes[..., None] if codes.ndim == 2 else codes
    h, w, c = codes.shape
    be = codes.astype(">u2")
    passes = [(0, 0, 8, 8), (0, 4, 8, 8), (4, 0, 8, 4), (0, 2, 4, 4), (2, 0, 4, 2), (0, 1, 2, 2), (1, 0, 2, 1)]
    raw = b""
    for y0, x0, dy, dx in passes if interlace else [(0, 0, 1, 1)]:
        sub = be[y0::dy, x0::dx]
        if sub.size:
            raw += b"".join(b"\0" + row.tobytes() for row in sub)

    def chunk(tag: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + tag + body + struct.pack(">I", zlib.crc32(tag + body))

    ihdr = struct.pack(">IIBBBBB", w, h, 16, {1: 0, 2: 4, 3: 2, 4: 6}[c], 0, 0, int(interlace))
    body = chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b"")
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + body)


def _write_exr(path: Path, channels: dict[str, np.ndarray]) -> None:
    # OpenEXR's binding ignores numpy strides: channel arrays must be C-contiguous.
    channels = {k: np.ascontiguousarray(v) for k, v in channels.items()}
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}, channels) as f:
        f.write(str(path))


# --------------------------------------------------------------------------- round trips


@pytest.mark.parametrize("channels", [1, 3, 4])
def test_png8_round_trip_is_exact_in_codes(tmp_path, channels):
    img = _image(c=channels)
    p = br.write_image(tmp_path / "a.png", img[..., 0] if channels == 1 else img)
    back = br.read_image(p)
    assert back.dtype == np.float32 and back.shape == (24, 32, 4 if channels == 4 else 3)
    want = wr.srgb_codes(img, 8)
    got = wr.srgb_codes(back if channels != 1 else back[..., :1], 8)
    np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("channels", [1, 3, 4])
def test_png16_round_trip_keeps_16_bit_precision(tmp_path, channels):
    img = _image(c=channels)
    back = br.read_image(br.write_image(tmp_path / "a.PNG", img, bit_depth=16))
    ref = np.repeat(img, 3, axis=2) if channels == 1 else img
    assert np.abs(back - ref).max() < 1e-4  # an 8-bit round trip is off by up to ~4e-3


@pytest.mark.parametrize("channels", [1, 2, 3, 4])
@pytest.mark.parametrize("interlace", [False, True])
def test_png16_reader_is_exact_against_independent_encoder(tmp_path, channels, interlace):
    codes = RNG.integers(0, 65536, (13, 11, channels), dtype=np.uint16)
    _png(tmp_path / "c.png", codes, interlace=interlace)
    back = br.read_image(tmp_path / "c.png")
    n_colour = 1 if channels <= 2 else 3
    lin = colour.srgb_to_linear(codes[..., :n_colour] / 65535.0)
    np.testing.assert_allclose(back[..., :3], np.broadcast_to(lin, (13, 11, 3)), rtol=0, atol=1e-6)
    if channels in (2, 4):
        np.testing.assert_allclose(back[..., 3], codes[..., -1] / 65535.0, rtol=0, atol=1e-7)


def test_png16_writer_decodes_exactly_with_pillow(tmp_path):
    d = np.clip(np.cumsum(RNG.normal(0, 0.01, (300, 50)), axis=1) + 0.5, 0, 1).astype(np.float32)  # > 1 row block
    d[::7] = RNG.uniform(0, 1, (43, 50))  # noisy rows too, so several filter types get chosen
    p = br.write_disparity(tmp_path / "d.png", d)
    with Image.open(p) as im:
        codes = np.asarray(im)
    np.testing.assert_array_equal(codes, np.round(d.astype(np.float64) * 65535).astype(np.uint16))


def test_jpeg_round_trip(tmp_path):
    img = _smooth()
    back = br.read_image(br.write_image(tmp_path / "a.jpeg", img, quality=95))
    assert back.shape == img.shape and np.abs(back - img).mean() < 0.01 and np.abs(back - img).max() < 0.05


@pytest.mark.parametrize("bit_depth,tol", [(None, 1e-4), (8, 5e-3), (32, 0.0)])
def test_tiff_round_trip(tmp_path, bit_depth, tol):
    img = _image(c=4) * 1.0
    if bit_depth == 32:
        img[0, 0, 0] = 7.5  # float TIFF is linear and unclipped
    back = br.read_image(br.write_image(tmp_path / "a.tif", img, bit_depth=bit_depth))
    assert np.abs(back - img).max() <= tol


@pytest.mark.parametrize("half,tol", [(False, 1e-6), (True, 2e-3)])
def test_exr_round_trip(tmp_path, half, tol):
    img = _image() * 4.0  # HDR values stay as they are
    p = br.write_image(tmp_path / "a.exr", img, half=half)
    back = br.read_image(p)
    np.testing.assert_allclose(back, img, rtol=tol, atol=1e-6)
    with OpenEXR.File(str(p), separate_channels=True) as f:
        chans = f.parts[0].channels
        assert sorted(chans) == ["B", "G", "R"]
        assert chans["R"].pixels.dtype == (np.float16 if half else np.float32)
        assert f.header()["compression"] == OpenEXR.ZIP_COMPRESSION


def test_exr_rgba_is_premultiplied_on_disk_and_straight_in_memory(tmp_path):
    img = _image(c=4)
    img[..., 3] = RNG.uniform(0.2, 1.0, img.shape[:2])
    p = br.write_image(tmp_path / "a.exr", img)
    with OpenEXR.File(str(p), separate_channels=True) as f:
        np.testing.assert_allclose(f.parts[0].channels["R"].pixels, img[..., 0] * img[..., 3], rtol=1e-6)
    np.testing.assert_allclose(br.read_image(p), img, rtol=1e-5, atol=1e-6)


def test_exr_grey_and_packed_channels(tmp_path):
    grey = _image(c=1)
    p = br.write_image(tmp_path / "g.exr", grey[..., 0])
    with OpenEXR.File(str(p), separate_channels=True) as f:
        assert list(f.parts[0].channels) == ["Y"]
    np.testing.assert_array_equal(br.read_image(p), np.repeat(grey, 3, axis=2))
    rgb = _image().astype(np.float16)
    _write_exr(tmp_path / "packed.exr", {"RGB": rgb})
    np.testing.assert_array_equal(br.read_image(tmp_path / "packed.exr"), rgb.astype(np.float32))


@pytest.mark.parametrize("ext", [".png", ".exr", ".npy", ".tif"])
def test_disparity_round_trip(tmp_path, ext):
    d = RNG.uniform(0, 1, (20, 30)).astype(np.float32)
    back = br.read_disparity(br.write_disparity(tmp_path / f"d{ext}", d))
    assert back.dtype == np.float32 and back.shape == d.shape
    assert np.abs(back - d).max() <= (0.5 / 65535 + 1e-7 if ext == ".png" else 0.0)


def test_disparity_integer_formats_are_scaled_not_decoded(tmp_path):
    Image.fromarray(np.full((4, 5), 128, np.uint8)).save(tmp_path / "d8.png")
    np.testing.assert_allclose(br.read_disparity(tmp_path / "d8.png"), 128 / 255)
    tifffile.imwrite(tmp_path / "d16.tif", np.full((4, 5), 30000, np.uint16))
    np.testing.assert_allclose(br.read_disparity(tmp_path / "d16.tif"), 30000 / 65535)
    Image.fromarray(np.full((4, 5, 3), 77, np.uint8)).save(tmp_path / "grey3.png")  # equal channels: fine
    np.testing.assert_allclose(br.read_disparity(tmp_path / "grey3.png"), 77 / 255)
    np.save(tmp_path / "d.npy", np.full((4, 5, 1), 0.25))
    assert br.read_disparity(tmp_path / "d.npy").shape == (4, 5)


def test_depth_readers(tmp_path):
    z = RNG.uniform(0.5, 20, (8, 9)).astype(np.float32)
    z[0, 0] = np.inf  # sky: infinitely far is allowed
    _write_exr(tmp_path / "z.exr", {"Z": z, "R": np.zeros_like(z)})
    np.testing.assert_array_equal(br.read_depth(tmp_path / "z.exr"), z)
    tifffile.imwrite(tmp_path / "z.tif", z)
    np.testing.assert_array_equal(br.read_depth(tmp_path / "z.tif"), z)
    np.save(tmp_path / "z.npy", z.astype(np.float64))
    np.testing.assert_array_equal(br.read_depth(tmp_path / "z.npy"), z)


# --------------------------------------------------------------------------- colour handling


def test_srgb_decode_applies_to_png_not_exr(tmp_path):
    Image.fromarray(np.full((4, 4, 3), 128, np.uint8)).save(tmp_path / "g.png")
    np.testing.assert_allclose(br.read_image(tmp_path / "g.png"), 0.21586, atol=1e-4)
    _write_exr(tmp_path / "g.exr", {c: np.full((4, 4), 0.5, np.float32) for c in "RGB"})
    np.testing.assert_array_equal(br.read_image(tmp_path / "g.exr"), 0.5)
    assert abs(float(colour.linear_to_srgb(colour.srgb_to_linear(0.3))) - 0.3) < 1e-6


def test_alpha_is_not_gamma_decoded(tmp_path):
    Image.fromarray(np.full((4, 4, 4), 128, np.uint8)).save(tmp_path / "a.png")
    img = br.read_image(tmp_path / "a.png")
    np.testing.assert_allclose(img[..., :3], 0.21586, atol=1e-4)
    np.testing.assert_allclose(img[..., 3], 128 / 255, atol=1e-7)
    Image.fromarray(np.full((4, 4, 2), 128, np.uint8), mode="LA").save(tmp_path / "la.png")
    np.testing.assert_allclose(br.read_image(tmp_path / "la.png"), img, atol=1e-7)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
@pytest.mark.parametrize(("channels", "n_colour"), [(1, 1), (2, 1), (3, 3), (4, 3)])
def test_decode_codes_in_bands_equals_one_table_lookup(monkeypatch, dtype, channels, n_colour):
    """The banded decode gives the values of the whole-image lookup, bit for bit, bands cut mid-image included."""
    monkeypatch.setattr(memory, "BAND_PX", 7 * 5)  # 5 rows of 7 px a band: 23 rows end in a partial band
    rng = np.random.default_rng(channels)
    a = rng.integers(0, np.iinfo(dtype).max, (23, 7, channels), endpoint=True).astype(dtype)
    ref = np.empty(a.shape, np.float32)
    ref[..., :n_colour] = colour.srgb_decode_lut(a.dtype.itemsize * 8)[a[..., :n_colour]]
    ref[..., n_colour:] = a[..., n_colour:] / np.float32(np.iinfo(dtype).max)
    out = rd.decode_codes(a, n_colour)
    assert out.dtype == np.float32 and out.shape == a.shape
    np.testing.assert_array_equal(out.view(np.uint32), ref.view(np.uint32))


def test_grey_png_is_expanded(tmp_path):
    Image.fromarray(np.arange(20, dtype=np.uint8).reshape(4, 5)).save(tmp_path / "g.png")
    img = br.read_image(tmp_path / "g.png")
    assert img.shape == (4, 5, 3) and (img[..., 0] == img[..., 2]).all()


# --------------------------------------------------------------------------- read errors


def test_missing_file(tmp_path):
    with _raises(tmp_path / "nope.png", "does not exist"):
        br.read_image(tmp_path / "nope.png")


def test_directory(tmp_path):
    (tmp_path / "dir.png").mkdir()
    with _raises(tmp_path / "dir.png", "got a directory"):
        br.read_image(tmp_path / "dir.png")


def test_unsupported_extension(tmp_path):
    (tmp_path / "a.bmp").write_bytes(b"BM")
    with _raises(tmp_path / "a.bmp", r"unsupported extension '\.bmp'.*\.png, \.jpg"):
        br.read_image(tmp_path / "a.bmp")
    np.save(tmp_path / "a.npy", np.zeros((2, 2, 3)))
    with _raises(tmp_path / "a.npy", "unsupported extension '.npy' for reading images"):
        br.read_image(tmp_path / "a.npy")


@pytest.mark.parametrize("bit_depth", [8, 16])
def test_truncated_png(tmp_path, bit_depth):
    p = br.write_image(tmp_path / "t.png", _image(64, 64), bit_depth=bit_depth)
    p.write_bytes(p.read_bytes()[: p.stat().st_size // 2])
    with _raises(p, "cannot read .* as PNG: .*truncated"):
        br.read_image(p)


def test_png_with_wrong_content(tmp_path):
    (tmp_path / "x.png").write_bytes(b"GIF89a" + bytes(100))
    with _raises(tmp_path / "x.png", "as PNG: not a PNG file"):
        br.read_image(tmp_path / "x.png")


def test_corrupt_exr(tmp_path):
    (tmp_path / "c.exr").write_bytes(RNG.integers(0, 256, 2000, dtype=np.uint8).tobytes())
    with _raises(tmp_path / "c.exr", "cannot read .* as EXR"):
        br.read_image(tmp_path / "c.exr")
    p = br.write_image(tmp_path / "t.exr", _image(64, 64))
    p.write_bytes(p.read_bytes()[: p.stat().st_size // 2])
    with _raises(p, "cannot read .* as EXR"):
        br.read_image(p)


def test_truncated_jpeg(tmp_path):
    p = br.write_image(tmp_path / "t.jpg", _image(64, 64))
    p.write_bytes(p.read_bytes()[: p.stat().st_size // 2])
    with _raises(p, "cannot read .* as JPEG: .*truncated"):
        br.read_image(p)


def test_truncated_tiff(tmp_path):
    p = tmp_path / "t.tif"
    tifffile.imwrite(p, RNG.integers(0, 65535, (64, 64, 3), dtype=np.uint16), photometric="rgb")
    p.write_bytes(p.read_bytes()[: p.stat().st_size // 2])
    with _raises(p, "cannot read .* as TIFF"):
        br.read_image(p)


def test_nan_in_exr(tmp_path):
    img = _image()
    img[3, 5, 1] = np.nan
    _write_exr(tmp_path / "n.exr", {c: img[..., i] for i, c in enumerate("RGB")})
    with _raises(tmp_path / "n.exr", re.escape("NaN at (y, x) = (3, 5)")):
        br.read_image(tmp_path / "n.exr")


def test_inf_in_float_tiff(tmp_path):
    img = _image()
    img[2, 7] = np.inf
    tifffile.imwrite(tmp_path / "n.tif", img, photometric="rgb")
    with _raises(tmp_path / "n.tif", re.escape("+Inf at (y, x) = (2, 7)")):
        br.read_image(tmp_path / "n.tif")


def test_nan_in_npy_disparity_and_depth(tmp_path):
    d = np.full((6, 7), 0.5, np.float32)
    d[4, 1] = np.nan
    np.save(tmp_path / "n.npy", d)
    with _raises(tmp_path / "n.npy", re.escape("NaN at (y, x) = (4, 1)")):
        br.read_disparity(tmp_path / "n.npy")
    with _raises(tmp_path / "n.npy", re.escape("NaN at (y, x) = (4, 1)")):
        br.read_depth(tmp_path / "n.npy")


def test_colour_disparity_png_with_differing_channels(tmp_path):
    rgb = np.zeros((4, 5, 3), np.uint8)
    rgb[..., 1] = 9
    Image.fromarray(rgb).save(tmp_path / "d.png")
    with _raises(tmp_path / "d.png", "expected a single-channel disparity map, got 3 channels .the channels differ"):
        br.read_disparity(tmp_path / "d.png")


def test_4d_npy_disparity(tmp_path):
    np.save(tmp_path / "d.npy", np.zeros((2, 3, 4, 1)))
    with _raises(tmp_path / "d.npy", "expected a 2-D .* got 4-D"):
        br.read_disparity(tmp_path / "d.npy")


def test_integer_depth_needs_its_scale(tmp_path):
    """Integer maps hold codes, not metres: refused without ``scale`` (metres per code), read with it."""
    Image.fromarray(np.full((4, 4), 7, np.uint8)).save(tmp_path / "z.png")
    with _raises(tmp_path / "z.png", r"holds integer codes \(uint8\), not metres: give --depth-scale"):
        br.read_depth(tmp_path / "z.png")
    np.testing.assert_array_equal(br.read_depth(tmp_path / "z.png", scale=0.5), np.full((4, 4), 3.5))
    np.save(tmp_path / "z.npy", np.ones((4, 4), np.int32))
    with _raises(tmp_path / "z.npy", r"holds integer codes \(int32\), not metres"):
        br.read_depth(tmp_path / "z.npy")


def test_empty_and_wrong_channel_count(tmp_path):
    np.save(tmp_path / "e.npy", np.zeros((0, 5), np.float32))
    with _raises(tmp_path / "e.npy", "expected a non-empty image"):
        br.read_disparity(tmp_path / "e.npy")
    five = np.zeros((4, 4, 5), np.uint8)
    tifffile.imwrite(tmp_path / "five.tif", five, photometric="minisblack", planarconfig="contig")
    with _raises(tmp_path / "five.tif", "expected 1 to 4 channels, got 5"):
        br.read_image(tmp_path / "five.tif")
    _write_exr(tmp_path / "odd.exr", {"foo": np.zeros((4, 4), np.float32), "bar": np.zeros((4, 4), np.float32)})
    with _raises(tmp_path / "odd.exr", "expected EXR channels R,G,B,A or R,G,B .* got bar,foo"):
        br.read_image(tmp_path / "odd.exr")


def test_too_large_is_rejected_from_the_header(tmp_path, monkeypatch):
    p = tmp_path / "huge.png"  # IHDR claims 100000 x 100000 and there is no pixel data at all
    ihdr = struct.pack(">IIBBBBB", 100_000, 100_000, 8, 2, 0, 0, 0)
    crc = struct.pack(">I", zlib.crc32(b"IHDR" + ihdr))
    p.write_bytes(b"\x89PNG\r\n\x1a\n" + struct.pack(">I", 13) + b"IHDR" + ihdr + crc)
    with _raises(p, "expected at most 200,000,000 pixels, got 100000 x 100000"):
        br.read_image(p)
    monkeypatch.setattr(rd, "MAX_PIXELS", 100)
    for name in ("s.exr", "s.tif"):
        q = br.write_image(tmp_path / name, _image(), bit_depth=None)
        with _raises(q, "expected at most 100 pixels, got 32 x 24"):
            br.read_image(q)


# --------------------------------------------------------------------------- write errors


def test_write_rejects_nan(tmp_path):
    img = _image()
    img[5, 6, 2] = np.nan
    with _raises(tmp_path / "o.png", r"refusing to write .* contains NaN at \(y, x\) = \(5, 6\)"):
        br.write_image(tmp_path / "o.png", img)
    assert not (tmp_path / "o.png").exists()


@pytest.mark.parametrize(
    "name,kwargs,fragment",
    [
        ("o.bmp", {}, "unsupported extension '.bmp' for writing images"),
        ("o.jpg", {"bit_depth": 16}, "JPEG takes bit_depth 8, not 16"),
        ("o.png", {"bit_depth": 32}, "PNG takes bit_depth 8 or 16, not 32"),
        ("o.png", {"half": True}, r"half=True writes half floats, which only EXR stores, and this is a PNG file "
                                  r"\(name it .exr, or leave half=True out\)"),
        ("o.exr", {"half": True, "bit_depth": 32}, "half=True writes 16-bit half floats, and bit_depth 32 asks for "
                                                   "32-bit ones"),
        ("o.tif", {"half": True}, "only EXR stores, and this is a TIFF file"),
        ("o.jpg", {"quality": 0}, r"JPEG quality in \[1, 100\]"),
    ],
)
def test_write_rejects_bad_options(tmp_path, name, kwargs, fragment):
    with _raises(tmp_path / name, fragment):
        br.write_image(tmp_path / name, _image(), **kwargs)


def test_write_rejects_bad_images(tmp_path):
    with _raises(tmp_path / "o.jpg", "without alpha for JPEG"):
        br.write_image(tmp_path / "o.jpg", _image(c=4))
    with _raises(tmp_path / "o.png", "got dtype uint8"):
        br.write_image(tmp_path / "o.png", np.zeros((4, 4, 3), np.uint8))
    with _raises(tmp_path / "o.png", "got shape"):
        br.write_image(tmp_path / "o.png", np.zeros((4, 4, 2), np.float32))
    with _raises(tmp_path / "o.exr", re.escape("HALF range (+-65504) at (y, x) = (1, 2)")):
        big = _image()
        big[1, 2, 0] = 1e6
        br.write_image(tmp_path / "o.exr", big, half=True)
    with _raises(tmp_path / "d.png", r"within \[0, 1\] for 16-bit PNG, got \[0, 1.5\]"):
        br.write_disparity(tmp_path / "d.png", np.array([[0.0, 1.5]]))
    assert list(tmp_path.iterdir()) == []


def test_write_onto_a_directory(tmp_path):
    (tmp_path / "d.exr").mkdir()
    with _raises(tmp_path / "d.exr", "expected a file, got a directory"):
        br.write_disparity(tmp_path / "d.exr", np.zeros((2, 2)))


def test_write_creates_parent_directories(tmp_path):
    p = br.write_image(tmp_path / "a" / "b" / "c.png", _image())
    assert p == tmp_path / "a" / "b" / "c.png" and p.is_file()
    assert [f.name for f in p.parent.iterdir()] == ["c.png"]


# --------------------------------------------------------------------------- atomic writes


def _partial_then_fail(target) -> None:
    """Stand-in for an encoder: writes a few bytes to its target (path or file), then fails."""
    if hasattr(target, "write"):
        target.write(b"partial data")
    else:
        Path(target).write_bytes(b"partial data")
    raise OSError("disk on fire")


@pytest.mark.parametrize("name,bit_depth", [("a.png", 8), ("a.png", 16), ("a.exr", None), ("a.tif", None)])
def test_failed_write_leaves_good_file_untouched(tmp_path, monkeypatch, name, bit_depth):
    target = br.write_image(tmp_path / name, _image(), bit_depth=bit_depth)
    good = target.read_bytes()
    if name == "a.png" and bit_depth == 8:
        monkeypatch.setattr(Image.Image, "save", lambda self, fp, *a, **k: _partial_then_fail(fp))
    elif name == "a.png":
        monkeypatch.setattr(wr, "write_bytes", lambda tmp, data: _partial_then_fail(tmp))
    elif name == "a.exr":
        monkeypatch.setattr(OpenEXR.File, "write", lambda self, target: _partial_then_fail(target))
    else:
        monkeypatch.setattr(tifffile, "imwrite", lambda tmp, *a, **k: _partial_then_fail(tmp))
    with pytest.raises(OSError, match="disk on fire"):
        br.write_image(target, _image() * 0.5, bit_depth=bit_depth)
    assert target.read_bytes() == good
    assert sorted(os.listdir(tmp_path)) == [name]


def test_failed_write_to_new_path_leaves_nothing(tmp_path, monkeypatch):
    monkeypatch.setattr(np, "save", lambda fh, arr, **k: _partial_then_fail(fh))
    with pytest.raises(OSError, match="disk on fire"):
        br.write_disparity(tmp_path / "d.npy", np.zeros((3, 3)))
    assert os.listdir(tmp_path) == []


# --------------------------------------------------------------------------- writer errors, stale temporaries


@pytest.mark.parametrize("name,patch", [
    ("a.exr", "exr"), ("a.png", "pil"), ("a16.png", "bytes"), ("a.tif", "tiff"), ("a.jpg", "pil"), ("d.npy", "npy"),
])
def test_every_writer_error_names_the_output_file(tmp_path, monkeypatch, name, patch):
    """A full disk (ENOSPC), however the encoder reports it, is one OutputError naming the target, not the temp."""
    import errno

    from bokehray.errors import OutputError

    def enospc_os(target, *a, **k):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    def enospc_exr(self, target):  # what OpenEXR's binding raises when the disk fills
        Path(target).write_bytes(b"partial")
        raise RuntimeError(f'Failed to write pixel data to image file "{target}". No space left on device.')

    if patch == "exr":
        monkeypatch.setattr(OpenEXR.File, "write", enospc_exr)
    elif patch == "pil":
        monkeypatch.setattr(Image.Image, "save", lambda self, fp, *a, **k: enospc_os(fp))
    elif patch == "bytes":
        monkeypatch.setattr(wr, "write_bytes", lambda tmp, data: enospc_os(tmp))
    elif patch == "tiff":
        monkeypatch.setattr(tifffile, "imwrite", enospc_os)
    else:
        monkeypatch.setattr(np, "save", lambda fh, arr, **k: enospc_os(fh))
    target = tmp_path / "out" / name
    with pytest.raises(OutputError) as info:
        if name.endswith(".npy"):
            br.write_disparity(target, np.zeros((3, 3)))
        else:
            br.write_image(target, _image(), bit_depth=16 if name == "a16.png" else None)
    assert str(info.value) == f"cannot write {target}: No space left on device"
    assert isinstance(info.value, OSError) and os.listdir(target.parent) == []


def test_a_folder_that_cannot_be_made_is_an_output_error_naming_the_file(tmp_path):
    from bokehray.errors import OutputError

    (tmp_path / "f").write_text("a file, not a folder")
    with pytest.raises(OutputError, match=re.escape(f"cannot write {tmp_path / 'f' / 'o.png'}: ")):
        br.write_image(tmp_path / "f" / "o.png", _image())


def _dead_pid() -> int:
    import subprocess
    import sys

    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid  # reaped: no process has this id (until the system reuses it, which takes a while)


def test_stale_temporaries_of_a_killed_write_are_removed_by_the_next_write(tmp_path):
    prefix = at.temporary_prefix(tmp_path / "o.png")
    host_part = prefix.rsplit("-", 2)[0]
    dead = tmp_path / f"{host_part}-{_dead_pid()}-abc123.png"
    live = tmp_path / f"{host_part}-{os.getppid()}-def456.png"  # our parent is alive: a concurrent writer
    other_host = tmp_path / ".o.png.tmp-elsewhere-1-ghi789.png"  # a shared folder: not ours to judge
    other_name = tmp_path / f".p.png.tmp-{host_part.split('tmp-')[1]}-{_dead_pid()}-jkl.png"
    for f in (dead, live, other_host, other_name):
        f.write_bytes(b"partial")
    br.write_image(tmp_path / "o.png", _image())
    left = sorted(f.name for f in tmp_path.iterdir())
    assert left == sorted(["o.png", live.name, other_host.name, other_name.name])
    assert not at.remove_stale_temporaries(tmp_path / "o.png")


@pytest.mark.slow
@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="zombies are seen through Linux's /proc")
def test_a_killed_writer_not_yet_reaped_counts_as_dead(tmp_path):
    """A pool or a Dask nanny may not have reaped its killed worker when the retry writes: that zombie still answers
    kill(pid, 0), and its temporary stayed (seen once in CI)."""
    import signal
    import subprocess
    import sys
    import time

    p = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        assert at.writer_alive(p.pid)
        os.kill(p.pid, signal.SIGKILL)
        for _ in range(200):  # the kernel marks it a zombie at once; it stays one until we wait for it
            if at.is_zombie(p.pid):
                break
            time.sleep(0.01)
        host_part = at.temporary_prefix(tmp_path / "o.png").rsplit("-", 2)[0]
        stale = tmp_path / f"{host_part}-{p.pid}-abc123.png"
        stale.write_bytes(b"partial")
        assert not at.writer_alive(p.pid)
        assert at.remove_stale_temporaries(tmp_path / "o.png") == [stale] and not stale.exists()
    finally:
        p.kill()
        p.wait()


def test_temporary_names_carry_host_and_pid(tmp_path, monkeypatch):
    seen = []
    monkeypatch.setattr(wr, "encode_pil", lambda tmp, codes, fmt, **k: (seen.append(tmp), Path(tmp).write_bytes(b"x")))
    br.write_image(tmp_path / "o.png", _image())
    name = Path(seen[0]).name
    assert name.startswith(".o.png.tmp-") and f"-{os.getpid()}-" in name and name.endswith(".png")


@pytest.mark.parametrize("size", [230, 251, 255])
def test_a_name_near_the_file_systems_limit_is_written_and_its_stale_temporary_found(tmp_path, size):
    """Output names of 230-255 bytes failed with "File name too long" after the whole render: the hidden temporary's
    name (the name plus about 60 bytes) passed the file system's limit. A long name is shortened in the temporary."""
    name = "\u00e9" * ((size - 4) // 2) + "a" * ((size - 4) % 2) + ".png"  # two bytes a character in UTF-8
    assert len(os.fsencode(name)) == size
    target = tmp_path / name
    host_part = at.temporary_prefix(target).rsplit("-", 2)[0]
    assert len(os.fsencode(host_part)) < 200
    stale = tmp_path / f"{host_part}-{_dead_pid()}-abc123.png"
    stale.write_bytes(b"partial")
    assert br.write_image(target, _image()) == target
    assert sorted(f.name for f in tmp_path.iterdir()) == [name]
    stale.write_bytes(b"partial")  # a batch's clean-up finds it by the output's name too
    assert at.remove_stale_outputs(tmp_path, [name]) == 1 and not stale.exists()


def test_a_name_beyond_the_file_systems_limit_is_refused_before_the_render(tmp_path):
    from bokehray.output.write import check_output_path

    name = "a" * 252 + ".png"
    with _raises(tmp_path / name, "the file name is 256 bytes long, more than the file system takes"):
        check_output_path(tmp_path / name)
    assert check_output_path(tmp_path / name[1:]) == tmp_path / name[1:]


# --------------------------------------------------------------------------- values as the file holds them


def test_float64_beyond_float32_is_reported_as_the_file_holds_it(tmp_path):
    """Disparity is float32: a value beyond its range is refused as the file holds it (depth is float64: kept)."""
    import warnings

    a = np.full((4, 5), 0.5)
    a[2, 3] = 1e300
    np.save(tmp_path / "d.npy", a)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no RuntimeWarning on the way (it used to say "overflow in cast")
        with _raises(tmp_path / "d.npy", re.escape("expected values within float32's range (+-3.4e38), got 1e+300 "
                                                    "at (y, x) = (2, 3)")):
            br.read_disparity(tmp_path / "d.npy")
    assert br.read_depth(tmp_path / "d.npy")[2, 3] == 1e300


def test_float64_tiff_image_beyond_float32_is_refused_without_warnings(tmp_path):
    import warnings

    a = np.full((4, 5, 3), 0.5)
    a[1, 2, 0] = -5e39
    tifffile.imwrite(tmp_path / "i.tif", a, photometric="rgb")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with _raises(tmp_path / "i.tif", re.escape("got -5e+39 at (y, x) = (1, 2)")):
            br.read_image(tmp_path / "i.tif")


def test_writers_refuse_float64_beyond_float32_without_warnings(tmp_path):
    import warnings

    a = np.full((4, 5, 3), 0.5)
    a[0, 1, 2] = 1e300
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with _raises(tmp_path / "o.exr", re.escape("beyond float32's range (+-3.4e38): 1e+300 at (y, x) = (0, 1)")):
            br.write_image(tmp_path / "o.exr", a)
        with _raises(tmp_path / "d.npy", re.escape("1e+300 at (y, x) = (0, 1)")):
            br.write_disparity(tmp_path / "d.npy", a[..., 2])
        rgba = np.full((2, 2, 4), 3e38, np.float32)
        rgba[..., 3] = 2.0  # alpha above 1 times a colour near float32's maximum
        with _raises(tmp_path / "o.exr", "overflows float32: \\+Inf"):
            br.write_image(tmp_path / "o.exr", rgba)
    assert os.listdir(tmp_path) == []


# --------------------------------------------------------------------------- questionable inputs decided


def test_alpha_only_exr_is_neither_an_image_nor_a_map(tmp_path):
    """A lone 'A' channel is a matte (coverage); it used to be read as grey and accepted as disparity."""
    _write_exr(tmp_path / "a.exr", {"A": np.full((4, 5), 0.5, np.float32)})
    for read in (br.read_image, br.read_disparity, br.read_depth):
        with _raises(tmp_path / "a.exr", "holds only the alpha channel 'A' \\(coverage, not values\\)"):
            read(tmp_path / "a.exr")
    _write_exr(tmp_path / "layer.exr", {"matte.A": np.full((4, 5), 0.5, np.float32)})
    with _raises(tmp_path / "layer.exr", "alpha channel 'matte.A'"):
        br.read_disparity(tmp_path / "layer.exr")
    _write_exr(tmp_path / "z.exr", {"depth": np.full((4, 5), 0.5, np.float32)})  # any other lone channel: taken
    assert br.read_disparity(tmp_path / "z.exr").shape == (4, 5)


def test_cmyk_jpeg_is_refused_not_miscoloured(tmp_path):
    """Without its ICC profile CMYK has no defined RGB (a real CMYK photo decoded to mean 0.31 for 0.50)."""
    Image.new("RGB", (16, 12), (128, 128, 128)).convert("CMYK").save(tmp_path / "c.jpg", quality=95)
    with _raises(tmp_path / "c.jpg", "expected an RGB or greyscale JPEG, got CMYK colour"):
        br.read_image(tmp_path / "c.jpg")


def test_multi_page_tiff_is_refused_but_reduced_resolution_pages_are_ignored(tmp_path):
    a, b = np.zeros((8, 9), np.uint16), np.full((8, 9), 60000, np.uint16)
    tifffile.imwrite(tmp_path / "stack.tif", np.stack([a, b]), photometric="minisblack")
    with tifffile.TiffWriter(tmp_path / "two.tif") as w:
        w.write(a, photometric="minisblack")
        w.write(b, photometric="minisblack")
    for name in ("stack.tif", "two.tif"):
        for read in (br.read_image, br.read_disparity):
            with _raises(tmp_path / name, "expected one image, got a multi-page TIFF with 2 full-size pages"):
                read(tmp_path / name)
    with tifffile.TiffWriter(tmp_path / "pyramid.tif") as w:  # a preview page is not a second image
        w.write(b, photometric="minisblack")
        w.write(b[::2, ::2], photometric="minisblack", subfiletype=1)
    np.testing.assert_array_equal(br.read_disparity(tmp_path / "pyramid.tif"), b / np.float32(65535))


def test_jpeg_compressed_ycbcr_tiff_reads_as_rgb_and_other_ycbcr_is_refused(tmp_path):
    """Scanners and Photoshop save JPEG-compressed TIFFs as YCbCr; tifffile's JPEG decoder returns them as RGB, so
    they were refused for nothing. Uncompressed YCbCr comes back as luma and chroma: still refused, saying why."""
    codes = np.round(colour.linear_to_srgb(_smooth()) * 255).astype(np.uint8)
    tifffile.imwrite(tmp_path / "rgb.tif", codes, photometric="rgb")
    tifffile.imwrite(tmp_path / "ycc.tif", codes, photometric="rgb", compression="jpeg")  # stored as YCbCr
    with tifffile.TiffFile(tmp_path / "ycc.tif") as tf:
        assert tf.pages[0].photometric == tifffile.PHOTOMETRIC.YCBCR
        decoded = tf.pages[0].asarray()
    ycc = br.read_image(tmp_path / "ycc.tif")
    rgb = br.read_image(tmp_path / "rgb.tif")
    assert ycc.shape == rgb.shape == (48, 64, 3)
    assert np.abs(ycc - rgb).mean() < 0.01 and np.abs(ycc - rgb).max() < 0.05  # JPEG's loss only
    tifffile.imwrite(tmp_path / "same.tif", decoded, photometric="rgb")  # the decoded codes, decoded from sRGB alike
    np.testing.assert_array_equal(ycc, br.read_image(tmp_path / "same.tif"))
    tifffile.imwrite(tmp_path / "raw.tif", codes, photometric="ycbcr")
    with _raises(tmp_path / "raw.tif", "got photometric YCBCR with NONE compression, whose samples decode as luma"):
        br.read_image(tmp_path / "raw.tif")


def test_white_is_zero_tiff_is_inverted(tmp_path):
    """A MINISWHITE (0 = white) greyscale TIFF reads as the picture it shows, as its black-is-zero twin would."""
    grey = RNG.integers(0, 65536, (12, 16), dtype=np.uint16)
    tifffile.imwrite(tmp_path / "black.tif", grey, photometric="minisblack")
    tifffile.imwrite(tmp_path / "white.tif", 65535 - grey, photometric="miniswhite")
    np.testing.assert_array_equal(br.read_image(tmp_path / "white.tif"), br.read_image(tmp_path / "black.tif"))
    np.testing.assert_array_equal(br.read_disparity(tmp_path / "white.tif"), grey / np.float32(65535))
    with_alpha = np.stack([255 - (grey >> 8), np.full_like(grey, 200)], axis=-1).astype(np.uint8)
    tifffile.imwrite(tmp_path / "wa.tif", with_alpha, photometric="miniswhite", extrasamples=["unassalpha"])
    back = br.read_image(tmp_path / "wa.tif")
    np.testing.assert_allclose(back[..., 3], 200 / 255, rtol=1e-6)  # the alpha is not inverted
    np.testing.assert_array_equal(back[..., 0], colour.srgb_decode_lut(8)[(grey >> 8).astype(np.uint8)])
    tifffile.imwrite(tmp_path / "wf.tif", grey.astype(np.float32) / 65535, photometric="miniswhite")
    with _raises(tmp_path / "wf.tif", r"expected integer samples in a white-is-zero \(MINISWHITE\) TIFF, got float32"):
        br.read_image(tmp_path / "wf.tif")


def _write_exr_windows(path: Path, channels: dict[str, np.ndarray], data: tuple, display: tuple) -> None:
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage,
              "dataWindow": data, "displayWindow": display}
    with OpenEXR.File(header, {k: np.ascontiguousarray(v) for k, v in channels.items()}) as f:
        f.write(str(path))


def test_an_exr_whose_data_window_is_not_its_display_window_is_refused(tmp_path, capsys):
    """A crop or border render (data window inside the frame) or overscan (beyond it) was read as a smaller or larger
    picture that had lost its place in the frame. Refused now, naming both windows; equal windows anywhere are read."""
    from bokehray.app.cli import main

    v = RNG.uniform(0.0, 1.0, (4, 5)).astype(np.float32)
    chans = {"R": v, "G": v, "B": v, "Y": v, "Z": v + 1}
    _write_exr_windows(tmp_path / "crop.exr", chans, ((10, 20), (14, 23)), ((0, 0), (99, 99)))
    _write_exr_windows(tmp_path / "over.exr", chans, ((-1, -1), (3, 2)), ((0, 0), (2, 1)))
    _write_exr_windows(tmp_path / "corner.exr", chans, ((0, 0), (4, 3)), ((0, 0), (99, 99)))
    for name, data, display in (("crop.exr", r"\(10, 20\)..\(14, 23\), 5 x 4", r"\(0, 0\)..\(99, 99\), 100 x 100"),
                                ("over.exr", r"\(-1, -1\)..\(3, 2\), 5 x 4", r"\(0, 0\)..\(2, 1\), 3 x 2"),
                                ("corner.exr", r"\(0, 0\)..\(4, 3\), 5 x 4", r"\(0, 0\)..\(99, 99\), 100 x 100")):
        for read in (br.read_image, br.read_disparity, br.read_depth, rd.read_size):
            with _raises(tmp_path / name, f"its data window {data} \\(the pixels it stores\\) differs from its "
                                          f"display window {display}"):
                read(tmp_path / name)
    _write_exr_windows(tmp_path / "moved.exr", chans, ((10, 20), (14, 23)), ((10, 20), (14, 23)))
    np.testing.assert_array_equal(br.read_image(tmp_path / "moved.exr"), np.stack([v, v, v], axis=-1))
    np.testing.assert_array_equal(br.read_depth(tmp_path / "moved.exr"), v + 1)  # Z; as disparity, channels differ
    assert rd.read_size(tmp_path / "moved.exr") == (4, 5)
    br.write_disparity(tmp_path / "d.npy", v)
    code = main(["render", str(tmp_path / "crop.exr"), "--disparity", str(tmp_path / "d.npy"), "-o", str(tmp_path / "o.png")])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and err.startswith("bokehray: error: ") and "crop.exr" in err, err
    assert "display window" in err and not (tmp_path / "o.png").exists()


@pytest.mark.parametrize(("bits", "dtype"), [(12, np.uint16), (10, np.uint16), (4, np.uint8)])
def test_tiff_codes_are_scaled_by_the_files_own_bit_depth(tmp_path, bits, dtype):
    """A 12-bit TIFF (BitsPerSample 12: packed samples tifffile unpacks into uint16 codes up to 4095) was divided by
    65535, the container's largest code, and read 16 times too dark; a 4-bit one by 255 instead of 15. Codes are
    divided by the file's own largest code now. Depth maps keep their codes (metres per code is the user's scale)."""
    white = (1 << bits) - 1
    codes = RNG.integers(0, white + 1, (12, 16), dtype=dtype)
    codes[0, 0], codes[0, 1] = 0, white
    tifffile.imwrite(tmp_path / "g.tif", codes, photometric="minisblack", bitspersample=bits)
    with tifffile.TiffFile(tmp_path / "g.tif") as tf:  # what the decoder gives: the file's codes in a wider container
        assert tf.pages[0].bitspersample == bits and tf.pages[0].dtype == dtype
        np.testing.assert_array_equal(tf.pages[0].asarray(), codes)
    np.testing.assert_array_equal(br.read_disparity(tmp_path / "g.tif"), (codes / np.float64(white)).astype(np.float32))
    img = br.read_image(tmp_path / "g.tif")
    expected = colour.srgb_decode_lut(bits)[codes]
    np.testing.assert_array_equal(img, np.repeat(expected[..., None], 3, axis=2))
    assert img[0, 1, 0] == 1.0 and img[0, 0, 0] == 0.0  # the file's white is white
    np.testing.assert_array_equal(br.read_depth(tmp_path / "g.tif", scale=0.001), codes * 0.001)
    rgba = np.stack([codes, codes[::-1], codes[:, ::-1], np.full_like(codes, white)], axis=-1)
    tifffile.imwrite(tmp_path / "c.tif", rgba, photometric="rgb", bitspersample=bits, extrasamples=["unassalpha"])
    back = br.read_image(tmp_path / "c.tif")
    np.testing.assert_array_equal(back[..., :3], colour.srgb_decode_lut(bits)[rgba[..., :3]])
    np.testing.assert_array_equal(back[..., 3], 1.0)
    tifffile.imwrite(tmp_path / "w.tif", white - codes, photometric="miniswhite", bitspersample=bits)
    np.testing.assert_array_equal(br.read_disparity(tmp_path / "w.tif"), br.read_disparity(tmp_path / "g.tif"))


def test_tiff_codes_beyond_the_declared_bit_depth_are_refused(tmp_path, monkeypatch):
    """A decoder handing back codes above what BitsPerSample allows (a damaged or mislabelled file) is refused
    rather than read past 1 (or past the 12-bit decoding table)."""
    tifffile.imwrite(tmp_path / "g.tif", np.full((4, 5), 4095, np.uint16), photometric="minisblack", bitspersample=12)
    monkeypatch.setattr(tifffile.TiffPage, "asarray", lambda self, *a, **k: np.full((4, 5), 5000, np.uint16))
    with _raises(tmp_path / "g.tif", "holds codes up to 5000, above 4095, the largest 12-bit code"):
        br.read_image(tmp_path / "g.tif")


@pytest.mark.parametrize("name", ["i.png", "i16.png", "i.jpg", "i.tif", "i.exr", "d.npy", "d.exr", "planar.tif"])
def test_read_size_matches_the_decoded_shape_without_decoding(tmp_path, monkeypatch, name):
    img = _image(13, 17)
    p = tmp_path / name
    if name == "d.npy" or name == "d.exr":
        br.write_disparity(p, img[..., 0])
    elif name == "planar.tif":
        tifffile.imwrite(p, np.moveaxis((img * 255).astype(np.uint8), -1, 0), photometric="rgb", planarconfig="separate")
    else:
        br.write_image(p, img, bit_depth=16 if name == "i16.png" else None)
    shape = (br.read_disparity(p) if name.startswith("d") else br.read_image(p)).shape[:2]
    monkeypatch.setattr(rd, "load_samples", lambda *a, **k: pytest.fail("read_size decoded pixels"))
    assert rd.read_size(p) == shape == (13, 17)


def test_read_size_refuses_what_it_cannot_read(tmp_path):
    (tmp_path / "x.png").write_bytes(b"not a png at all, really not")
    with _raises(tmp_path / "x.png", "not a PNG file"):
        rd.read_size(tmp_path / "x.png")
    with _raises(tmp_path / "nope.exr", "does not exist"):
        rd.read_size(tmp_path / "nope.exr")


@pytest.mark.slow
def test_outputs_are_byte_reproducible_across_processes(tmp_path):
    """The sRGB profile tagging PNG/JPEG/TIFF outputs is made by littleCMS, which stamps the time it was made: two
    runs wrote different bytes for the same image (found comparing batch outputs of two executors)."""
    import subprocess
    import sys

    code = ("import sys, numpy as np, bokehray as br; "
            "br.write_image(sys.argv[1], np.linspace(0, 1, 48, dtype=np.float32).reshape(4, 4, 3))")
    outs = []
    for i in range(2):
        p = tmp_path / f"o{i}.png"
        subprocess.run([sys.executable, "-c", code, str(p)], check=True)
        outs.append(p.read_bytes())
    assert outs[0] == outs[1]


@pytest.mark.parametrize("no_links", [None, errno.EPERM, errno.EINVAL, errno.ENOSYS])
def test_an_exclusive_write_never_replaces_a_file_made_meanwhile(tmp_path, monkeypatch, no_links):
    """Two writers that chose the same free name: the one that finishes second gets OutputExistsError, the first one's
    file stays as written and no temporary is left (``no_links``: a file system without hard links, and how it
    says so)."""
    from bokehray.errors import OutputExistsError

    target = tmp_path / "o.png"
    if no_links is not None:
        def no_link(src, dst):
            raise OSError(no_links, os.strerror(no_links))

        monkeypatch.setattr(at.os, "link", no_link)

    def encode_while_another_writes(tmp):
        target.write_bytes(b"the other writer's file")
        Path(tmp).write_bytes(b"ours")

    with pytest.raises(OutputExistsError, match="o.png: a file of that name was made meanwhile"):
        at.atomic_write(target, encode_while_another_writes, exclusive=True)
    assert target.read_bytes() == b"the other writer's file" and [f.name for f in tmp_path.iterdir()] == ["o.png"]
    fresh = tmp_path / "p.png"
    assert at.atomic_write(fresh, lambda tmp: Path(tmp).write_bytes(b"ours"), exclusive=True) == fresh
    assert fresh.read_bytes() == b"ours" and sorted(f.name for f in tmp_path.iterdir()) == ["o.png", "p.png"]
    at.atomic_write(target, lambda tmp: Path(tmp).write_bytes(b"replaced"))  # not exclusive: replaces, as before
    assert target.read_bytes() == b"replaced"


def test_an_exclusive_write_does_not_replace_a_dangling_link(tmp_path):
    from bokehray.errors import OutputExistsError

    link = tmp_path / "o.png"
    link.symlink_to(tmp_path / "gone.png")
    with pytest.raises(OutputExistsError):
        at.atomic_write(link, lambda tmp: Path(tmp).write_bytes(b"ours"), exclusive=True)
    assert link.is_symlink() and [f.name for f in tmp_path.iterdir()] == ["o.png"]


def test_an_exclusive_write_tries_the_next_names_without_encoding_again(tmp_path):
    """Where the name is taken, ``next_name`` gives the next one and the same encoded file is published there: the
    encoder runs once, the taken files stay, no temporary is left; None gives up; a name in another folder or with
    another extension (the file is encoded for this one) is refused."""
    from bokehray.errors import OutputError, OutputExistsError

    for name in ("o-001.png", "o-002.png"):
        (tmp_path / name).write_bytes(b"taken")
    encoded = []
    encode = lambda tmp: encoded.append(tmp) or Path(tmp).write_bytes(b"ours")  # noqa: E731
    names = iter(tmp_path / f"o-{n:03d}.png" for n in (2, 3))
    got = at.atomic_write(tmp_path / "o-001.png", encode, exclusive=True, next_name=lambda taken: next(names))
    assert got == tmp_path / "o-003.png" and got.read_bytes() == b"ours" and len(encoded) == 1
    assert sorted(f.name for f in tmp_path.iterdir()) == ["o-001.png", "o-002.png", "o-003.png"]
    assert (tmp_path / "o-001.png").read_bytes() == (tmp_path / "o-002.png").read_bytes() == b"taken"
    with pytest.raises(OutputExistsError):
        at.atomic_write(tmp_path / "o-001.png", encode, exclusive=True, next_name=lambda taken: None)
    for other in (tmp_path / "sub" / "o-009.png", tmp_path / "o-009.jpg"):
        with pytest.raises(OutputError, match="encoded as .png"):
            at.atomic_write(tmp_path / "o-001.png", encode, exclusive=True, next_name=lambda taken, o=other: o)
    assert sorted(f.name for f in tmp_path.iterdir()) == ["o-001.png", "o-002.png", "o-003.png"]


@pytest.mark.parametrize("ext", ["png", "jpg", "tif", "exr"])
def test_writing_leaves_the_caller_s_float32_image_as_it_was(tmp_path, ext):
    """to_float32 hands float32 pixels on without a copy: no writer may change them (RGBA EXR premultiplies, the
    integer formats clip and encode, all into arrays of their own)."""
    rng = np.random.default_rng(3)
    img = (rng.random((37, 53, 4), dtype=np.float32) * 1.4 - 0.2)
    img[..., 3] = np.clip(img[..., 3], 0, 1)
    img = img if ext in ("png", "tif", "exr") else np.ascontiguousarray(img[..., :3])
    before = img.copy()
    br.write_image(tmp_path / f"o.{ext}", img)
    assert np.array_equal(img, before)
