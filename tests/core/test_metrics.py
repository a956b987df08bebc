"""Metrics of the benchmark against hand-computed values and against the dev set's own score.py."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from scripts import load_script

from bokehray.data.metrics import PerceptualMetric, discontinuity_band, exposure_align, psnr, score, ssim_map, to_srgb
from bokehray.errors import InputError

SCORE_PY = Path(__file__).resolve().parents[3] / "shared" / "data" / "pathtraced-dev" / "score.py"


def test_to_srgb_hand_values():
    x = np.array([-1.0, 0.0, 0.0031308, 0.5, 1.0, 7.0])
    want = [0.0, 0.0, 12.92 * 0.0031308, 1.055 * 0.5 ** (1 / 2.4) - 0.055, 1.0, 1.0]
    np.testing.assert_allclose(to_srgb(x), want, rtol=1e-12)
    assert to_srgb(x).dtype == np.float64


def test_psnr_hand_values():
    a = np.zeros((4, 5, 3))
    b = np.full((4, 5, 3), 0.1)
    assert psnr(a, b) == pytest.approx(20.0, abs=1e-12)  # MSE 0.01
    b2 = a.copy()
    b2[0, 0, 0] = 0.6  # one of 60 values off by 0.6: MSE 0.006
    assert psnr(a, b2) == pytest.approx(10 * math.log10(1 / 0.006), abs=1e-12)
    mask = np.zeros((4, 5), bool)
    mask[0, :2] = True  # 6 values, one off by 0.6: MSE 0.06
    assert psnr(a, b2, mask) == pytest.approx(10 * math.log10(1 / 0.06), abs=1e-12)
    assert psnr(a, a) == math.inf
    assert math.isnan(psnr(a, b, np.zeros((4, 5), bool)))
    with pytest.raises(InputError):
        psnr(a, b[:2])


def test_ssim_of_constant_images_is_the_luminance_term():
    # constant images: no variance, so SSIM = (2 mx my + C1) / (mx^2 + my^2 + C1), C1 = (0.01 * 1)^2
    a, b = np.full((16, 16, 3), 0.2), np.full((16, 16, 3), 0.4)
    want = (2 * 0.2 * 0.4 + 1e-4) / (0.2**2 + 0.4**2 + 1e-4)
    np.testing.assert_allclose(ssim_map(a, b), want, rtol=1e-9)
    rng = np.random.default_rng(0)
    x = rng.random((20, 20, 3))
    np.testing.assert_allclose(ssim_map(x, x), 1.0)


def test_band_hand_values():
    d = np.full((30, 40), 0.5, np.float32)
    d[:, 20:] = 0.6  # 20 % jump between columns 19 and 20
    band = discontinuity_band(d, 8)
    cols = np.flatnonzero(band[0])
    assert cols.min() == 11 and cols.max() == 28 and band.all(axis=0)[11:29].all()
    d2 = np.full((30, 40), 0.5, np.float32)
    d2[:, 20:] = 0.51  # 2 %: a slope, not a discontinuity
    assert not discontinuity_band(d2, 8).any()
    d3 = np.zeros((30, 40), np.float32)
    d3[:, 20:] = 0.1  # infinitely far next to anything is an edge
    assert discontinuity_band(d3, 2)[0, 17:23].all() and not discontinuity_band(d3, 2)[0, :17].any()


@pytest.mark.skipif(not SCORE_PY.is_file(), reason="path-traced dev set not present")
def test_band_equals_the_dev_set_scoring_script():
    mod = load_script(SCORE_PY, "devset_score")
    rng = np.random.default_rng(3)
    d = rng.choice([0.15, 0.3, 0.31, 0.8], size=(8, 10)).repeat(6, 0).repeat(6, 1).astype(np.float32)
    d += np.linspace(0, 0.01, d.shape[1], dtype=np.float32)  # a slight slope everywhere
    np.testing.assert_array_equal(discontinuity_band(d, 8), mod.discontinuity_band(1.0 / d.astype(np.float64), 8))
    a, b = rng.random((48, 60, 3)).astype(np.float32), rng.random((48, 60, 3)).astype(np.float32)
    band = discontinuity_band(d)
    s = score(a, b, band)
    ga, gb = mod.to_srgb(b), mod.to_srgb(a)
    assert s["psnr"] == mod.psnr(ga, gb) and s["band_psnr"] == mod.psnr(ga, gb, band)


def test_score_identical_and_keys():
    rng = np.random.default_rng(1)
    x = rng.random((24, 24, 3)).astype(np.float32) * 2  # values above 1 are clipped before scoring
    s = score(x, x, np.ones((24, 24), bool))
    assert s["psnr"] == math.inf and s["ssim"] == pytest.approx(1.0) and s["band_ssim"] == pytest.approx(1.0)
    s = score(x, np.clip(x, 0, 1))  # clipping makes these equal in sRGB
    assert s["psnr"] == math.inf and math.isnan(s["band_psnr"])


def test_exposure_align_is_one_global_gain():
    rng = np.random.default_rng(2)
    tgt = rng.random((10, 12, 3)).astype(np.float32)
    img = tgt * np.float32(0.4)
    aligned, gain = exposure_align(img, tgt)
    assert gain == pytest.approx(2.5, rel=1e-6)
    np.testing.assert_allclose(aligned, tgt, rtol=1e-5)
    black, g = exposure_align(np.zeros_like(tgt), tgt)
    assert g == 1.0 and not black.any()


@pytest.mark.filterwarnings("ignore::DeprecationWarning")  # torch.jit is deprecated upstream, still works
def test_perceptual_metric_needs_a_local_file(tmp_path):
    with pytest.raises(InputError, match="does not exist"):
        PerceptualMetric("lpips", str(tmp_path / "missing.pt"))
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a model")
    pytest.importorskip("torch")
    with pytest.raises(InputError, match="cannot load"):
        PerceptualMetric("lpips", str(bad))


@pytest.mark.filterwarnings("ignore::DeprecationWarning")
def test_perceptual_metric_runs_a_torchscript_model(tmp_path):
    torch = pytest.importorskip("torch")

    class MeanAbs(torch.nn.Module):
        def forward(self, x, y):
            return (x - y).abs().mean()

    path = tmp_path / "l1.pt"
    torch.jit.script(MeanAbs()).save(str(path))
    m = PerceptualMetric("lpips", str(path))
    a = np.zeros((8, 8, 3), np.float32)
    b = np.ones((8, 8, 3), np.float32)
    assert m(a, b) == pytest.approx(2.0)  # [-1, 1] range: black vs white is 2 apart
    assert m(a, a) == 0.0
