"""Writing images and disparity maps, atomically, the format chosen by the extension.

Display-referred formats (PNG, JPEG, integer TIFF) are encoded to sRGB and tagged with an sRGB ICC profile;
OpenEXR and float TIFF stay linear (EXR colour is premultiplied, as the format requires).
"""

from __future__ import annotations

import io
import os
import struct
from collections.abc import Callable, Mapping
from numbers import Integral
from pathlib import Path

import imagecodecs
import numpy as np
import numpy.typing as npt
import OpenEXR
import tifffile
from PIL import Image

from ..colour import SRGB_CHROMATICITIES, quantize, srgb_icc
from ..errors import InputError
from ..formats import HALF_MAX, check_finite, first_index, format_of, to_float32
from ..validate import array_shape, check_bool, check_path, fits_in_memory, shown
from .atomic import atomic_write

__all__ = ["API_NAMES", "CLI_NAMES", "PNG_COMPRESS_LEVEL", "WRITE_BYTES_PER_SAMPLE", "check_output_path",
           "write_disparity", "write_image"]

PNG_COMPRESS_LEVEL = 3
"""zlib level of 8-bit PNG outputs: lossless at any level; a low one writes much faster for slightly larger files
(docs/robustness.md, "Write speed")."""


WRITE_BYTES_PER_SAMPLE = 48
"""Peak bytes per sample of :func:`write_image` beyond its input (42 measured with tracemalloc for PNG, JPEG and
16-bit TIFF: the float32 copy, the finiteness masks, the sRGB encoding's temporaries and the codes; EXR needs a
quarter of it), with a margin."""


def _write_exr(tmp: str, img: np.ndarray, *, half: bool) -> None:
    dtype = np.float16 if half else np.float32
    names = "Y" if img.shape[2] == 1 else "RGBA"[: img.shape[2]]
    chans = {n: np.ascontiguousarray(img[..., i], dtype=dtype) for i, n in enumerate(names)}
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage,
              "chromaticities": SRGB_CHROMATICITIES}  # linear Rec. 709 / sRGB primaries, D65
    with OpenEXR.File(header, chans) as f:
        f.write(tmp)


def _write_tiff(tmp: str, img: np.ndarray, icc: bytes | None = None) -> None:
    photometric = "minisblack" if img.shape[2] == 1 else "rgb"
    extra = {"iccprofile": icc} if icc is not None and img.shape[2] >= 3 else {}
    tifffile.imwrite(tmp, img[..., 0] if img.shape[2] == 1 else img, photometric=photometric, compression="zlib",
                     **extra)


def encode_pil(tmp: str, codes: np.ndarray, fmt: str, **options: object) -> None:
    # Encoded in memory, then written by Python: Pillow (13.0) saving a JPEG straight to a full disk stops at
    # the first short write and reports success, leaving a truncated file.
    options = {k: v for k, v in options.items() if v is not None}
    buf = io.BytesIO()
    Image.fromarray(codes[..., 0] if codes.shape[2] == 1 else codes).save(buf, format=fmt, **options)
    write_bytes(tmp, buf.getbuffer())


def _png_with_icc(data: bytes, icc: bytes) -> bytes:
    """``data`` (a PNG) with an iCCP chunk holding ``icc`` right after IHDR (the 16-bit encoder writes none)."""
    import zlib

    body = b"sRGB\x00\x00" + zlib.compress(icc)  # profile name, NUL, compression method 0, zlib stream
    chunk = struct.pack(">I", len(body)) + b"iCCP" + body + struct.pack(">I", zlib.crc32(b"iCCP" + body))
    end_ihdr = 8 + 8 + 13 + 4  # signature, IHDR length + type, IHDR data, CRC
    return data[:end_ihdr] + chunk + data[end_ihdr:]


def write_bytes(tmp: str, data: bytes | memoryview) -> None:
    with open(tmp, "wb") as fh:
        fh.write(data)


def srgb_codes(img: np.ndarray, bits: int) -> np.ndarray:
    """sRGB-encode the colour channels (not alpha) and round to ``bits``-bit codes (``bokehray.colour.quantize``:
    8-bit codes through an exact table, band by band)."""
    return quantize(img, bits)


API_NAMES = {"bit_depth": "bit_depth", "half": "half=True"}
"""How :func:`check_output_path`'s refusals name the options by default (the API's keywords)."""
CLI_NAMES = {"bit_depth": "--bit-depth", "half": "--half"}
"""... and on the command line."""


def check_output_path(path: str | os.PathLike[str], *, bit_depth: int | None = None, half: bool = False,
                      names: Mapping[str, str] = API_NAMES) -> Path:
    """Validate an output path and its options before rendering (so a long render cannot fail at the end).

    Checks the extension, the bit depth for that format, and that the target is
    not a directory. Raises :class:`InputError` naming the options as ``names`` says (:data:`API_NAMES`,
    :data:`CLI_NAMES`); returns the path.
    """
    check_path(path)
    p, fmt = format_of(path, ("PNG", "JPEG", "TIFF", "EXR"), "images", read=False)
    _output_bits(p, fmt, bit_depth, half, names)
    parent = p.resolve().parent
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir() or not os.access(parent, os.W_OK):
        raise InputError(f"{p}: cannot write there ({parent} is not a writable folder)")
    return p


def _check_write_options(p: Path, bit_depth: object, half: object, quality: object, exclusive: object) -> int:
    """The types of :func:`write_image`'s options (``half="yes"`` was taken as True, ``quality="95"`` a TypeError)
    and the JPEG quality's range (checked for every format: it is an argument all the same)."""
    check_bool(half, "half")
    check_bool(exclusive, "exclusive")
    if isinstance(quality, bool) or not isinstance(quality, Integral) or not 1 <= quality <= 100:
        raise InputError(f"{p}: expected JPEG quality in [1, 100] (an integer), got {shown(quality)}"[:300])
    return int(quality)  # Pillow refuses NumPy's integers


def _output_bits(p: Path, fmt: str, bit_depth: int | None, half: bool, names: Mapping[str, str] = API_NAMES) -> int:
    if bit_depth is not None and (isinstance(bit_depth, bool) or not isinstance(bit_depth, Integral)):
        raise InputError(f"{p}: {names['bit_depth']} expects None or an integer, got {shown(bit_depth)}"[:300])
    depths = {"PNG": (8, 16), "JPEG": (8,), "TIFF": (8, 16, 32), "EXR": (16, 32)}[fmt]
    bits = bit_depth if bit_depth is not None else {"PNG": 8, "JPEG": 8, "TIFF": 16, "EXR": 16 if half else 32}[fmt]
    bd, hf = names["bit_depth"], names["half"]
    if half and fmt != "EXR":
        raise InputError(f"{p}: {hf} writes half floats, which only EXR stores, and this is a {fmt} file "
                         f"(name it .exr, or leave {hf} out)")
    if bits not in depths:
        raise InputError(f"{p}: {fmt} takes {bd} {' or '.join(map(str, depths))}, not {bit_depth!r}")
    if half and bits != 16:
        raise InputError(f"{p}: {hf} writes 16-bit half floats, and {bd} {bit_depth} asks for 32-bit ones "
                         f"(leave one of them out)")
    return bits


def write_image(
    path: str | os.PathLike[str],
    image: npt.ArrayLike,
    *,
    bit_depth: int | None = None,
    half: bool = False,
    quality: int = 95,
    exif: bytes | None = None,
    exclusive: bool = False,
    next_name: Callable[[Path], Path | None] | None = None,
) -> Path:
    """Write a linear float image atomically, choosing the format from the extension.

    ``.png``: 8 (default) or 16-bit sRGB. ``.jpg``/``.jpeg``: 8-bit sRGB at ``quality``,
    no alpha. ``.tif``/``.tiff``: 16-bit (default) or 8-bit sRGB, or ``bit_depth=32``
    for linear float32. ``.exr``: linear float32 (default) or HALF (``half=True`` or
    ``bit_depth=16``), ZIP-compressed, channels ``R,G,B[,A]`` or ``Y``. Integer
    formats clip to [0, 1]; alpha is written linearly and colour is taken as not
    premultiplied (it is premultiplied for EXR, as that format requires).

    Args:
        path: Target file; missing parent directories are created.
        image: ``H x W``, ``H x W x 1``, ``H x W x 3`` or ``H x W x 4`` linear floats.
        bit_depth: Bits per sample, or None for the format's default.
        half: Write OpenEXR HALF channels.
        quality: JPEG quality, 1 to 100.
        exif: an EXIF block to embed in a JPEG (``bokehray.photo.embedded.exif_for_output`` keeps the input's, with the
            orientation reset), or None.
        exclusive: never replace a file at ``path``, even one made while this wrote
            (``OutputExistsError``; see :func:`~bokehray.output.atomic.atomic_write`).
        next_name: with ``exclusive``, where the name is taken: ``next_name(taken)`` is another name in the same
            folder to publish the same encoded file under, or None to give up (the image is encoded once).

    Display-referred outputs are tagged sRGB: an sRGB ICC profile in PNG, JPEG and integer TIFF; EXR files carry
    the sRGB / Rec. 709 primaries as their ``chromaticities`` attribute.

    Returns:
        The path written.

    Raises:
        InputError: Bad extension, shape, dtype, bit depth, NaN/Inf or out-of-range values.
    """
    check_path(path)
    p, fmt = format_of(path, ("PNG", "JPEG", "TIFF", "EXR"), "images", read=False)
    quality = _check_write_options(p, bit_depth, half, quality, exclusive)
    shape = array_shape(image, f"refusing to write {p}: image")
    channels = shape[2] if len(shape) == 3 and isinstance(shape[2], int) else 1
    fits_in_memory(shape, WRITE_BYTES_PER_SAMPLE * channels, f"refusing to write {p}")  # before any copy
    img = np.asarray(image)
    img = img[..., None] if img.ndim == 2 else img
    if img.ndim != 3 or img.shape[2] not in (1, 3, 4) or img.size == 0:
        raise InputError(f"{p}: expected an H x W, H x W x 3 or H x W x 4 image, got shape {np.shape(image)}")
    if img.dtype.kind != "f":
        raise InputError(f"{p}: expected a floating-point linear image, got dtype {img.dtype}")
    img = to_float32(img, f"refusing to write {p}: image contains",
                      f"refusing to write {p}: image holds a value beyond float32's range (+-3.4e38):")
    bits = _output_bits(p, fmt, bit_depth, half)
    if fmt == "EXR":
        if img.shape[2] == 4:
            with np.errstate(over="ignore"):
                img = np.concatenate([img[..., :3] * img[..., 3:], img[..., 3:]], axis=2)
            check_finite(img, f"refusing to write {p}: colour x alpha (OpenEXR stores premultiplied colour) "
                          "overflows float32:")
        big = np.abs(img) > HALF_MAX
        if bits == 16 and big.any():
            y, x = first_index(big)[:2]
            raise InputError(f"refusing to write {p}: value beyond the HALF range (+-65504) at (y, x) = ({y}, {x})")
        return atomic_write(p, lambda tmp: _write_exr(tmp, img, half=bits == 16), exclusive, next_name)
    if fmt == "TIFF":
        data = img if bits == 32 else srgb_codes(img, bits)
        icc = None if bits == 32 else srgb_icc()
        return atomic_write(p, lambda tmp: _write_tiff(tmp, data, icc), exclusive, next_name)
    if fmt == "JPEG" and img.shape[2] == 4:
        raise InputError(f"{p}: expected an image without alpha for JPEG, got 4 channels")
    codes = srgb_codes(img, bits)
    icc = srgb_icc() if img.shape[2] >= 3 else None
    if fmt == "JPEG":
        return atomic_write(p, lambda tmp: encode_pil(tmp, codes, "JPEG", quality=quality, icc_profile=icc, exif=exif), exclusive, next_name)
    if bits == 16:
        data = imagecodecs.png_encode(codes)
        return atomic_write(p, lambda tmp: write_bytes(tmp, _png_with_icc(data, icc) if icc else data), exclusive, next_name)
    return atomic_write(p, lambda tmp: encode_pil(tmp, codes, "PNG", icc_profile=icc, compress_level=PNG_COMPRESS_LEVEL), exclusive, next_name)


def write_disparity(path: str | os.PathLike[str], d: npt.ArrayLike) -> Path:
    """Write a disparity map atomically.

    ``.exr``: float32 channel ``Y``; ``.png``: 16-bit grey ``round(d * 65535)``, which
    needs ``d`` within [0, 1]; ``.npy``: float32 array; ``.tif``/``.tiff``: float32.

    Args:
        path: Target file; missing parent directories are created.
        d: ``H x W`` (or ``H x W x 1``) disparity values.

    Returns:
        The path written.

    Raises:
        InputError: Bad extension, shape, NaN/Inf, or values outside [0, 1] for PNG.
    """
    check_path(path)
    p, fmt = format_of(path, ("PNG", "TIFF", "EXR", "NPY"), "disparity", read=False)
    fits_in_memory(np.shape(d), WRITE_BYTES_PER_SAMPLE, f"refusing to write {p}")  # before any copy
    a = np.asarray(d)
    a = a[..., 0] if a.ndim == 3 and a.shape[2] == 1 else a
    if a.ndim != 2 or a.size == 0 or a.dtype.kind not in "fiu":
        raise InputError(f"{p}: expected a non-empty H x W real disparity array, got shape {a.shape} dtype {a.dtype}")
    a = to_float32(a, f"refusing to write {p}: disparity contains",
                    f"refusing to write {p}: disparity holds a value beyond float32's range (+-3.4e38):")
    if fmt == "PNG":
        lo, hi = float(a.min()), float(a.max())
        if lo < 0.0 or hi > 1.0:
            raise InputError(f"{p}: expected disparity within [0, 1] for 16-bit PNG, got [{lo:g}, {hi:g}]")
        codes = np.round(a[..., None].astype(np.float64) * 65535).astype(np.uint16)
        return atomic_write(p, lambda tmp: write_bytes(tmp, imagecodecs.png_encode(codes)))
    if fmt == "EXR":
        return atomic_write(p, lambda tmp: _write_exr(tmp, a[..., None], half=False))
    if fmt == "TIFF":
        return atomic_write(p, lambda tmp: _write_tiff(tmp, a[..., None]))

    def save_npy(tmp: str) -> None:
        with open(tmp, "wb") as fh:
            np.save(fh, a)

    return atomic_write(p, save_npy)
