"""Reading images, disparity maps and depth maps.

Conventions: images are ``float32`` arrays ``H x W x C`` in scene-linear light, row 0 at the top. Display-referred
files (PNG, JPEG, integer TIFF) are decoded from sRGB; OpenEXR and float TIFF hold linear values and stay linear.
Alpha is linear coverage and colour is never premultiplied (OpenEXR stores premultiplied colour by specification,
so it is divided by alpha on read). Every bad input raises :class:`~bokehray.errors.InputError` naming the file.
"""

from __future__ import annotations

import contextlib
import os
import struct
from collections.abc import Iterator
from pathlib import Path

import imagecodecs
import numpy as np
import OpenEXR
import tifffile
from PIL import Image

from .._memory import available_bytes, on_cores, row_bands
from .._quiet import library_log, native_output
from ..colour import srgb_decode_lut
from ..errors import InputError, ResourceError
from ..formats import check_finite, first_index, format_of, range_prefix, to_float32
from ..validate import check_path

__all__ = ["MAX_PIXELS", "decode_codes", "load_samples", "read_disparity", "read_image", "read_size", "single_channel"]

MAX_PIXELS = 200_000_000
"""Largest image (height x width) any reader accepts."""

_DECODE_BYTES_PER_PX = 40
"""Peak bytes per pixel while decoding (4 channels of 16-bit codes or float32 samples, plus the float32
result and a conversion temporary): a file whose header declares more than the memory available is
refused before any pixel is decoded (a decompression bomb)."""
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _check_dims(path: Path, h: int, w: int) -> None:
    if h <= 0 or w <= 0:
        raise InputError(f"{path}: expected a non-empty image, got {w} x {h} pixels")
    if h * w > MAX_PIXELS:
        raise InputError(f"{path}: expected at most {MAX_PIXELS:,} pixels, got {w} x {h} = {h * w:,}")
    need, have = h * w * _DECODE_BYTES_PER_PX, available_bytes()
    if need > have:
        raise ResourceError(f"{path}: decoding {w} x {h} pixels needs about {need >> 20:,} MB, but only "
                            f"{have >> 20:,} MB of memory is available")


@contextlib.contextmanager
def _decoding(path: Path, fmt: str) -> Iterator[None]:
    """Turn a decoder library's exception into an InputError naming the file and format."""
    try:
        yield
    except (InputError, ResourceError):
        raise
    except MemoryError:
        raise ResourceError(f"{path}: ran out of memory while decoding it as {fmt}") from None
    except Exception as exc:  # noqa: BLE001 - decoders raise anything from OSError to RuntimeError
        raise InputError(f"cannot read {path} as {fmt}: {exc}") from None


# --------------------------------------------------------------------------- decoders


def _png_header(path: Path) -> tuple[int, int, int]:
    """Width, height and bit depth from the IHDR chunk."""
    with open(path, "rb") as fh:
        head = fh.read(33)
    if len(head) < 33 or head[:8] != _PNG_SIGNATURE or head[12:16] != b"IHDR":
        raise InputError(f"cannot read {path} as PNG: not a PNG file (bad signature or header)")
    w, h, depth = struct.unpack(">IIB", head[16:25])
    return w, h, depth


def _png_images(path: Path) -> int:
    """How many images a PNG holds: 1, or an animated PNG's (APNG) frames, as Pillow counts them from the chunks
    before the image data (no pixel is decoded)."""
    with Image.open(path, formats=["PNG"]) as im:
        return int(getattr(im, "n_frames", 1))


def _load_png(path: Path) -> np.ndarray:
    w, h, depth = _png_header(path)
    _check_dims(path, h, w)
    images = _png_images(path)
    if images > 1:  # both decoders return the first frame alone, silently
        raise InputError(f"{path}: expected one image, got an animated PNG (APNG) with {images} frames; save the "
                         "frame to use as its own file")
    if depth != 16:
        return decode_pil(path, "PNG")
    # Pillow truncates 16-bit colour PNGs to 8 bits; imagecodecs (libpng) keeps all 16.
    data = path.read_bytes()
    try:
        with library_log("imagecodecs"):  # libpng's warnings (an iCCP profile it rejects): the pixels decode fine
            return np.asarray(imagecodecs.png_decode(data))
    except imagecodecs.PngError as exc:
        raise ValueError(f"file is truncated or corrupt (libpng: {exc})") from None


def decode_pil(path: Path, fmt: str) -> np.ndarray:
    with Image.open(path, formats=[fmt]) as im:  # lazy: reads the header only
        _check_dims(path, im.height, im.width)
        if im.mode in ("CMYK", "YCbCr", "LAB", "HSV"):  # a JPEG in CMYK/YCCK: colours need its ICC profile
            raise InputError(f"{path}: expected an RGB or greyscale {fmt}, got {im.mode} colour, which has no "
                             "defined conversion to RGB without a colour-managed workflow; convert it to sRGB first "
                             "(e.g. ImageMagick: magick in.jpg -colorspace sRGB out.jpg)")
        im.load()
        if "transparency" in im.info:
            im = im.convert("RGBA")
        elif im.mode not in ("L", "LA", "RGB", "RGBA"):
            im = im.convert("RGB")
        return np.asarray(im)


def _load_tiff(path: Path, *, size_only: bool = False):
    with library_log("tifffile") as said:
        try:
            return _load_tiff_quietly(path, size_only=size_only)
        except (InputError, ResourceError):
            raise
        except Exception as exc:  # noqa: BLE001 - tifffile's log often says more than its exception
            why = f"{exc}; {said[0]}" if said else str(exc)
            raise ValueError(why) from None


_TIFF_AUXILIARY = 0b101
"""NewSubfileType bits of pages that are not separate images: reduced resolution (1), transparency mask (4)."""


_TIFF_JPEG = (tifffile.COMPRESSION.JPEG, tifffile.COMPRESSION.OJPEG, tifffile.COMPRESSION.JPEG_LOSSY,
              tifffile.COMPRESSION.ALT_JPEG)
"""Compressions whose YCbCr samples tifffile has libjpeg convert to RGB (its ``jpeg_decode_colorspace``)."""


def _ycbcr_decodes_to_rgb(page: tifffile.TiffPage) -> bool:
    """Whether tifffile returns a YCbCr page as RGB: only a JPEG decoder converts it, and only for interleaved
    samples without extra (alpha) ones; other YCbCr pages (uncompressed, LZW, planar) come back as Y, Cb, Cr."""
    return (page.compression in _TIFF_JPEG and page.planarconfig == tifffile.PLANARCONFIG.CONTIG
            and not page.extrasamples)


def _check_codes_fit(path: Path, a: np.ndarray, bits: int) -> None:
    """Integer codes of a file narrower than their dtype (12-bit in uint16) must fit the file's bit depth."""
    white = (1 << bits) - 1
    if a.dtype.kind == "u" and bits < a.dtype.itemsize * 8 and a.size and int(a.max()) > white:
        raise InputError(f"{path}: holds codes up to {int(a.max())}, above {white}, the largest {bits}-bit code its "
                         "BitsPerSample declares")


def _load_tiff_quietly(path: Path, *, size_only: bool = False) -> tuple[np.ndarray, int] | tuple[int, int]:
    with tifffile.TiffFile(path) as tf:
        page = tf.pages[0]
        axes = page.axes
        dims = dict(zip(axes, page.shape))
        if size_only:
            return dims.get("Y", 0), dims.get("X", 0)
        _check_dims(path, dims.get("Y", 0), dims.get("X", 0))
        n_pages = len(tf.pages)
        images = 1 + sum(1 for i in range(1, min(n_pages, 64)) if not tf.pages[i].subfiletype & _TIFF_AUXILIARY)
        if images > 1:
            more = "+" if n_pages > 64 else ""
            raise InputError(f"{path}: expected one image, got a multi-page TIFF with {images}{more} full-size pages; "
                             "save the page to use as its own file")
        if set(axes) - set("SYX"):
            raise InputError(f"{path}: expected a 2-D TIFF image (axes YX, YXS or SYX), got axes {axes}")
        photometric, ph = page.photometric, tifffile.PHOTOMETRIC
        if photometric not in (ph.MINISBLACK, ph.MINISWHITE, ph.RGB, ph.YCBCR):
            raise InputError(f"{path}: expected a greyscale or RGB TIFF, got photometric {photometric.name}")
        if photometric == ph.YCBCR and not _ycbcr_decodes_to_rgb(page):
            raise InputError(f"{path}: expected a greyscale or RGB TIFF, got photometric YCBCR with "
                             f"{page.compression.name} compression, whose samples decode as luma and chroma, not RGB "
                             "(only JPEG-compressed, interleaved YCbCr without extra samples decodes to RGB); save it "
                             "as an RGB TIFF first")
        if tifffile.EXTRASAMPLE.ASSOCALPHA in page.extrasamples:
            raise InputError(f"{path}: expected unassociated alpha, got associated (premultiplied) alpha")
        if page.dtype not in (np.uint8, np.uint16, np.float16, np.float32, np.float64):
            raise InputError(f"{path}: expected uint8, uint16 or float samples, got {page.dtype}")
        if photometric == ph.MINISWHITE and page.dtype.kind != "u":
            raise InputError(f"{path}: expected integer samples in a white-is-zero (MINISWHITE) TIFF, got "
                             f"{page.dtype}, which has no defined white to invert from")
        a = page.asarray()
        bits = int(page.bitspersample)
        white = (1 << bits) - 1
    a = np.moveaxis(a, axes.index("S"), -1) if "S" in axes else a
    _check_codes_fit(path, a, bits)
    if photometric == ph.MINISWHITE:  # 0 is white: the grey (not the alpha) turned into black-is-zero codes
        grey = a[..., 0] if a.ndim == 3 else a
        np.subtract(white, grey, out=grey, casting="unsafe")
    return a, bits


def _exr_windows(path: Path) -> tuple[tuple[int, int, int, int], tuple[int, int, int, int] | None]:
    """The header's dataWindow (the pixels the file stores) and displayWindow (the picture's frame), each as
    ``(x0, y0, x1, y1)``, inclusive; a file the binding cannot read is an InputError naming it."""
    failure = None
    with native_output() as said:
        try:
            with OpenEXR.File(str(path), header_only=True) as f:
                header = f.header()
                (x0, y0), (x1, y1) = header["dataWindow"]
                data = int(x0), int(y0), int(x1), int(y1)
                display = header.get("displayWindow")
                if display is not None:
                    (x0, y0), (x1, y1) = display
                    display = int(x0), int(y0), int(x1), int(y1)
        except Exception as exc:  # noqa: BLE001 - as in _exr_channels
            failure = exc
    if failure is not None or said:
        why = (said[0] if said else str(failure)).removeprefix(f"{path}: ")
        raise InputError(f"cannot read {path} as EXR: file is truncated or corrupt ({why})")
    return data, display


def _exr_size(path: Path, *, check: bool = False) -> tuple[int, int]:
    """``(height, width)`` of the EXR's data window, which must be its display window (docs/robustness.md, "Reading files"):
    a data window inside a larger frame (a crop or border render) or beyond it (overscan) is refused, naming both,
    rather than read as a smaller or larger picture that has lost its place in the frame. ``check``: the pixel and
    memory limits as well (the reader's)."""
    if not OpenEXR.isOpenExrFile(str(path)):
        raise InputError(f"cannot read {path} as EXR: not an OpenEXR file (bad magic number)")
    data, display = _exr_windows(path)
    h, w = data[3] - data[1] + 1, data[2] - data[0] + 1
    if check:
        _check_dims(path, h, w)
    if display is not None and display != data:
        def box(b: tuple[int, int, int, int]) -> str:
            return f"({b[0]}, {b[1]})..({b[2]}, {b[3]}), {b[2] - b[0] + 1} x {b[3] - b[1] + 1}"
        raise InputError(f"{path}: its data window {box(data)} (the pixels it stores) differs from its display "
                         f"window {box(display)} (the picture's frame); bokehray reads EXRs whose two windows are the "
                         "same: crop or pad it to the display window first (e.g. oiiotool in.exr --croptofull -o "
                         "out.exr)")
    return h, w


_EXR_NOT_RGB = (({"RY", "BY"}, "luminance/chroma channels (Y, RY, BY)"), ({"X", "Y", "Z"}, "CIE X, Y, Z channels"))
"""Channel sets of EXR colour that is not RGB: their Y is only the luminance, so reading it as a grey image would
drop the colour silently."""


def _is_alpha(name: str) -> bool:
    """An EXR channel of coverage (``A``, or a layer's ``*.A``), not of values."""
    return name == "A" or name.endswith(".A")


def _exr_map_channel(path: Path, chans: dict[str, np.ndarray], preferred: tuple[tuple[str, ...], ...],
                     what: str) -> str:
    """The channel a disparity or depth map is read from: the first ``preferred`` one the file holds (depth: ``Z``,
    the standard depth channel, whatever else is there), else its only channel, or any of its channels when they
    are all equal (an alpha channel aside: a grey map saved as RGBA). Channels that differ are refused, named:
    taking the first would be a guess."""
    for (name,) in preferred:
        if name in chans:
            return name
    names = sorted(n for n in chans if not _is_alpha(n)) or sorted(chans)  # coverage is no value
    first = chans[names[0]]
    if any(chans[n].shape != first.shape or not np.array_equal(chans[n], first) for n in names[1:]):
        hint = f" (or name the map's channel {preferred[0][0]})" if preferred else ""
        raise InputError(f"{path}: expected a single-channel {what} map, got {len(names)} EXR channels "
                         f"({','.join(names)}) that differ; save the map as one channel{hint}")
    return names[0]


def _check_exr_colour(path: Path, chans: dict[str, np.ndarray], picked: tuple[str, ...]) -> None:
    if picked[0] != "Y":
        return
    for needs, words in _EXR_NOT_RGB:
        if needs <= set(chans):
            raise InputError(f"{path}: holds {words}, not R, G, B; bokehray reads RGB or greyscale EXR images, and "
                             "its Y alone would render the photo as grey: convert it to an RGB EXR first")


def _exr_channels(path: Path) -> dict[str, np.ndarray]:
    """Every channel of the EXR's first part by name (packed ones split), after its size and windows are checked;
    a file the binding cannot read, or warns about, is an InputError naming it."""
    _exr_size(path, check=True)  # the magic number, the windows, the size
    chans: dict[str, np.ndarray] = {}
    failure = None
    with native_output() as said:
        try:
            with OpenEXR.File(str(path), separate_channels=True) as f:
                for name, ch in f.parts[0].channels.items():
                    px = ch.pixels
                    if px.ndim == 3 and len(name) == px.shape[-1]:  # packed "RGB"/"RGBA" channel
                        chans.update(zip(name, np.moveaxis(px, -1, 0)))
                    else:
                        chans[name] = px
        except (InputError, ResourceError):
            raise
        except Exception as exc:  # noqa: BLE001 - the binding raises anything; the library's own words are better
            failure = exc
    # the binding reports damaged pixel data as a printed warning and carries on: never return what it made of it
    if failure is not None or said:
        why = (said[0] if said else str(failure)).removeprefix(f"{path}: ")
        raise InputError(f"cannot read {path} as EXR: file is truncated or corrupt ({why})")
    return chans


def _load_exr(path: Path, choices: tuple[tuple[str, ...], ...], map_of: str | None = None) -> np.ndarray:
    """The file's channels in ``choices`` (the first set it holds all of), or for a map (``map_of``: what it is)
    its one channel (:func:`_exr_map_channel`, ``choices`` the channels preferred)."""
    chans = _exr_channels(path)
    only = tuple(chans) if len(chans) == 1 else None
    wanted = " or ".join(",".join(c) for c in choices) or "one channel of values"
    if only is not None and _is_alpha(only[0]):
        # coverage, not values: reading it as grey would turn a matte into a disparity map or an image
        raise InputError(f"{path}: holds only the alpha channel {only[0]!r} (coverage, not values); expected EXR "
                         f"channels {wanted}")
    if map_of is not None and chans:
        picked = (_exr_map_channel(path, chans, choices, map_of),)
    else:
        picked = next((c for c in choices if all(n in chans for n in c)), only)
    if picked is None:
        raise InputError(f"{path}: expected EXR channels {wanted}, got {','.join(sorted(chans))}")
    _check_exr_colour(path, chans, picked)
    for n in picked:
        if chans[n].dtype.kind != "f" or chans[n].shape != chans[picked[0]].shape:
            raise InputError(f"{path}: expected full-resolution HALF or FLOAT channels, got {n!r} {chans[n].dtype}")
    a = np.stack([chans[n] for n in picked], axis=-1).astype(np.float32)
    return a[..., 0] if a.shape[-1] == 1 else a


def _load_npy(path: Path, *, size_only: bool = False):
    with open(path, "rb") as fh:
        if fh.read(6) != b"\x93NUMPY":
            raise InputError(f"cannot read {path} as NPY: not a NPY file (bad magic string)")
        fh.seek(0)
        version = np.lib.format.read_magic(fh)
        if version == (1, 0):
            shape, _, dtype = np.lib.format.read_array_header_1_0(fh)
        elif version == (2, 0):
            shape, _, dtype = np.lib.format.read_array_header_2_0(fh)
        else:
            raise InputError(f"cannot read {path} as NPY: unsupported format version {version[0]}.{version[1]}")
        offset = fh.tell()
    # the header alone decides: shape, dtype and whether the file holds that many bytes (no mmap, no allocation)
    if len(shape) not in (2, 3):
        raise InputError(f"{path}: expected a 2-D (H x W) array, got {len(shape)}-D shape {shape}")
    if size_only:
        return int(shape[0]), int(shape[1])
    _check_dims(path, shape[0], shape[1])
    if dtype.kind not in "fiu" or dtype.hasobject:
        raise InputError(f"{path}: expected a float or integer array, got dtype {dtype}")
    need = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
    have = path.stat().st_size - offset
    if have < need:
        raise InputError(f"{path}: file is truncated: its header declares {shape} {dtype} ({need:,} bytes of data), "
                         f"but only {max(have, 0):,} bytes follow")
    return np.array(np.load(path, mmap_mode="r", allow_pickle=False))


def load_samples(path: Path, fmt: str, exr_channels: tuple[tuple[str, ...], ...], *,
                 with_bits: bool = False, map_of: str | None = None) -> np.ndarray | tuple[np.ndarray, int]:
    """Decode ``path`` to its stored samples: H x W or H x W x C, integer codes or floats. ``map_of`` (``"depth"``,
    ``"disparity"``): an EXR is a map, read from one channel (``exr_channels``: the ones preferred).

    With ``with_bits``, ``(samples, bits)``: their bit depth as the file declares it, the dtype's except for TIFFs
    of other depths, which decode into the next wider dtype (12-bit: uint16 codes up to 4095; 4-bit: uint8 up to
    15). Readers that scale codes need it; depth maps keep the codes as they are."""
    bits = None
    with _decoding(path, fmt):
        if fmt == "PNG":
            a = _load_png(path)
        elif fmt == "JPEG":
            a = decode_pil(path, "JPEG")
        elif fmt == "TIFF":
            a, bits = _load_tiff(path)
        elif fmt == "EXR":
            a = _load_exr(path, exr_channels, map_of)
        else:
            a = _load_npy(path)
    if fmt in ("PNG", "JPEG", "TIFF") and a.ndim in (2, 3):
        from .embedded import apply_orientation, embedded

        a = apply_orientation(a, embedded(path, fmt).orientation)  # EXIF orientation: the pixels as displayed
    if a.ndim not in (2, 3):
        raise InputError(f"{path}: expected an H x W or H x W x C image, got shape {a.shape}")
    _check_dims(path, a.shape[0], a.shape[1])
    if a.ndim == 3 and not 1 <= a.shape[2] <= 4:
        raise InputError(f"{path}: expected 1 to 4 channels, got {a.shape[2]}")
    if not with_bits:
        return a
    return a, a.dtype.itemsize * 8 if bits is None or a.dtype.kind != "u" else bits


def single_channel(path: Path, a: np.ndarray, fmt: str, what: str) -> np.ndarray:
    if a.ndim == 3 and a.shape[2] == 3 and fmt in ("PNG", "TIFF") and (a == a[..., :1]).all():
        return a[..., 0]
    if a.ndim == 3 and a.shape[2] == 1:
        return a[..., 0]
    if a.ndim == 3:
        differ = " (the channels differ)" if a.shape[2] == 3 else ""
        raise InputError(f"{path}: expected a single-channel {what} map, got {a.shape[2]} channels{differ}")
    return a


def decode_codes(a: np.ndarray, n_colour: int, bits: int | None = None) -> np.ndarray:
    """Linear float32 of integer codes ``a`` (H x W x C, uint8 or uint16): the first ``n_colour`` channels decoded
    from sRGB by table (:func:`~bokehray.colour.srgb_decode_lut`), the others (alpha) divided by the largest code,
    ``2**bits - 1`` (``bits``: the file's bit depth, by default the dtype's; a 12-bit TIFF's codes end at 4095).

    Band by band of rows (``_memory.row_bands``), straight into the result (``np.take`` into it): the same values
    as the whole-image ``lut[a]``, without its full-size index and value temporaries (at 12 MP, 288 MB of indices and
    a second 144 MB float32 copy); the bands on the CPU's cores (``_memory.on_cores``)."""
    bits = a.dtype.itemsize * 8 if bits is None else bits
    lut = srgb_decode_lut(bits)
    top = np.float32((1 << bits) - 1)
    out = np.empty(a.shape, np.float32)

    def band(y0: int, y1: int) -> None:
        src, dst = a[y0:y1], out[y0:y1]
        if n_colour == a.shape[2]:
            np.take(lut, src, out=dst)
        else:
            dst[..., :n_colour] = np.take(lut, src[..., :n_colour])
            dst[..., n_colour:] = src[..., n_colour:] / top

    on_cores(band, list(row_bands(*a.shape[:2])))
    return out


# --------------------------------------------------------------------------- public readers


def read_size(path: str | os.PathLike[str]) -> tuple[int, int]:
    """``(height, width)`` of an image, disparity or depth file, from its header alone (no pixel is decoded).

    Lets a caller compare the sizes of two files before spending seconds decoding a large
    one (the CLI does, for the image and its disparity map). Accepts every format a reader
    takes; a file whose header cannot be read raises :class:`InputError` naming it.
    """
    check_path(path)
    p, fmt = format_of(path, ("PNG", "JPEG", "TIFF", "EXR", "NPY"), "images or maps")
    with _decoding(p, fmt):
        if fmt == "PNG":
            w, h, _ = _png_header(p)
            hw = int(h), int(w)
        elif fmt == "JPEG":
            with Image.open(p, formats=["JPEG"]) as im:
                hw = int(im.height), int(im.width)
        elif fmt == "TIFF":
            hw = _load_tiff(p, size_only=True)
        elif fmt == "EXR":
            return _exr_size(p)
        else:
            return _load_npy(p, size_only=True)
        from .embedded import embedded

        # the size as read: EXIF orientations 5-8 turn the picture a quarter (read_image applies them)
        return hw[::-1] if embedded(p, fmt).orientation in (5, 6, 7, 8) else hw


def read_image(path: str | os.PathLike[str]) -> np.ndarray:
    """Read a colour image as scene-linear float32.

    PNG, JPEG and TIFF (8- or 16-bit integer; TIFF also 2 to 15 bits, scaled by its
    own largest code) are scaled to [0, 1] and decoded from sRGB; float TIFF and
    OpenEXR (HALF or FLOAT; channels ``R,G,B[,A]`` or ``Y[,A]``, but not luminance/chroma
    ``Y,RY,BY`` or CIE ``X,Y,Z``; the data window must be the display window) are linear already. Grey images are expanded to three
    channels.

    Args:
        path: A ``.png``, ``.jpg``/``.jpeg``, ``.tif``/``.tiff`` or ``.exr`` file.

    Returns:
        ``H x W x 3`` (RGB) or ``H x W x 4`` (RGBA) float32, row 0 at the top. Alpha
        is linear coverage (never sRGB-decoded) and the colour is NOT premultiplied.

    Raises:
        InputError: The file is missing, unreadable, truncated, too large, empty, has
            an unsupported extension or channel layout, or holds NaN/Inf.
    """
    check_path(path)
    p, fmt = format_of(path, ("PNG", "JPEG", "TIFF", "EXR"), "images")
    a, bits = load_samples(p, fmt, (("R", "G", "B", "A"), ("R", "G", "B"), ("Y", "A"), ("Y",)), with_bits=True)
    a = a[..., None] if a.ndim == 2 else a
    n_colour = 1 if a.shape[2] <= 2 else 3
    if a.dtype.kind == "f":
        out = to_float32(a, f"{p}: expected finite values, got", range_prefix(p))
        if fmt == "EXR" and a.shape[2] in (2, 4):  # OpenEXR colour is premultiplied
            alpha = out[..., -1:]
            with np.errstate(over="ignore", invalid="ignore"):
                np.divide(out[..., :-1], alpha, out=out[..., :-1], where=alpha != 0)
            # a tiny alpha (1e-22) under a large colour overflows float32 (tests/data/fuzz)
            check_finite(out, f"{p}: colour / alpha (OpenEXR stores premultiplied colour) overflows float32:")
    elif a.dtype in (np.uint8, np.uint16):
        from .embedded import embedded, to_srgb_codes

        meta = embedded(p, fmt)
        if not meta.is_srgb and bits != a.dtype.itemsize * 8:  # the profile's conversion takes 8- or 16-bit codes
            a = np.round(a * (np.iinfo(a.dtype).max / ((1 << bits) - 1))).astype(a.dtype)
            bits = a.dtype.itemsize * 8
        a = to_srgb_codes(a, meta, str(p))  # an embedded ICC profile (Display P3, Adobe RGB) -> sRGB
        out = decode_codes(a, n_colour, bits)
    else:
        raise InputError(f"{p}: expected 8- or 16-bit integer or float samples, got {a.dtype}")
    if n_colour == 1:
        out = out[..., [0, 0, 0, 1]] if out.shape[2] == 2 else np.repeat(out, 3, axis=2)
    return out


def read_disparity(path: str | os.PathLike[str], *, check_range: bool = False) -> np.ndarray:
    """Read a disparity map (1 = nearest, 0 = farthest) as float32 ``H x W``.

    PNG and integer TIFF codes are divided by their largest code (255, 65535; a TIFF of
    another bit depth by its own, 4095 for 12 bits) with
    no sRGB decoding; float TIFF and OpenEXR (its only channel, of any name, or several
    channels only if they are all equal) are taken as they are; ``.npy`` holds a 2-D (or ``H x W x 1``) float or
    integer array of the values themselves. A three-channel PNG/TIFF is accepted
    only if its channels are equal. Values are range-checked only with
    ``check_range=True`` (the renderer checks them anyway; the reader's message
    names the file).

    Raises:
        InputError: Unreadable file, wrong dimensionality or channel count, NaN/Inf,
            and with ``check_range`` values outside [0, 1].
    """
    check_path(path)
    p, fmt = format_of(path, ("PNG", "TIFF", "EXR", "NPY"), "disparity")
    a, bits = load_samples(p, fmt, (), with_bits=True, map_of="disparity")
    a = single_channel(p, a, fmt, "disparity")
    if a.dtype.kind == "u" and fmt != "NPY":  # uint8 / uint16 over a float32 is float32 already: no second copy
        return (a / np.float32((1 << bits) - 1)).astype(np.float32, copy=False)  # a 12-bit TIFF's white: 4095
    if a.dtype.kind == "i" and fmt != "NPY":
        raise InputError(f"{p}: expected unsigned integer or float samples, got {a.dtype}")
    out = to_float32(a, f"{p}: expected finite values, got", range_prefix(p))
    if check_range and out.size and (out.min() < 0.0 or out.max() > 1.0):
        bad = (out < 0.0) | (out > 1.0)
        y, x = first_index(bad)[:2]
        raise InputError(f"{p}: expected disparity in [0, 1] (1 = nearest), got {float(out[y, x]):.4g} at (y, x) = "
                         f"({y}, {x}) (range [{float(out.min()):.4g}, {float(out.max()):.4g}]); normalise it, or "
                         "give metric depth with --depth")
    return out
