"""Grain kept (bokehray.photo.grain): the photo's noise measured in its flat areas, restored where the blur removed
it, seeded; on by default for display-referred photos, off for EXR and with --no-grain."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

import bokehray as br
from bokehray.app.cli import main
from bokehray.colour import linear_to_srgb, srgb_to_linear
from bokehray.photo import grain as gr


def _hp_codes(codes: np.ndarray) -> float:
    import cv2

    luma = codes.astype(np.float32) @ np.array([0.2126, 0.7152, 0.0722], np.float32)
    return float((luma - cv2.GaussianBlur(luma, (0, 0), 2.0)).std())


def _grainy(shape=(192, 256), noise=1.5, seed=1) -> tuple[np.ndarray, np.ndarray]:
    """A smooth gradient with Gaussian grain of ``noise`` codes per channel: (8-bit codes, linear image)."""
    h, w = shape
    base = np.linspace(60, 190, w, dtype=np.float32)[None, :, None] * np.array([1.0, 0.9, 0.8], np.float32)
    codes = np.clip(np.round(base + np.random.default_rng(seed).normal(0, noise, (h, w, 3))), 0, 255)
    return codes.astype(np.uint8), srgb_to_linear(codes / 255.0).astype(np.float32)


def test_the_grain_measured_is_the_photos_highpass():
    codes, img = _grainy()
    g = gr.measure_grain(img)
    assert g.codes == pytest.approx(_hp_codes(codes), rel=0.1)
    assert all(c * 255 == pytest.approx(1.5 * 0.93, rel=0.15) for c in g.channels)  # the high-pass keeps ~93 %


def test_a_clean_photo_has_no_grain_and_is_left_alone():
    img = np.full((128, 128, 3), 0.3, np.float32)
    g = gr.measure_grain(img)
    assert g.luma == 0.0
    out = gr.restore_grain(img.copy(), g, np.ones((128, 128), np.float32))
    assert np.array_equal(out, img)


def test_restored_grain_matches_the_photo_where_the_blur_removed_it():
    codes, img = _grainy()
    g = gr.measure_grain(img)
    flat = np.full_like(img, float(img.mean()))  # what a wide blur leaves: no grain at all
    coc = np.full(img.shape[:2], 30.0, np.float32)
    out = gr.restore_grain(flat.copy(), g, gr.removed_share(coc), dither_bits=8)
    back = np.round(linear_to_srgb(np.clip(out, 0, 1)) * 255)
    assert _hp_codes(back) == pytest.approx(_hp_codes(codes), rel=0.2)


def test_sharp_pixels_are_not_touched_and_the_grain_is_seeded():
    _, img = _grainy()
    g = gr.measure_grain(img)
    coc = np.zeros(img.shape[:2], np.float32)
    coc[:, 128:] = 20.0  # the right half blurred
    removed = gr.removed_share(coc)
    a = gr.restore_grain(img.copy(), g, removed, seed=0)
    b = gr.restore_grain(img.copy(), g, removed, seed=0)
    c = gr.restore_grain(img.copy(), g, removed, seed=1)
    assert np.array_equal(a[:, :128], img[:, :128])
    assert np.array_equal(a, b) and not np.array_equal(a[:, 128:], c[:, 128:])
    assert (a >= 0).all() and np.isfinite(a).all()


def test_alpha_is_not_touched():
    _, img = _grainy()
    rgba = np.concatenate([img, np.full(img.shape[:2] + (1,), 0.5, np.float32)], axis=2)
    out = gr.restore_grain(rgba.copy(), gr.measure_grain(img), np.ones(img.shape[:2], np.float32))
    assert np.array_equal(out[..., 3], rgba[..., 3])


@given(st.floats(0.0, 500.0, allow_nan=False), st.floats(0.0, 500.0, allow_nan=False))
def test_removed_share_is_none_when_sharp_and_grows_with_the_blur(r1, r2):
    lo, hi = sorted((r1, r2))
    s = gr.removed_share(np.array([lo, hi], np.float32))
    assert 0.0 <= s[0] <= s[1] <= 1.0
    if hi <= 1 / math.sqrt(math.pi):  # a disc this small keeps all the noise (one pixel)
        assert s[1] == 0.0


def test_an_8_bit_output_is_dithered_where_a_clean_photo_is_blurred():
    img = np.full((64, 64, 3), 0.3, np.float32)
    g = gr.measure_grain(img)
    removed = np.zeros((64, 64), np.float32)
    removed[:, 32:] = 1.0
    out = gr.restore_grain(img.copy(), g, removed, dither_bits=8)
    assert np.array_equal(out[:, :32], img[:, :32])
    codes = linear_to_srgb(out[:, 32:]) * 255 - linear_to_srgb(img[:, 32:]) * 255
    assert 0.2 < codes.std() < 0.6 and np.abs(codes).max() <= 1.0 + 1e-3  # a triangular dither of one code


def test_render_restores_grain_for_png_only_and_reproducibly(tmp_path, capsys):
    codes, img = _grainy()
    from PIL import Image

    Image.fromarray(codes).save(tmp_path / "p.png")
    br.write_image(tmp_path / "p.exr", img)
    d = np.full(codes.shape[:2], 0.2, np.float32)
    d[:, :96] = 0.8  # the left part in focus, the rest far behind
    br.write_disparity(tmp_path / "d.png", d)
    common = ["--disparity", tmp_path / "d.png", "--blur", 40, "--focus", 0.8]

    def render(src, out, *extra):
        code = main([str(a) for a in ("render", tmp_path / src, *common, "-o", tmp_path / out, *extra)])
        assert code == 0
        return capsys.readouterr().out

    assert "grain: " in render("p.png", "a.png")
    render("p.png", "a2.png")
    assert "grain:" not in render("p.png", "b.png", "--no-grain")
    assert "grain:" not in render("p.exr", "c.png")
    a, a2, b = (np.asarray(Image.open(tmp_path / n)) for n in ("a.png", "a2.png", "b.png"))
    assert np.array_equal(a, a2)  # seeded: the same command writes the same pixels
    assert np.array_equal(a[:, :80], b[:, :80])  # the sharp part keeps the photo's own grain, untouched
    photo, blurred, kept = _hp_codes(codes[:, :80]), _hp_codes(b[:, 120:]), _hp_codes(a[:, 120:])
    assert blurred < 0.5 * photo  # the blur removed it
    assert kept == pytest.approx(photo, rel=0.2)  # the grain step restored it


def test_the_patch_strip_measures_what_the_whole_frame_high_pass_gives():
    """The measurement's shortcut (tiles cut out with the high-pass's reach, blurred as one strip) against the
    obvious way: the high-pass of the whole frame, each tile's standard deviation, the quantile."""
    import cv2

    _, img = _grainy((100, 140), noise=2.0, seed=4)
    g = gr.measure_grain(img)
    srgb = linear_to_srgb(np.clip(img, 0, 1)).astype(np.float64)
    t, m = gr.TILE, 8
    luma = srgb @ np.array([0.2126, 0.7152, 0.0722])
    hp = luma - cv2.GaussianBlur(luma, (0, 0), gr.HIGHPASS_SIGMA, borderType=cv2.BORDER_REFLECT)
    stds = [hp[m + y : m + y + t, m + x : m + x + t].std() for y in range(0, 100 - 2 * m - t + 1, t)
            for x in range(0, 140 - 2 * m - t + 1, t)]
    assert g.tiles == len(stds) == 5 * 7
    assert g.luma == pytest.approx(np.quantile(stds, gr.FLAT_QUANTILE), rel=1e-4)


def test_the_api_keep_grain_is_what_render_writes(tmp_path, capsys):
    """``bokehray.keep_grain`` after ``bokehray.render``: the same pixels as ``bokehray render`` writes."""
    from PIL import Image

    codes, _ = _grainy(seed=9)
    Image.fromarray(codes).save(tmp_path / "p.png")
    d = np.full(codes.shape[:2], 0.2, np.float32)
    d[:, :96] = 0.8
    br.write_disparity(tmp_path / "d.exr", d)
    assert main([str(a) for a in ("render", tmp_path / "p.png", "--disparity", tmp_path / "d.exr", "--blur", 30,
                                  "--focus", 0.8, "-o", tmp_path / "o.exr", "--quiet")]) == 0
    photo = br.read_image(tmp_path / "p.png")
    blur = br.BlurParams(30, 0.8)
    out = br.keep_grain(br.render(photo, d, blur), photo, d, blur)
    np.testing.assert_allclose(br.read_image(tmp_path / "o.exr"), out, atol=1e-6)
    assert not np.allclose(out, br.render(photo, d, blur), atol=1e-3)  # the render itself has none


@pytest.mark.parametrize("shape", [(), (1,), (4,)])
def test_grey_and_alpha_arrays_get_grain_too(shape):
    _, img = _grainy()
    if shape == ():
        arr = np.ascontiguousarray(img[..., 1])
    elif shape == (1,):
        arr = np.ascontiguousarray(img[..., 1:2])
    else:
        arr = np.concatenate([img, np.ones(img.shape[:2] + (1,), np.float32)], axis=2)
    g = gr.measure_grain(arr)
    assert g.luma > 0
    out = gr.restore_grain(arr.copy(), g, np.ones(img.shape[:2], np.float32))
    assert out.shape == arr.shape and not np.array_equal(out, arr) and (out >= 0).all()


def test_the_grain_does_not_depend_on_the_number_of_cores(monkeypatch):
    """Each band of rows draws from its own generator: one core or many give the same pixels."""
    _, img = _grainy((700, 900))  # several row bands
    g = gr.measure_grain(img)
    removed = gr.removed_share(np.full(img.shape[:2], 12.0, np.float32))
    many = gr.restore_grain(img.copy(), g, removed, dither_bits=8)
    monkeypatch.setattr(gr.os, "cpu_count", lambda: 1)
    one = gr.restore_grain(img.copy(), g, removed, dither_bits=8)
    assert np.array_equal(one, many) and not np.array_equal(one, img)


def test_unit_noise_has_a_unit_highpass():
    n = np.random.default_rng(3).standard_normal((1024, 1024), dtype=np.float32)
    assert float(gr._highpass(n * np.float32(gr._unit_gain())).std()) == pytest.approx(1.0, rel=0.01)


@given(st.floats(-1.0, 4.0, allow_nan=False, width=32))
def test_the_srgb_slope_table_follows_the_curve(x):
    got = float(gr._srgb_slope(np.array([x], np.float32))[0])
    lin = min(max(x, 0.0), 1.0)
    want = 0.0 if x >= 1.0 else (2.4 / 1.055 * lin ** (1.4 / 2.4) if lin > 0.0031308 else 1 / 12.92)
    assert got == pytest.approx(want, rel=0.018, abs=1e-12)
