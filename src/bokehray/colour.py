"""sRGB (IEC 61966-2-1): the transfer functions between display codes and scene-linear light, and the tags that
say so in an output (its primaries for EXR, an ICC profile for PNG, JPEG and TIFF)."""

from __future__ import annotations

import struct
from functools import cache

import numpy as np
import numpy.typing as npt

__all__ = ["SRGB_CHROMATICITIES", "SRGB_KNEE", "linear_to_srgb", "srgb_decode_lut", "srgb_icc", "srgb_to_linear"]

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
