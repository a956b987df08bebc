"""sRGB (IEC 61966-2-1): the transfer functions between display codes and scene-linear light, and the tags that
say so in an output (its primaries for EXR, an ICC profile for PNG, JPEG and TIFF)."""

from __future__ import annotations

import struct
from functools import cache

import numpy as np
import numpy.typing as npt

from ._memory import on_cores

__all__ = ["SRGB_CHROMATICITIES", "SRGB_KNEE", "linear_to_srgb", "quantize", "srgb_decode_lut", "srgb_icc",
           "srgb_to_linear"]

SRGB_CHROMATICITIES = (0.64, 0.33, 0.30, 0.60, 0.15, 0.06, 0.3127, 0.3290)
"""Red, green, blue and white (x, y) of sRGB / Rec. 709 primaries with D65: the chromaticities written to EXR."""

SRGB_KNEE = 12.92 * 0.0031308
"""Encoded value of the linear knee 0.0031308 (0.04044994): where the decoding switches segments, as
colour-science has it (the standard's 0.04045 differs by 6e-8 and both segments agree there to 1e-9)."""

def srgb_to_linear(x: npt.ArrayLike) -> np.ndarray:
    """Decode sRGB-encoded values in [0, 1] to linear light (IEC 61966-2-1), as float32.

    The piecewise curve ``x / 12.92`` up to the image of 0.0031308 under the encoding (0.04044994),
    ``((x + 0.055) / 1.055) ** 2.4`` above, evaluated in float64
    and rounded once to float32: the same numbers as colour-science's ``eotf_sRGB`` (tested), without its
    slow import. Values below 0 follow the linear segment; NaN stays NaN.
    """
    v = np.asarray(x, dtype=np.float32).astype(np.float64)
    with np.errstate(invalid="ignore"):
        out = np.where(v <= SRGB_KNEE, v / 12.92, ((np.maximum(v, SRGB_KNEE) + 0.055) / 1.055) ** 2.4)
    return out.astype(np.float32)


def linear_to_srgb(x: npt.ArrayLike) -> np.ndarray:
    """Encode linear-light values with the sRGB transfer function (IEC 61966-2-1), as float32.

    ``12.92 x`` below 0.0031308, ``1.055 x ** (1 / 2.4) - 0.055`` above, in float64 rounded once to float32 (the
    same numbers as colour-science's ``eotf_inverse_sRGB``, tested).
    """
    v = np.asarray(x, dtype=np.float32).astype(np.float64)
    with np.errstate(invalid="ignore"):
        out = np.where(v <= 0.0031308, v * 12.92, 1.055 * np.maximum(v, 0.0031308) ** (1 / 2.4) - 0.055)
    return out.astype(np.float32)



@cache
def srgb_decode_lut(bits: int) -> np.ndarray:
    """Linear light of every ``bits``-bit sRGB code (read-only float32, ``2**bits`` entries)."""
    lut = srgb_to_linear(np.arange(2**bits, dtype=np.float64) / (2**bits - 1))
    lut.flags.writeable = False
    return lut


def _codes_plain(x: np.ndarray, bits: int, srgb: bool) -> np.ndarray:
    """The plain formula: ``round(float32(clip(float32(enc(x)), 0, 1)) * (2^bits - 1))`` with ``enc`` the sRGB
    curve (:func:`linear_to_srgb`) or the identity (alpha), as uint8 / uint16."""
    enc = linear_to_srgb(x) if srgb else np.asarray(x, np.float32)
    return np.round(np.clip(enc, 0.0, 1.0) * (2**bits - 1)).astype(np.uint8 if bits == 8 else np.uint16)


_BUCKET_SHIFT = 15
"""The 8-bit table is indexed by a float32's top 17 bits (sign, exponent, 8 mantissa bits): 32,513 buckets in
[0, 1], each of relative width <= 1/256, narrower than any gap between two of the 255 code thresholds."""


@cache
def _u8_table(srgb: bool) -> tuple[np.ndarray, np.ndarray]:
    """(code at each bucket's start, the threshold of the next code above it) for :func:`quantize` at 8 bits.

    ``code(x)`` of :func:`_codes_plain` is monotone in float32 ``x``, so code ``c`` starts at the smallest float32
    ``t_c`` with ``code(t_c) >= c``: found for all 255 codes at once by bisection over the float32 bit patterns of
    [0, 1] (ordered as integers). Each bucket holds at most one threshold (checked), so ``code(x) = base[b] +
    (x >= next[b])`` for ``x`` in bucket ``b``: the plain formula's codes, bit for bit."""
    one = int(np.float32(1.0).view(np.uint32))
    lo = np.zeros(255, np.int64)  # code(bits lo) < c  (code(0) = 0)
    hi = np.full(255, one, np.int64)  # code(bits hi) >= c (code(1) = 255)
    want = np.arange(1, 256)
    while np.any(hi - lo > 1):
        mid = (lo + hi) // 2
        ok = _codes_plain(mid.astype(np.uint32).view(np.float32), 8, srgb).astype(np.int64) >= want
        hi, lo = np.where(ok, mid, hi), np.where(ok, lo, mid)
    thresholds = hi.astype(np.uint32).view(np.float32)  # t_1 .. t_255, non-decreasing
    starts = (np.arange((one >> _BUCKET_SHIFT) + 1, dtype=np.uint32) << _BUCKET_SHIFT).view(np.float32)
    base = np.searchsorted(thresholds, starts, side="right").astype(np.uint8)
    nxt = np.append(thresholds, np.float32(np.inf))[base]
    ends = ((np.arange((one >> _BUCKET_SHIFT) + 1, dtype=np.uint32) + 1) << _BUCKET_SHIFT).view(np.float32)
    after = np.append(thresholds, [np.float32(np.inf)] * 2)[base.astype(np.int64) + 1]
    if not np.all(after >= ends):  # a bucket with two thresholds: the table would be wrong
        raise AssertionError("colour._u8_table: a bucket holds two code thresholds")
    for a in (base, nxt):
        a.flags.writeable = False
    return base, nxt


def quantize(img: np.ndarray, bits: int, *, rows: int = 256) -> np.ndarray:
    """sRGB-encode the colour channels (the first three; a fourth, alpha, stays linear) of a float32 H x W x C
    image and round to ``bits``-bit codes: ``round(clip(linear_to_srgb(x), 0, 1) * (2^bits - 1))``, the same codes
    as that formula (8 bits through an exact table, :func:`_u8_table`; 16 bits through the formula itself), a band
    of ``rows`` rows at a time so that no full-frame float64 temporary exists, the bands on the CPU's cores."""
    img = np.asarray(img, np.float32)
    h, w, c = img.shape
    out = np.empty((h, w, c), np.uint8 if bits == 8 else np.uint16)
    n_colour = min(c, 3)

    def band_rows(y: int, y1: int) -> None:
        band = img[y:y1]
        for ch0, ch1, srgb in ((0, n_colour, True), (n_colour, c, False)):
            if ch1 <= ch0:
                continue
            part = band[..., ch0:ch1]
            if bits != 8:
                out[y:y1, :, ch0:ch1] = _codes_plain(part, bits, srgb)
                continue
            base, nxt = _u8_table(srgb)
            x = np.clip(part, 0.0, 1.0)
            x += np.float32(0.0)  # -0.0 -> +0.0 (its bit pattern would index past the table)
            b = x.view(np.uint32) >> _BUCKET_SHIFT
            out[y:y1, :, ch0:ch1] = base[b] + (x >= nxt[b])

    if bits == 8:  # the cached tables made once, before the bands' threads
        _u8_table(True)
        _u8_table(False)
    on_cores(band_rows, [(y, min(h, y + rows)) for y in range(0, h, rows)])  # NumPy's loops release the GIL
    return out


@cache
def srgb_icc() -> bytes:
    """An sRGB ICC profile (littleCMS's built-in one) to tag PNG, JPEG and TIFF outputs with."""
    from PIL import ImageCms

    icc = bytearray(ImageCms.ImageCmsProfile(ImageCms.createProfile("sRGB")).tobytes())
    # littleCMS stamps the profile with the time it was made (header bytes 24-35) and the MD5 of the result
    # (84-99): a fixed date and no ID (zeros: "not computed", ICC.1 7.2.18) keep outputs byte-reproducible
    icc[24:36] = struct.pack(">6H", 2026, 1, 1, 0, 0, 0)
    icc[84:100] = bytes(16)
    return bytes(icc)
