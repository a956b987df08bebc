"""A matrix/TRC ICC profile built byte by byte (ICC.1:2001-04, version 2.1), so tests can embed real colour
profiles (Display P3, Adobe RGB) in the files they write without any profile file on the machine, and the
colour conversion they expect, from the primaries alone (NumPy, float64)."""

from __future__ import annotations

import struct

import numpy as np

D50 = np.array([0.9642, 1.0, 0.8249])
BRADFORD = np.array([[0.8951, 0.2664, -0.1614], [-0.7502, 1.7135, 0.0367], [0.0389, -0.0685, 1.0296]])
SRGB_PRIMARIES = ((0.64, 0.33), (0.30, 0.60), (0.15, 0.06))
P3_PRIMARIES = ((0.680, 0.320), (0.265, 0.690), (0.150, 0.060))
D65_XY = (0.3127, 0.3290)


def _xyz(xy: tuple[float, float]) -> np.ndarray:
    x, y = xy
    return np.array([x / y, 1.0, (1 - x - y) / y])


def rgb_to_xyz(primaries, white_xy=D65_XY) -> np.ndarray:
    """The 3 x 3 matrix from linear RGB to XYZ for these primaries and white (white maps to Y = 1)."""
    cols = np.stack([_xyz(p) for p in primaries], axis=1)
    scale = np.linalg.solve(cols, _xyz(white_xy))
    return cols * scale


def _adapt_to_d50(white_xy=D65_XY) -> np.ndarray:
    src = BRADFORD @ _xyz(white_xy)
    dst = BRADFORD @ D50
    return np.linalg.inv(BRADFORD) @ np.diag(dst / src) @ BRADFORD


def _s15(v: float) -> bytes:
    return struct.pack(">i", int(round(v * 65536)))


def _xyz_tag(v) -> bytes:
    return b"XYZ " + b"\0" * 4 + b"".join(_s15(c) for c in v)


def _srgb_trc() -> bytes:  # parametric curve type 3: the sRGB transfer function
    g, a, b, c, d = 2.4, 1 / 1.055, 0.055 / 1.055, 1 / 12.92, 0.04045
    return b"para" + b"\0" * 4 + struct.pack(">HH", 3, 0) + b"".join(_s15(v) for v in (g, a, b, c, d))


def _desc(text: str) -> bytes:
    ascii_ = text.encode("ascii") + b"\0"
    return (b"desc" + b"\0" * 4 + struct.pack(">I", len(ascii_)) + ascii_ + struct.pack(">II", 0, 0)
            + struct.pack(">HB", 0, 0) + b"\0" * 67)


def matrix_trc_profile(name: str, primaries=P3_PRIMARIES, white_xy=D65_XY) -> bytes:
    """An RGB display profile: the primaries (adapted to the D50 PCS with Bradford) and sRGB's curve per channel."""
    colorants = _adapt_to_d50(white_xy) @ rgb_to_xyz(primaries, white_xy)
    trc = _srgb_trc()
    tags = [(b"desc", _desc(name)), (b"wtpt", _xyz_tag(D50)), (b"rXYZ", _xyz_tag(colorants[:, 0])),
            (b"gXYZ", _xyz_tag(colorants[:, 1])), (b"bXYZ", _xyz_tag(colorants[:, 2])), (b"rTRC", trc),
            (b"gTRC", trc), (b"bTRC", trc), (b"cprt", b"text" + b"\0" * 4 + b"public domain\0")]
    offset = 128 + 4 + 12 * len(tags)
    table, data = [], b""
    for sig, body in tags:
        while (offset + len(data)) % 4:
            data += b"\0"
        table.append(sig + struct.pack(">II", offset + len(data), len(body)))
        data += body
    while len(data) % 4:
        data += b"\0"
    body = struct.pack(">I", len(tags)) + b"".join(table) + data
    size = 128 + len(body)
    header = (struct.pack(">I", size) + b"\0" * 4 + struct.pack(">I", 0x02100000) + b"mntrRGB XYZ " + b"\0" * 12
              + b"acsp" + b"\0" * 4 + b"\0" * 4 + b"\0" * 8 + b"\0" * 8 + b"\0" * 4 + b"".join(_s15(c) for c in D50)
              + b"\0" * 4 + b"\0" * 16 + b"\0" * 28)
    assert len(header) == 128
    return header + body


def srgb_decode(c: np.ndarray) -> np.ndarray:
    c = np.asarray(c, np.float64)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def p3_codes_to_linear_srgb(codes: np.ndarray) -> np.ndarray:
    """8-bit Display P3 codes -> linear sRGB (clipped to the sRGB gamut), the exact expectation."""
    lin_p3 = srgb_decode(np.asarray(codes, np.float64) / 255.0)
    m = np.linalg.inv(rgb_to_xyz(SRGB_PRIMARIES)) @ rgb_to_xyz(P3_PRIMARIES)
    return np.clip(lin_p3 @ m.T, 0.0, 1.0)
