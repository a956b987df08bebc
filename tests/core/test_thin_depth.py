"""Thin structures a soft map's blur flattened get their depth back from the photo (bokehray.thin_depth,
docs/soft-scene.md "Soft maps")."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import ndimage

import bokehray as br
from bokehray import thin_depth
from bokehray.thin_depth import ThinRule, restore_thin
from tests.core.test_soft_maps import _band_psnr
from tests.reference.thin_ref import restore_thin_ref
from tests.reference.two_planes_ref import TwoPlanes


def _wires(n: int, seed: int, width: float = 2.0, spacing: int = 24):
    """A grid of wires ``width`` px wide (disparity 1, one grey) over a textured background (disparity 0): the
    photo (wire edges antialiased) and the exact map (the alpha >= 0.5 rule)."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:n, 0:n] + 0.5
    off = rng.uniform(0, spacing, 2)
    dist = np.minimum(np.abs((xx - off[0]) % spacing - spacing / 2), np.abs((yy - off[1]) % spacing - spacing / 2))
    alpha = np.clip(width / 2 - dist + 0.5, 0, 1)[..., None]
    wire = rng.uniform(0.4, 0.8) * np.ones(3)
    texture = ndimage.gaussian_filter(rng.uniform(0, 1, (n, n, 3)), (1.5, 1.5, 0))
    background = rng.uniform(0.05, 0.3, 3) * (0.6 + 0.8 * texture)
    image = (alpha * wire + (1 - alpha) * background).astype(np.float32)
    return image, (alpha[..., 0] >= 0.5).astype(np.float32)


def _disc(n: int, seed: int, radius: float = 36.0):
    """A wide object: a disc (disparity 1) with a strong fine texture (fur, grass: +-60 % of its colour) over a
    textured background (disparity 0); the photo and the exact map."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:n, 0:n] + 0.5
    c = n / 2 + rng.uniform(-4, 4, 2)
    alpha = np.clip(radius + 0.5 - np.hypot(yy - c[0], xx - c[1]), 0, 1)[..., None]

    def texture():
        t = ndimage.gaussian_filter(rng.uniform(0, 1, (n, n, 3)), (1.0, 1.0, 0))
        return (t - t.mean()) / t.std()

    fur, ground = texture(), texture()
    fg = rng.uniform(0.2, 0.5, 3) * (1 + 0.6 * fur[..., :1])
    bg = rng.uniform(0.05, 0.3, 3) * (1 + 0.3 * ground)
    image = np.clip(alpha * fg + (1 - alpha) * bg, 0, None).astype(np.float32)
    return image, (alpha[..., 0] >= 0.5).astype(np.float32)


@settings(max_examples=8, deadline=None)
@given(seed=st.integers(0, 2**16), sigma=st.sampled_from([2.0, 4.0]), k=st.floats(8.0, 40.0))
def test_a_wide_object_is_not_restored_nearer_than_itself(seed, sigma, k):
    """A wide object's blurred map keeps its depth as a plateau: its rim is restored no nearer than that (the
    colour model over a texture overshoots: the window's largest restored value lay up to 2.8 K nearer)."""
    image, hard = _disc(128, seed)
    s = (k * (ndimage.gaussian_filter(hard, sigma, mode="nearest") - 0.5)).astype(np.float32)
    out, _ = restore_thin(image, s)
    assert out.max() <= 0.5 * k + 0.5, out.max() - 0.5 * k


@settings(max_examples=8, deadline=None)
@given(seed=st.integers(0, 2**16), sigma=st.sampled_from([2.0, 4.0]), k=st.floats(8.0, 40.0))
def test_blurred_wires_get_their_depth_back(seed, sigma, k):
    """A 2 px wire blurred by 2-4 px keeps a fraction of its step; restored, most wire pixels are at the wire's
    depth again and most background pixels at the background's."""
    image, hard = _wires(96, seed)
    soft = ndimage.gaussian_filter(hard, sigma, mode="nearest")
    s = (k * (soft - 0.5)).astype(np.float32)
    out, n = restore_thin(image, s, bounds=(-0.5 * k, 0.5 * k))
    wire, bg = hard > 0.5, ndimage.binary_erosion(hard < 0.5, iterations=2)
    assert n > 0
    err_before = np.abs(s - k * (hard - 0.5))
    err_after = np.abs(out - k * (hard - 0.5))
    assert err_after[wire].mean() < 0.5 * err_before[wire].mean()
    assert (err_after[wire] < 0.25 * k).mean() > 0.7
    assert (err_after[bg] < 0.05 * k).mean() > 0.9
    assert out.min() >= -0.5 * k and out.max() <= 0.5 * k


@settings(max_examples=25, deadline=None)
@given(levels=st.lists(st.floats(-30.0, 30.0), min_size=2, max_size=3), cell=st.integers(1, 10),
       seed=st.integers(0, 2**16))
def test_a_hard_map_is_left_exactly_as_it_is(levels, cell, seed):
    """Two or three depths, in blocks of any size down to single pixels, under any photo: every window holds a
    step of half its range or more, which no blur makes."""
    rng = np.random.default_rng(seed)
    labels = ndimage.zoom(rng.integers(0, len(levels), (-(-64 // cell),) * 2), cell, order=0)[:64, :64]
    s = np.asarray(levels, np.float32)[labels]
    img = rng.uniform(0, 1, s.shape + (3,)).astype(np.float32)
    out, n = restore_thin(img, s, bounds=(-30.0, 30.0))
    assert n == 0 and out is s


@settings(max_examples=25, deadline=None)
@given(gy=st.floats(-3.0, 3.0), gx=st.floats(-3.0, 3.0), c=st.floats(-20.0, 20.0), seed=st.integers(0, 2**16))
def test_a_tilted_plane_is_left_exactly_as_it_is(gy, gx, c, seed):
    yy, xx = np.mgrid[0:96, 0:96].astype(np.float32)
    s = (c + gy * (yy - 48) + gx * (xx - 48)).astype(np.float32)
    img, _ = _wires(96, seed)  # a photo with strong thin structures the plane must not take
    out, n = restore_thin(img, s)
    assert n == 0 and out is s


@settings(max_examples=40, deadline=None)
@given(height=st.floats(2.0, 40.0), width=st.floats(12.0, 40.0), seed=st.integers(0, 2**16))
def test_a_smooth_slope_is_left_exactly_as_it_is(height, width, seed):
    """A hill (a face turning, a rounded object) is explained by no photo better than by its own smooth surface."""
    yy, xx = np.mgrid[0:96, 0:96].astype(np.float32)
    s = (height * np.exp(-((yy - 48) ** 2 + (xx - 40) ** 2) / (2 * width**2))).astype(np.float32)
    img = np.random.default_rng(seed).uniform(0, 1, (96, 96, 3)).astype(np.float32)
    out, n = restore_thin(img, s)
    assert n == 0 and out is s


@settings(max_examples=4, deadline=None)
@given(seed=st.integers(0, 2**16), sigma=st.sampled_from([2.0, 4.0]), k=st.floats(8.0, 40.0),
       wide=st.booleans())
def test_the_restoration_matches_the_float64_oracle(seed, sigma, k, wide):
    """Wires (thin: the largest restored value) or a textured disc (wide: the map's plateau)."""
    rule = ThinRule(sigmas=(2.0, 4.0))
    image, hard = _disc(64, seed, radius=18.0) if wide else _wires(64, seed, spacing=16)
    s = (k * (ndimage.gaussian_filter(hard, sigma, mode="nearest") - 0.5)).astype(np.float32)
    got, _ = restore_thin(image, s, rule)
    want, moved = restore_thin_ref(image, s, rule)
    got_moved = got != s
    assert moved.any()
    # float32 block means and model against float64 windows: a threshold can fall either side at a pixel or a
    # block, and a window's near value is the largest of its blocks' values (one more or one fewer moves it)
    assert (got_moved != moved).mean() <= 0.03
    both = got_moved & moved
    assert (np.abs(got[both] - want[both]) <= 1e-3 * k).mean() >= 0.9
    assert np.median(np.abs(got[both] - want[both])) <= 1e-4 * k


def test_a_map_without_ramps_is_returned_as_given():
    s = np.full((40, 50), 3.0, np.float32)
    out, n = restore_thin(np.zeros((40, 50, 3), np.float32), s)
    assert n == 0 and out is s


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(10 * np.log10(1.0 / np.mean((np.clip(a, 0, 1) - np.clip(b, 0, 1)) ** 2)))


def test_a_render_from_a_soft_map_of_wires_comes_close_to_the_hard_map_s():
    """Focused on the background, wires in front blurred: from the soft map (sigma 2 px) with the restoration the
    render is much closer to the hard map's render than without it (where the wires keep the background's depth
    and stay sharp)."""
    image, hard = _wires(128, 5)
    soft = ndimage.gaussian_filter(hard, 2.0, mode="nearest").astype(np.float32)
    blur = br.BlurParams(16.0, 0.0)
    want = br.render(image, hard, blur)
    on = br.render(image, soft, blur, layers=br.LayerOptions(thin_depth=True))
    off = br.render(image, soft, blur)
    assert _psnr(on, want) > _psnr(off, want) + 3.0, (_psnr(on, want), _psnr(off, want))


def test_the_option_is_checked():
    with pytest.raises(br.InputError, match="thin_depth"):
        br.LayerOptions(thin_depth=1)


@pytest.mark.parametrize("focus", [0.15, 0.5, 0.85])
def test_the_two_plane_scene_stays_within_1_5_db_of_the_hard_map(focus):
    """A wide edge is the ramp snap's: with the restoration on, the soft map of the analytic two-plane scene still
    renders within 1.5 dB of the hard map in the band (tests/core/test_soft_maps.py, the same check without it)."""
    sc = TwoPlanes()
    photo, hard = sc.photo().astype(np.float32), sc.hard_map().astype(np.float32)
    k = 24.0
    ref = sc.bokeh(k, focus)
    yy, xx = np.mgrid[0 : sc.n, 0 : sc.n] + 0.5
    band = np.abs(np.hypot(yy - sc.c, xx - sc.c) - sc.radius) <= k * max(focus, 1 - focus) + 4
    soft = ndimage.gaussian_filter(hard, 4.0, mode="nearest").astype(np.float32)
    blur = br.BlurParams(k, focus)
    p_hard = _band_psnr(br.render(photo, hard, blur), ref, band)
    p_thin = _band_psnr(br.render(photo, soft, blur, layers=br.LayerOptions(thin_depth=True)), ref, band)
    assert p_thin >= p_hard - 1.5, (p_hard, p_thin)


def test_tiles_give_the_whole_image_s_result(monkeypatch):
    """The fit goes over its grid tile by tile with a margin its windows and blur reach through: small tiles give
    what one tile does (the same pixels moved, to the same values up to float32 rounding)."""
    image, hard = _wires(160, 11, spacing=20)
    s = (24.0 * (ndimage.gaussian_filter(hard, 2.0, mode="nearest") - 0.5)).astype(np.float32)
    whole, n = restore_thin(image, s)
    monkeypatch.setattr(thin_depth, "_TILE", 6)
    tiled, m = restore_thin(image, s)
    assert n > 0 and m == n
    np.testing.assert_array_equal(tiled != s, whole != s)
    np.testing.assert_allclose(tiled, whole, atol=1e-4)  # each tile centres its colours: rounding only


def test_a_capped_map_is_not_restored():
    """Radii beyond twice the diagonal are compressed (scene.cap_coc): the map is then no blur of one, and the
    restoration is not attempted (the render equals the one without it)."""
    image, hard = _wires(48, 2, spacing=16)
    soft = ndimage.gaussian_filter(hard, 2.0, mode="nearest").astype(np.float32)
    blur = br.BlurParams(2000.0, 0.0)
    on = br.render(image, soft, blur, layers=br.LayerOptions(thin_depth=True))
    np.testing.assert_array_equal(on, br.render(image, soft, blur))
    _, stats = br.render_with_stats(image, soft, br.BlurParams(16.0, 0.0), layers=br.LayerOptions(thin_depth=True))
    assert "thin depth" in stats.stage_seconds


def _chosen_blurs(monkeypatch) -> list:
    """The blur each restore_thin call keeps for its image (recorded from its choice)."""
    chosen = []
    best_fit = thin_depth._best_fit

    def spy(*args):
        fit = best_fit(*args)
        chosen.append(None if fit is None else fit.sigma)
        return fit

    monkeypatch.setattr(thin_depth, "_best_fit", spy)
    return chosen


@settings(max_examples=6, deadline=None)
@given(seed=st.integers(0, 2**16), sigma=st.sampled_from([2.0, 4.0, 8.0]))
def test_the_image_keeps_the_blur_its_map_has(seed, sigma):
    """One map, one blur: wires 3 px wide, their map blurred by 2, 4 or 8 px, are read with that blur."""
    with pytest.MonkeyPatch.context() as mp:
        chosen = _chosen_blurs(mp)
        image, hard = _wires(192, seed, spacing=40, width=3.0)
        s = (24.0 * (ndimage.gaussian_filter(hard, sigma, mode="nearest") - 0.5)).astype(np.float32)
        _, n = restore_thin(image, s)
    assert chosen == [sigma] and n > 0


def test_a_map_blurred_beyond_the_blurs_tried_is_read_with_the_largest(monkeypatch):
    """The demo with its map blurred by 11 px: the 2 px blur explains a handful of windows best (its median
    residual is the lowest) but is not the map's; the image is read with 8 px, the one most of it fits, and its
    thin structures move (read with 2 px, nothing did)."""
    from bokehray.app.demo import build_demo_scene

    chosen = _chosen_blurs(monkeypatch)
    sc = build_demo_scene(768, 512)
    d = ndimage.gaussian_filter(sc.disparity, 11.0, mode="nearest").astype(np.float32)
    _, n = restore_thin(sc.image, (30.0 * (d - 0.1)).astype(np.float32), bounds=(-3.0, 27.0))
    assert chosen == [8.0] and n > 0


@settings(max_examples=4, deadline=None)
@given(seed=st.integers(0, 2**16), sigma=st.sampled_from([2.0, 4.0, 8.0]))
def test_the_blur_chosen_from_part_of_the_tiles_is_the_one_all_of_them_choose(seed, sigma):
    """The image's blur is chosen from a lattice of the grid's tiles (where there are enough), and the chosen blur
    then fitted on all of them: the same map as a choice from every tile."""
    image, hard = _wires(192, seed, spacing=40, width=3.0)
    s = (24.0 * (ndimage.gaussian_filter(hard, sigma, mode="nearest") - 0.5)).astype(np.float32)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(thin_depth, "_TILE", 12)  # 4 - 64 tiles a grid: the choice from a half or a quarter of them
        half, n = restore_thin(image, s)
        mp.setattr(thin_depth, "_SPARE", 10**9)
        every, m = restore_thin(image, s)
    assert n > 0 and m == n
    np.testing.assert_array_equal(half, every)
