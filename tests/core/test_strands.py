"""Strands broken in the map: gaps bridged where the photo shows the strand (bokehray.strands, docs/soft-scene.md)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import ndimage

import bokehray as br
from bokehray.app.demo import stroke
from bokehray.colour import linear_to_srgb
from bokehray.levels.raytrace import Layer, raytrace_layers
from bokehray.matting import split_mixed_pixels
from bokehray.strands import (
    TILE_PX,
    HiddenLightRule,
    StrandRule,
    bridge_strands,
    gap_offsets,
    hidden_lights,
    varied_tiles,
)
from tests.reference.strands_ref import bridge_strands_ref, hidden_lights_ref, strand_pixels_ref

K, FOCUS, D_STRAND, D_BG = 32.0, 0.1, 0.9, 0.1


def _strand_scene(n: int, seed: int, width: float = 0.6, gap_colour: bool = False):
    """A slanted strand ``width`` px wide over a textured background, its map by the alpha >= 0.5 rule (a row of
    dashes for a width below 1 px). ``gap_colour``: the photo shows background, not the strand, wherever the map
    has no strand (a dashed strand in the photo too). Returns the photo, the map, the strand's coverage and the map
    with the strand whole (each row's most covered pixel too)."""
    rng = np.random.default_rng(seed)
    tex = ndimage.gaussian_filter(rng.uniform(0.05, 0.3, (n, n, 3)), (1.5, 1.5, 0))
    x0, x1 = rng.uniform(0.3, 0.45) * n, rng.uniform(0.55, 0.7) * n
    pts = np.array([[x0, -2.0], [x1, n + 2.0]])
    sl, a = stroke(pts, np.full(2, width), n, n)
    alpha = np.zeros((n, n), np.float32)
    alpha[sl] = a
    disp = np.where(alpha >= 0.5, D_STRAND, D_BG).astype(np.float32)
    if gap_colour:
        alpha = np.where(alpha >= 0.5, alpha, 0.0).astype(np.float32)
    colour = np.array(rng.uniform(0.5, 0.9, 3), np.float32) * np.float32([0.9, 1.0, 0.4])
    img = (alpha[..., None] * colour + (1 - alpha[..., None]) * tex).astype(np.float32)
    whole = disp.copy()
    rows = np.flatnonzero(alpha.max(1) > 0.1)
    whole[rows, alpha[rows].argmax(1)] = D_STRAND
    return img, disp, alpha, whole


def _edge_scene(n: int, seed: int, width: float = 0.9, light: float = 0.0):
    """A bright strand ``width`` px wide entering the frame through its right border at a shallow angle (the
    demo's blade at the frame's edge), over a dark textured background (its mean lifted by ``light``). Returns the
    photo, the map by the alpha >= 0.5 rule, the strand's coverage and the map with the strand whole."""
    rng = np.random.default_rng(seed)
    tex = ndimage.gaussian_filter(rng.uniform(0.02, 0.06, (n, n, 3)), (1.5, 1.5, 0)) + np.float32(light)
    pts = np.array([[n + 2.5, -4.0], [n - 12.0, n + 2.0]])
    sl, a = stroke(pts, np.full(2, width), n, n)
    alpha = np.zeros((n, n), np.float32)
    alpha[sl] = a
    disp = np.where(alpha >= 0.5, D_STRAND, D_BG).astype(np.float32)
    colour = np.float32([0.45, 0.5, 0.3])
    img = (alpha[..., None] * colour + (1 - alpha[..., None]) * tex).astype(np.float32)
    whole = disp.copy()
    rows = np.flatnonzero(alpha.max(1) > 0.1)
    whole[rows, alpha[rows].argmax(1)] = D_STRAND
    return img, disp, alpha, whole


def _coc(disp: np.ndarray) -> np.ndarray:
    return (K * (disp - FOCUS)).astype(np.float32)


@pytest.mark.parametrize("seed", range(6))
def test_the_kernel_matches_the_float64_oracle(seed):
    rng = np.random.default_rng(seed)
    img, disp, _, _ = _strand_scene(48, seed, width=rng.uniform(0.5, 0.9), gap_colour=seed % 3 == 2)
    # a second, wider strand and a solid block at other depths: pairs across depths, thick and thin pixels
    disp[30:40, 5:15] = 0.6
    disp[:, 40] = np.where(np.arange(48) % 5 < 3, 0.7, disp[:, 40])  # its gaps in the map, not in the photo
    img[:, 40] = 0.4 * img[:, 40] + 0.6 * np.float32([0.1, 0.5, 0.9])
    s = _coc(disp)
    rule = StrandRule()
    got, n = bridge_strands(img, s, rule)
    want = bridge_strands_ref(img, s, rule, gap_offsets(rule.max_gap))
    assert n == int((want != s).sum()) and n > 0
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-4)


@pytest.mark.parametrize("seed", range(3))
def test_the_kernel_extends_ends_as_the_oracle_does(seed):
    """Dash ends extended along their strands (a strand entering the frame, the tips of a tapered one): the same
    pixels and values as the float64 oracle, and some there are."""
    img, disp, _, _ = _edge_scene(48, seed)
    sl, a = stroke(np.array([[8.0, 6.0], [20.0, 40.0]]), np.array([1.6, 0.0]), 48, 48)  # a tapered blade
    tip = np.zeros((48, 48), np.float32)
    tip[sl] = a
    disp = np.where(tip >= 0.5, 0.7, disp).astype(np.float32)
    img = (tip[..., None] * np.float32([0.6, 0.3, 0.2]) + (1 - tip[..., None]) * img).astype(np.float32)
    s = _coc(disp)
    for rule in (StrandRule(), StrandRule(end_px=0)):
        got, _ = bridge_strands(img, s, rule)
        np.testing.assert_allclose(got, bridge_strands_ref(img, s, rule, gap_offsets(rule.max_gap)), rtol=0, atol=1e-4)
    ends = bridge_strands(img, s)[0] != bridge_strands(img, s, StrandRule(end_px=0))[0]
    assert ends.sum() >= 2


def test_a_strand_entering_the_frame_takes_its_depth_up_to_the_border():
    """The regression (the demo's blade at the frame's right edge): a strand whose core lies beyond the border
    covers the last column by less than 1/2 for a few rows before its first dash; those pixels kept the
    background's depth and stayed sharp when the strand blurred in front. They now take the strand's depth as far
    as the photo shows a quarter of the strand's colour."""
    img, disp, alpha, _ = _edge_scene(64, 0)
    s = _coc(disp)
    out, _ = bridge_strands(img, s)
    first = int(np.flatnonzero(disp[:, -1] > D_BG)[0])  # the strand's first dash in the last column
    lead = np.arange(first)
    held = lead[alpha[lead, -1] >= 0.15]  # a quarter of the first dash's share of the strand, or more
    assert held.size >= 2
    assert np.allclose(out[held, -1], K * (D_STRAND - FOCUS))
    assert (out[lead[alpha[lead, -1] < 0.05]] == s[lead[alpha[lead, -1] < 0.05]]).all()


def test_a_strand_entering_the_frame_blurred_in_front_leaves_no_speck():
    """Its faint start at the border rendered +47 in 8-bit sRGB over the render with the strand whole."""
    img, disp, alpha, whole = _edge_scene(96, 1)
    blur = br.BlurParams(K, FOCUS)
    ref = br.render(img, whole, blur)
    on = br.render(img, disp, blur)
    entry = alpha >= 0.05
    entry[int(np.flatnonzero(disp[:, -1] > D_BG)[0]) + 2 :] = False  # down to just below its first dash
    assert _speck(on, ref, entry) <= 3.0


def test_no_gap_or_end_is_taken_over_a_light():
    """Over a light (the background brighter than a white surface), the colour test cannot read the strand's
    share: a gap pixel there keeps its depth (the fur's bridges over a lamp's rim split the lamp into the blur)."""
    img, disp, _, _ = _strand_scene(64, 1)
    lit = (img + np.float32(1.5)).astype(np.float32)
    s = _coc(disp)
    assert bridge_strands(img, s)[1] > 10
    out, n = bridge_strands(lit, s)
    assert n == 0 and out is s


def test_a_dashed_strand_s_gaps_take_its_depth():
    img, disp, alpha, _ = _strand_scene(64, 1)
    s = _coc(disp)
    out, n = bridge_strands(img, s)
    bridged = out != s
    assert n > 10
    assert np.allclose(out[bridged], K * (D_STRAND - FOCUS))
    assert alpha[bridged].min() > 0.1  # only pixels holding the strand
    # the strand is whole in the map: its dashes joined into one 8-connected piece
    assert ndimage.label(s > 0, np.ones((3, 3)))[1] > 3
    assert ndimage.label(out > 0, np.ones((3, 3)))[1] == 1


def test_a_gap_the_photo_shows_as_background_stays():
    img, disp, _, _ = _strand_scene(64, 1, gap_colour=True)
    s = _coc(disp)
    out, n = bridge_strands(img, s)
    assert n == 0 and out is s


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**16), kind=st.sampled_from(["disc", "box"]), size=st.integers(5, 20),
       levels=st.integers(2, 4))
def test_a_hard_map_of_solid_objects_is_left_exactly_as_it_is(seed, kind, size, levels):
    """No pixel of a map of solid objects (at least 5 px across, overlapping at several depths) moves when the photo
    shows them as the map does (the photo is the map's own shading, plus noise): a box's corners are thin along a
    diagonal, but what lies between two of them is what the photo shows there."""
    rng = np.random.default_rng(seed)
    n = 40
    yy, xx = np.mgrid[0:n, 0:n]
    disp = np.full((n, n), rng.uniform(0, 0.3), np.float32)
    for _ in range(levels - 1):
        cy, cx = rng.uniform(0, n, 2)
        if kind == "disc":
            m = (yy - cy) ** 2 + (xx - cx) ** 2 <= (size / 2) ** 2
        else:
            m = (np.abs(yy - cy) <= size / 2) & (np.abs(xx - cx) <= size / 2)
        disp[m] = rng.uniform(0.35, 1.0)
    img = np.repeat(disp[..., None], 3, 2) * rng.uniform(0.2, 1.0, 3).astype(np.float32)
    img = (img + rng.uniform(0, 0.05, img.shape)).astype(np.float32)
    s = _coc(disp)
    out, n_moved = bridge_strands(img, s)
    assert n_moved == 0 and out is s


def _speck(render: np.ndarray, ref: np.ndarray, where: np.ndarray) -> float:
    """The largest local excess of ``render`` over ``ref`` at ``where``, in 8-bit sRGB: their difference less its
    median over 9 x 9 px (a broad difference is the blur's level, not a speck)."""
    d = (linear_to_srgb(np.clip(render, 0, 1)) - linear_to_srgb(np.clip(ref, 0, 1))) * 255
    local = np.stack([ndimage.median_filter(d[..., c], size=9) for c in range(3)], -1)
    return float((d - local).max(2)[where].max())


def test_a_dashed_strand_blurred_in_front_leaves_no_speck():
    """The regression: a 0.6 px strand the map breaks into dashes, blurred in front (focus far), left a speck of
    its colour at every gap (the gap's share of the strand stayed sharp at the background's depth)."""
    img, disp, alpha, whole = _strand_scene(96, 3)
    blur = br.BlurParams(K, FOCUS)
    ref = br.render(img, whole, blur)
    on = br.render(img, disp, blur)
    off = br.render(img, disp, blur, layers=br.LayerOptions(strand_gaps=False))
    where = alpha >= 0.05
    assert _speck(off, ref, where) > 6.0
    assert _speck(on, ref, where) <= 3.0


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**16), h=st.integers(5, 70), w=st.integers(5, 70), n=st.integers(0, 6))
def test_the_tiles_skipped_hold_no_strand_pixel(seed, h, w, n):
    """The strand-pixel pass skips tiles whose neighbourhood's map spans at most a jump: no pixel the oracle calls a
    strand pixel lies in one (maps of flat blocks, thin lines and a gentle slope)."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:h, :w]
    s = (0.01 * xx + 0.005 * yy).astype(np.float32)  # a slope: 0.01 px of CoC a px across
    for _ in range(n):
        y0, x0 = rng.integers(0, h), rng.integers(0, w)
        s[y0 : y0 + rng.integers(1, 20), x0 : x0 + rng.integers(1, 4)] += np.float32(rng.uniform(-5, 5))
    rule = StrandRule()
    strand = strand_pixels_ref(s, rule)
    covered = np.zeros((h, w), bool)
    for ty, tx in varied_tiles(s, rule.jump_px, rule.thin_px):
        covered[ty : ty + TILE_PX, tx : tx + TILE_PX] = True
    assert not (strand & ~covered).any()
    if n == 0 and h >= 3 * TILE_PX and w >= 3 * TILE_PX:
        assert not covered[TILE_PX : 2 * TILE_PX, TILE_PX : 2 * TILE_PX].any()  # a flat inner tile is skipped


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**16), th=st.integers(1, 6), tw=st.integers(1, 6), log_t=st.integers(0, 4))
def test_the_tile_reduction_is_the_tiles_max_and_min(seed, th, tw, log_t):
    """The strands' tile reduction by halving (rows first, then columns) gives each tile's max and min."""
    from bokehray.strands import _tile_reduce

    t = 1 << log_t
    a = np.random.default_rng(seed).normal(0, 3, (th * t, tw * t)).astype(np.float32)
    tiles = a.reshape(th, t, tw, t)
    np.testing.assert_array_equal(_tile_reduce(a, t, np.maximum), tiles.max(axis=(1, 3)))
    np.testing.assert_array_equal(_tile_reduce(a, t, np.minimum), tiles.min(axis=(1, 3)))


def _lamp_scene(n: int, width: float, seed: int = 0, radius: float = 3.5, radiance: float = 8.0):
    """An opaque strand ``width`` px wide across a light (a disc of ``radiance``) on a dark textured plane: the
    two layers (straight RGBA; strand at disparity 0.85, plane at 0.15), the photo and its map (alpha >= 0.5)."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:n, 0:n] + 0.5
    bg = ndimage.gaussian_filter(rng.uniform(0.02, 0.08, (n, n, 3)), (1.5, 1.5, 0))
    disc = np.clip(radius + 0.5 - np.hypot(yy - n / 2, xx - n / 2 - 0.3), 0, 1)[..., None]
    bg = (bg * (1 - disc) + disc * radiance * np.array([1.0, 0.85, 0.6])).astype(np.float32)
    a = np.clip(width / 2 + 0.5 - np.abs((yy - n / 2 - 0.4) * 0.96 - (xx - n / 2) * 0.28), 0, 1).astype(np.float32)
    fg = np.concatenate([np.broadcast_to(np.float32([0.3, 0.2, 0.12]), (n, n, 3)), a[..., None]], 2)
    photo = (a[..., None] * fg[..., :3] + (1 - a[..., None]) * bg).astype(np.float32)
    layers = [Layer(fg.astype(np.float32), plane=(0.0, 0.0, 0.85)),
              Layer(np.concatenate([bg, np.ones((n, n, 1), np.float32)], 2), plane=(0.0, 0.0, 0.15))]
    return photo, np.where(a >= 0.5, 0.85, 0.15).astype(np.float32), a, layers


@pytest.mark.parametrize("width", [1.6, 2.5, 3.0])
def test_hidden_lights_match_the_loop_oracle(width):
    photo, disp, _, _ = _lamp_scene(40, width)
    s = (24.0 * (disp - 0.15)).astype(np.float32)
    soft = split_mixed_pixels(photo, s)
    rule = HiddenLightRule()
    out, n = hidden_lights(photo, s, soft, rule)
    want = hidden_lights_ref(photo, s, soft, rule)
    added = np.setdiff1d(out.index, soft.index)
    assert n == len(want) == added.size and n > 0
    assert sorted(want) == added.tolist()
    k = np.searchsorted(out.index, added)
    np.testing.assert_allclose(out.background[k], [want[i][0] for i in added], rtol=1e-5)
    np.testing.assert_allclose(out.far_coc[k], [want[i][1] for i in added], rtol=1e-5)
    np.testing.assert_allclose(out.alpha[k][:, None] * out.foreground[k] + (1 - out.alpha[k][:, None])
                               * out.background[k], photo.reshape(-1, 3)[added], atol=1e-5)  # the photo, in focus
    kept = np.searchsorted(out.index, soft.index)
    np.testing.assert_array_equal(out.background[kept], soft.background)


def test_no_light_no_hidden_light():
    photo, disp, _, _ = _lamp_scene(40, 3.0, radiance=0.9)  # a bright surface, not a light
    s = (24.0 * (disp - 0.15)).astype(np.float32)
    soft = split_mixed_pixels(photo, s)
    out, n = hidden_lights(photo, s, soft)
    assert n == 0 and out is soft


def test_a_light_behind_an_opaque_strand_shows_once_the_strand_blurs():
    """The regression: a 3 px opaque strand across a light, focused on the light (the strand blurred in front).
    Through the lens the light shows whole; the render filled the hidden part with the dim tone-mapped fill of a
    hidden region (the bench's thin strands: the largest error). Against the exact thin-lens trace of the two
    layers, over the light's hidden pixels."""
    photo, disp, a, layers = _lamp_scene(48, 3.0)
    blur = br.BlurParams(24.0, 0.15)
    truth, _ = raytrace_layers(layers, blur, options=br.RaytraceOptions(max_spp=64))
    truth = truth[..., :3]
    hidden = (a > 0.99) & (truth.mean(2) > 1.0)  # the strand's opaque pixels where the light shows through the lens
    assert hidden.sum() >= 10

    def err(img):  # in linear light: a light's value, not its clipped display
        return float(np.abs(img - truth)[hidden].mean())

    before = br.render(photo, disp, blur, layers=br.LayerOptions(strand_gaps=False))
    after = br.render(photo, disp, blur)
    assert err(before) > 2.0  # the light's 5.2 there rendered 2.2
    assert err(after) < 0.4 * err(before)


@pytest.mark.parametrize(("width", "radius"), [(0.6, 6.0), (0.7, 6.0), (0.7, 3.5)])
def test_a_strand_thinner_than_a_pixel_across_a_light_in_focus_shows_its_own_colour(width, radius):
    """The regression (the dev set's lamp spoke): a strand thinner than a pixel across a light, focused on the
    strand (the light blurred behind it). Through a pixel it shows ``(1 - c) L + c F``: sharp, its share ``c F``
    and the light's share blurred away. The matting took F from the strand's most covered samples over the dark
    plane (its colour times their coverage), or kept the window's lamp-bright F where that one held too little
    more of the light: pixels of the strand rendered at the lamp's brightness (1.1 - 1.4 against 0.3 - 0.4).
    Against the exact thin-lens trace, in linear light, at the strand's map pixels over the light."""
    photo, disp, _, layers = _lamp_scene(64, width, radius=radius, radiance=6.0)
    blur = br.BlurParams(24.0, 0.85)
    truth, _ = raytrace_layers(layers, blur, options=br.RaytraceOptions(max_spp=64))
    over = (disp == 0.85) & (photo.mean(2) > 1.0)
    assert over.sum() >= 4
    err = np.abs(br.render(photo, disp, blur) - truth[..., :3])[over]
    assert err.max() < 0.15 and err.mean() < 0.05


@pytest.mark.parametrize(("width", "radius", "radiance", "bound"), [(4.0, 3.0, 17.0, 0.09), (4.0, 2.5, 8.0, 0.042)])
@pytest.mark.parametrize("focus", [0.85, 0.15])
def test_a_near_pixel_brighter_than_both_its_parts_takes_the_light_behind_it(width, radius, radiance, bound, focus):
    """The regression (``bench_thin.py``'s strands: dim bokeh discs around small lights): a strand 4 px wide over a
    small light. A rim pixel of the strand over the light is brighter than the window's F (the strand) and its B
    (the purest far samples: the dark plane around the small light), which ``alpha F + (1 - alpha) B`` cannot be;
    the pixel stayed whole, lamp-bright at the strand's depth: a dim disc of the light's colour when the strand
    blurs, a hole in the light when it is in focus behind it. Its B is now the brightest far samples within 4 px.
    Mean linear error against the exact trace within 22 px of the light: before 0.113 / 0.117 and 0.049 / 0.051
    (focus on the strand / on the light), now 0.069 / 0.075 and 0.034 / 0.038."""
    photo, disp, _, layers = _lamp_scene(48, width, radius=radius, radiance=radiance)
    blur = br.BlurParams(24.0, focus)
    truth, _ = raytrace_layers(layers, blur, options=br.RaytraceOptions(max_spp=64))
    yy, xx = np.mgrid[0:48, 0:48]
    near = np.hypot(yy - 24, xx - 24) < 22
    assert float(np.abs(br.render(photo, disp, blur) - truth[..., :3])[near].mean()) < bound


def test_the_brightest_far_samples_match_the_oracle():
    """The band kernel against its float64 loop where a near pixel brighter than both its parts takes the window's
    brightest far samples as B (the branch runs: B moves)."""
    from reference.matting_ref import band_pixel_ref, gaussian_weights

    from bokehray.edge_estimate import MattingRule, depth_edges, launch_band_kernel, window_offsets

    photo, disp, _, _ = _lamp_scene(48, 4.0, radius=3.0, radiance=17.0)
    coc = (24.0 * (disp - 0.85)).astype(np.float32)
    scale = float(photo.max())
    img = photo / np.float32(scale)
    edges = depth_edges(coc, 1.0)
    by, bx = np.nonzero(edges)
    rule = MattingRule()
    got = launch_band_kernel(img, coc, edges, by, bx, 4, rule, "cpu", 2, scale=scale)
    offs, dist = window_offsets(4)
    g = gaussian_weights(dist, 4)
    moved = 0
    for i in range(by.size):
        args = (img, coc, edges, by[i], bx[i], offs, g, rule.jump_px, rule.unknown_weight, rule.ridge, rule.purity)
        want = band_pixel_ref(*args, rule.light_level / scale, rule.light_ratio, rule.light_reach, rule.light_thin,
                              rule.light_share)
        moved += int(np.abs(band_pixel_ref(*args)[2] - want[2]).max() > 1e-3)
        assert abs(got[0][i] - want[0]) < 2e-4
        np.testing.assert_allclose(got[1][i], want[1], atol=2e-5)
        np.testing.assert_allclose(got[2][i], want[2], atol=2e-5)
        np.testing.assert_allclose(got[4][i], want[4], atol=2e-5)
    assert moved >= 2


def test_a_light_at_two_depths_either_side_is_not_taken_behind_the_strand():
    """On a map blurred like an estimator's a light's own pixels carry depths along the map's ramp; lit pixels at
    two depths on the two sides of a strand are not one light behind it (bench_thin's estimated strands lost 0.65 dB
    in the band when they were)."""
    photo, disp, a, _ = _lamp_scene(40, 3.0)
    s = (24.0 * (disp - 0.15)).astype(np.float32)
    soft = split_mixed_pixels(photo, s)
    assert hidden_lights(photo, s, soft)[1] > 0
    yy = np.mgrid[0:40, 0:40][0]
    above = (a < 0.5) & (yy < 20)  # the far side above the strand, lifted by 3 jumps
    s2 = np.where(above, s + np.float32(3.0), s).astype(np.float32)
    soft2 = split_mixed_pixels(photo, s2)
    _, n = hidden_lights(photo, s2, soft2)
    assert n == len(hidden_lights_ref(photo, s2, soft2, HiddenLightRule())) == 0


@given(st.integers(0, 2**32 - 1), st.integers(1, 24), st.integers(1, 24), st.integers(0, 4))
def test_the_tile_grid_filter_is_scipys(seed, h, w, k):
    """The varied tiles' max and min filters (NumPy, no scipy.ndimage import on the command's path) give
    ndimage's values, the border repeated, infinities (the ragged tiles) included."""
    from bokehray.strands import _grid_filter

    rng = np.random.default_rng(seed)
    a = rng.normal(size=(h, w)).astype(np.float32)
    a[rng.random((h, w)) < 0.1] = np.inf
    a[rng.random((h, w)) < 0.1] = -np.inf
    assert np.array_equal(_grid_filter(a, k, np.maximum), ndimage.maximum_filter(a, 2 * k + 1, mode="nearest"))
    assert np.array_equal(_grid_filter(a, k, np.minimum), ndimage.minimum_filter(a, 2 * k + 1, mode="nearest"))
