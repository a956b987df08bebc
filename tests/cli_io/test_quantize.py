"""The writers' sRGB quantization (``bokehray.colour.quantize``) against the plain formula it replaces."""

import numpy as np
import pytest

from bokehray import colour


def plain(img: np.ndarray, bits: int) -> np.ndarray:
    """The formula the writers used: sRGB-encode colour (not alpha), clip, scale, round."""
    enc = img.copy()
    enc[..., : min(img.shape[2], 3)] = colour.linear_to_srgb(img[..., :3])
    return np.round(np.clip(enc, 0.0, 1.0) * (2**bits - 1)).astype(np.uint8 if bits == 8 else np.uint16)


@pytest.mark.parametrize("srgb", [True, False])
def test_u8_table_equals_formula_on_dense_float32(srgb):
    # every 64th float32 bit pattern in [0, 1] (16.6 million values; each code's threshold is hit exactly below)
    one = int(np.float32(1.0).view(np.uint32))
    x = np.arange(0, one + 1, 64, dtype=np.uint32).view(np.float32)
    base, nxt = colour._u8_table(srgb)
    b = x.view(np.uint32) >> colour._BUCKET_SHIFT
    np.testing.assert_array_equal(base[b] + (x >= nxt[b]), colour._codes_plain(x, 8, srgb))


@pytest.mark.parametrize("srgb", [True, False])
def test_u8_table_at_every_threshold(srgb):
    # the float32 values either side of each code change: the table's codes there are the formula's
    base, nxt = colour._u8_table(srgb)
    t = np.unique(nxt[np.isfinite(nxt)])
    assert len(t) == 255
    x = np.concatenate([t, np.nextafter(t, np.float32(0)), np.nextafter(t, np.float32(2))]).astype(np.float32)
    x = np.clip(x, 0, 1)
    b = x.view(np.uint32) >> colour._BUCKET_SHIFT
    np.testing.assert_array_equal(base[b] + (x >= nxt[b]), colour._codes_plain(x, 8, srgb))


@pytest.mark.parametrize("channels", [1, 3, 4])
@pytest.mark.parametrize("bits", [8, 16])
def test_quantize_equals_formula(channels, bits):
    rng = np.random.default_rng(channels + bits)
    img = rng.random((300, 257, channels), dtype=np.float32) * 1.4 - 0.2
    img[0, :6, 0] = [-0.0, 0.0, 1.0, np.nextafter(np.float32(1), np.float32(2)), -1e-30, 3e38]
    img[1] = rng.random((257, channels), dtype=np.float32) * 1e-3  # the linear segment
    np.testing.assert_array_equal(colour.quantize(img, bits, rows=7), plain(img, bits))
