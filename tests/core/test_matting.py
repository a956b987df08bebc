"""Soft edges at depth edges (``bokehray.matting.split_mixed_pixels``): the contract, accuracy on scenes whose
true layers are known, and invariants on arbitrary input."""

import itertools

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from reference.matting_ref import ramp_width_ref
from scipy import ndimage

from bokehray.edge_estimate import depth_edges, isolated_share, ramp_width, window_offsets
from bokehray.errors import InputError
from bokehray.matting import MattingRule, split_mixed_pixels
from bokehray.scene import SoftEdges

K = 30.0


def _textures(n, seed):
    rng = np.random.default_rng(seed)
    fg = np.array([0.7, 0.35, 0.15]) + ndimage.gaussian_filter(rng.normal(0, 0.08, (n, n, 3)), (1.5, 1.5, 0))
    bg = np.array([0.1, 0.25, 0.45]) + ndimage.gaussian_filter(rng.normal(0, 0.08, (n, n, 3)), (1.5, 1.5, 0))
    return np.clip(fg, 0.0, None).astype(np.float32), np.clip(bg, 0.0, None).astype(np.float32)


def two_plane(n=64, seed=0, kind="disc"):
    """A textured near layer (a disc with an antialiased rim, or 1-2 px strands) over a textured far plane.
    Returns (photo, signed CoC by the alpha >= 0.5 rule, true alpha, F, B)."""
    fg, bg = _textures(n, seed)
    yy, xx = np.mgrid[0:n, 0:n] + 0.5
    if kind == "disc":
        alpha = np.clip(0.3 * n + 0.5 - np.hypot(yy - n / 2, xx - n / 2), 0.0, 1.0)
    else:  # strands of width 1.2 and 2.0 px at slants
        alpha = np.zeros((n, n))
        for x0, slope, width in ((0.3 * n, 0.21, 1.2), (0.65 * n, -0.13, 2.0)):
            dist = np.abs(xx - (x0 + slope * yy)) / np.hypot(1.0, slope)
            alpha = np.maximum(alpha, np.clip(width / 2 + 0.5 - dist, 0.0, min(width, 1.0)))
    alpha = alpha.astype(np.float32)
    photo = (alpha[..., None] * fg + (1.0 - alpha[..., None]) * bg).astype(np.float32)
    coc = np.where(alpha >= 0.5, K * 0.4, -K * 0.3).astype(np.float32)
    return photo, coc, alpha, fg, bg


def estimated_alpha(se: SoftEdges, coc: np.ndarray) -> np.ndarray:
    """The alpha the scene then holds: split pixels their estimate, the others 1 on the near side, else 0."""
    est = (coc > 0).astype(np.float32).ravel()
    est[se.index] = se.alpha
    return est.reshape(coc.shape)


def check_contract(se: SoftEdges, image: np.ndarray, coc: np.ndarray, min_alpha: float = 0.02,
                   max_alpha: float = 0.9) -> None:
    h, w = coc.shape
    n = len(se)
    assert se.index.dtype == np.int64 and se.index.shape == (n,)
    for a, shape in ((se.alpha, (n,)), (se.foreground, (n, 3)), (se.background, (n, 3)), (se.near_coc, (n,)),
                     (se.far_coc, (n,))):
        assert a.dtype == np.float32 and a.shape == shape
        assert np.isfinite(a).all()
    assert (np.diff(se.index) > 0).all()
    assert n == 0 or (se.index.min() >= 0 and se.index.max() < h * w)
    assert ((se.alpha >= min_alpha) & (se.alpha <= max_alpha)).all()
    assert (se.near_coc > se.far_coc).all()
    # the split pixels' CoC are values of the map (the window's plateaus), not invented ones
    assert np.isin(se.near_coc, coc).all() and np.isin(se.far_coc, coc).all()
    photo = image.reshape(-1, image.shape[-1])[se.index][:, :3].astype(np.float64)
    a = se.alpha.astype(np.float64)[:, None]
    comp = a * se.foreground + (1.0 - a) * se.background
    scale = np.maximum(np.abs(photo), 1.0)
    np.testing.assert_allclose(comp / scale, photo / scale, rtol=0, atol=2e-6)
    # no negative light where the photo has none, and neither part brighter than its share of the pixel allows
    pos = photo >= 0
    assert (se.foreground[pos] >= 0).all() and (se.background[pos] >= 0).all()
    assert (se.foreground <= np.maximum(photo / a, 0) * (1 + 1e-5) + 1e-7).all()


def test_thin_strands_are_not_noise():
    """Dense one-pixel strands (diagonal ones too) have neighbours of their own depth along them."""
    coc = np.full((40, 40), -10.0, np.float32)
    for k in range(-40, 40, 3):
        coc[np.eye(40, k=k, dtype=bool)] = 10.0  # diagonal lines one pixel wide, two pixels apart
    assert isolated_share(coc, 1.0) == 0.0
    assert isolated_share(np.float32([[1.0]]), 1.0) == 0.0


def test_a_flat_map_or_a_smooth_slope_splits_nothing():
    photo, _, _, _, _ = two_plane()
    for coc in (np.zeros(photo.shape[:2], np.float32),
                np.linspace(-5, 5, photo.shape[0] * photo.shape[1], dtype=np.float32).reshape(photo.shape[:2])):
        se = split_mixed_pixels(photo, coc)
        assert len(se) == 0 and se.index.dtype == np.int64


@pytest.mark.parametrize("shape", [(1, 1), (1, 7), (7, 1), (2, 2)])
def test_tiny_images(shape):
    rng = np.random.default_rng(0)
    img = rng.uniform(0, 1, shape + (3,)).astype(np.float32)
    coc = rng.choice([-10.0, 10.0], shape).astype(np.float32)
    se = split_mixed_pixels(img, coc)
    check_contract(se, img, coc)


def test_two_plane_contract_and_only_pixels_at_the_edges_split():
    photo, coc, _alpha, _, _ = two_plane()
    se = split_mixed_pixels(photo, coc)
    assert len(se) > 0
    check_contract(se, photo, coc)
    # hard edges: the band is the depth-edge pixels (band_px 0); nothing else is touched
    assert depth_edges(coc, 1.0).ravel()[se.index].all()
    se1 = split_mixed_pixels(photo, coc, MattingRule(band_px=1))
    assert ndimage.binary_dilation(depth_edges(coc, 1.0), np.ones((3, 3), bool)).ravel()[se1.index].all()
    assert len(se1) >= len(se)
    # the near and far parts carry the two planes' CoC, not a mixed value
    assert set(np.unique(se.near_coc)) == {np.float32(K * 0.4)}
    assert set(np.unique(se.far_coc)) == {np.float32(-K * 0.3)}


@pytest.mark.parametrize("kind, bound", [("disc", 0.05), ("strands", 0.09)])
def test_alpha_accuracy_on_two_planes(kind, bound):
    """Alpha RMSE over the mixed pixels and their neighbours: well below one depth a pixel (the alpha >= 0.5 rule:
    0.14 disc, 0.19 strands) and below the bound (measured over seeds 0-2: disc 0.026-0.031, strands 0.057-0.059);
    F of the pixels mostly foreground within 0.05 (measured 0.013-0.033)."""
    for seed in range(3):
        photo, coc, alpha, fg, _bg = two_plane(seed=seed, kind=kind)
        se = split_mixed_pixels(photo, coc)
        ring = ndimage.binary_dilation((alpha > 0) & (alpha < 1), np.ones((3, 3), bool))
        before = np.sqrt((((coc > 0) - alpha)[ring] ** 2).mean())
        after = np.sqrt(((estimated_alpha(se, coc) - alpha)[ring] ** 2).mean())
        assert after < bound and after < 0.5 * before, (seed, before, after)
        # decontaminated colours: F of the pixels that hold most of the foreground is near the true F
        idx = se.index[alpha.ravel()[se.index] > 0.3]
        fg_err = np.abs(se.foreground[np.isin(se.index, idx)] - fg.reshape(-1, 3)[idx]).mean()
        assert fg_err < 0.05, fg_err


def test_noise_maps_split_nothing_and_all_edge_maps_stay_finite():
    rng = np.random.default_rng(3)
    img = rng.uniform(0, 1, (48, 40, 3)).astype(np.float32)
    noise = rng.uniform(-20, 20, (48, 40)).astype(np.float32)
    assert len(split_mixed_pixels(img, noise)) == 0
    assert isolated_share(noise, 1.0) > 0.5
    assert len(split_mixed_pixels(img, noise, MattingRule(max_isolated_share=1.0))) > 0  # the guard is what stopped it
    # a checkerboard of two depths is all edge (and diagonal strands, not noise): bounded work, a valid result
    checker = np.where((np.indices((48, 40)).sum(0) % 2) == 0, 10.0, -10.0).astype(np.float32)
    assert isolated_share(checker, 1.0) == 0.0
    se = split_mixed_pixels(img, checker)
    check_contract(se, img, checker)


def test_pixels_without_colour_contrast_are_left_alone():
    """A depth step with the same colour on both sides (e.g. an alpha channel rendered as grey over grey of the
    same value) says nothing about coverage: nothing is split."""
    img = np.full((32, 32, 3), 0.4, np.float32)
    coc = np.zeros((32, 32), np.float32)
    coc[:, 16:] = 12.0
    assert len(split_mixed_pixels(img, coc)) == 0


def test_grey_and_rgba_inputs_are_taken_as_rgb():
    photo, coc, _, _, _ = two_plane(n=40)
    grey = photo.mean(2)
    se_g = split_mixed_pixels(grey, coc)
    check_contract(se_g, np.repeat(grey[..., None], 3, 2), coc)
    rgba = np.concatenate([photo, np.ones(photo.shape[:2] + (1,), np.float32)], 2)
    se_a = split_mixed_pixels(rgba, coc)
    se = split_mixed_pixels(photo, coc)
    np.testing.assert_array_equal(se_a.index, se.index)
    np.testing.assert_array_equal(se_a.alpha, se.alpha)


def test_hdr_radiance_stays_finite_and_exact():
    photo, coc, _, _, _ = two_plane(n=40)
    for scale in (1e-6, 1e3, 1e30):
        img = photo * np.float32(scale)
        se = split_mixed_pixels(img, coc)
        assert len(se) > 0
        check_contract(se, img, coc)


def test_bad_input_is_refused():
    img = np.zeros((8, 8, 3), np.float32)
    with pytest.raises(InputError):
        split_mixed_pixels(img, np.zeros((8, 7), np.float32))
    with pytest.raises(InputError):
        split_mixed_pixels(np.zeros((8, 8, 2), np.float32), np.zeros((8, 8), np.float32))
    bad = np.zeros((8, 8), np.float32)
    bad[3, 4] = np.nan
    with pytest.raises(InputError):
        split_mixed_pixels(img, bad)


def test_finite_checked_inputs_split_alike():
    """The pipeline's finite_checked=True skips the NaN/Inf scans only: the same split on finite input."""
    photo, coc, _, _, _ = two_plane(n=40)
    a, b = split_mixed_pixels(photo, coc), split_mixed_pixels(photo, coc, finite_checked=True)
    assert len(a) > 0
    for f in ("index", "alpha", "foreground", "background", "near_coc", "far_coc"):
        np.testing.assert_array_equal(getattr(a, f), getattr(b, f))


def test_a_soft_map_widens_the_band():
    photo, coc, alpha, _, _ = two_plane(seed=1)
    soft = ndimage.gaussian_filter(coc, 1.5)
    assert ramp_width(coc, 1.0, 6) == 0
    assert ramp_width(soft, 1.0, 6) >= 2
    se = split_mixed_pixels(photo, soft)
    check_contract(se, photo, soft)
    ring = ndimage.binary_dilation((alpha > 0) & (alpha < 1), np.ones((3, 3), bool))
    est = soft.ravel() > 0
    est = est.astype(np.float32)
    est[se.index] = se.alpha
    before = np.sqrt((((soft > 0) - alpha)[ring] ** 2).mean())
    after = np.sqrt(((est.reshape(alpha.shape) - alpha)[ring] ** 2).mean())
    assert after < before


def test_window_offsets_are_nearest_first_and_symmetric():
    offs, dist = window_offsets(7)
    assert (np.diff(dist) >= 0).all() and dist[0] == 0
    assert {tuple(o) for o in offs} == {tuple(-o) for o in offs}
    assert (dist <= 7.5).all()


@given(st.integers(2, 20), st.integers(2, 20), st.integers(0, 2 ** 31 - 1), st.sampled_from([0.5, 3.0, 40.0]))
def test_invariants_on_random_layered_input(h, w, seed, jump):
    """Random blocky depth maps (a few depths) and random colours: every split pixel satisfies the contract."""
    rng = np.random.default_rng(seed)
    img = rng.uniform(0, 2, (h, w, 3)).astype(np.float32)
    img[rng.uniform(size=(h, w)) < 0.1] = 0.0
    depths = rng.uniform(-jump, jump, 3).astype(np.float32)
    coc = depths[rng.integers(0, 3, (max(1, h // 3), max(1, w // 3)))].repeat(3, 0).repeat(3, 1)[:h, :w]
    coc = np.pad(coc, ((0, h - coc.shape[0]), (0, w - coc.shape[1])), mode="edge")
    se = split_mixed_pixels(img, coc)
    check_contract(se, img, coc)


def test_ramp_width_matches_the_reference():
    rng = np.random.default_rng(5)
    for k in range(6):
        coc = rng.choice([-8.0, 0.0, 9.0], (5, 7)).repeat(3, 0).repeat(3, 1).astype(np.float32)
        if k % 2:
            coc = ndimage.gaussian_filter(coc, 0.5 + k * 0.3)
        for cap in (2, 6):
            assert ramp_width(coc, 1.0, cap) == ramp_width_ref(coc, 1.0, cap)
    assert ramp_width(np.zeros((1, 1), np.float32), 1.0, 6) == 0


@pytest.mark.parametrize("parts", [1, 3])
@pytest.mark.parametrize("shape", [(1, 1), (1, 6), (6, 1), (2, 2), (19, 23)])
def test_shared_steps_give_the_depth_edges_and_ramp_of_the_map(shape, parts, monkeypatch):
    """The edge estimate computes the steps once (map_steps) for both: the edges of a plain loop over the pairs,
    and the reference's ramp width; the same with the rows in ``parts`` parts on as many threads."""
    from bokehray import edge_estimate
    from bokehray.edge_estimate import edges_of_steps, map_steps, ramp_of_steps

    monkeypatch.setattr(edge_estimate, "PIXELS_PER_THREAD", 1 if parts > 1 else 1 << 30)
    monkeypatch.setattr(edge_estimate.os, "cpu_count", lambda: parts)
    rng = np.random.default_rng(shape[0] * 31 + shape[1])
    coc = ndimage.gaussian_filter(rng.choice([-8.0, 0.0, 9.0], shape), 0.7).astype(np.float32)
    want = np.zeros(shape, bool)
    for y in range(shape[0]):
        for x in range(shape[1]):
            for y2, x2 in ((y + 1, x), (y, x + 1)):
                if y2 < shape[0] and x2 < shape[1] and abs(float(coc[y, x]) - float(coc[y2, x2])) > 1.0:
                    want[y, x] = want[y2, x2] = True
    steps = map_steps(coc, 1.0)
    np.testing.assert_array_equal(edges_of_steps(steps), want)
    np.testing.assert_array_equal(depth_edges(coc, 1.0), want)
    assert ramp_of_steps(coc, steps, 6) == ramp_width(coc, 1.0, 6) == ramp_width_ref(coc, 1.0, 6)


@given(st.integers(0, 70), st.integers(0, 9), st.integers(1, 20), st.integers(1, 5), st.integers(1, 200))
def test_row_parts_tile_the_rows(h, w, align, threads, per_thread):
    """Consecutive parts from row 0 to the last, every inner cut on the alignment, at most one a thread."""
    from unittest import mock

    from bokehray import edge_estimate

    with mock.patch.object(edge_estimate, "PIXELS_PER_THREAD", per_thread):
        parts = edge_estimate.row_parts(h, w, align=align, threads=threads)
        got = edge_estimate.in_row_parts(h, w, lambda a, b: (a, b), align=align, threads=threads)
    assert got == parts
    assert 1 <= len(parts) <= threads and parts[0][0] == 0 and parts[-1][1] == h
    assert all(a < b for a, b in parts) or parts == [(0, 0)]
    assert all(p[1] == q[0] and p[1] % align == 0 for p, q in itertools.pairwise(parts))


@pytest.mark.parametrize("soft", [False, True])
def test_band_kernel_matches_the_reference(device, soft):
    """The Warp kernel against the float64 loop of tests/reference/matting_ref.py, pixel by pixel."""
    from reference.matting_ref import band_pixel_ref, gaussian_weights

    from bokehray.edge_estimate import launch_band_kernel

    photo, coc, _, _, _ = two_plane(n=28, seed=4, kind="strands" if soft else "disc")
    if soft:
        coc = ndimage.gaussian_filter(coc, 1.0)
    img = photo / np.float32(photo.max())
    edges = depth_edges(coc, 1.0)
    band = ndimage.binary_dilation(edges, np.ones((3, 3), bool))
    by, bx = np.nonzero(band)
    radius, params = 5, (1.0, 0.3, 0.03, 8.0)
    rule = MattingRule(jump_px=params[0], unknown_weight=params[1], ridge=params[2], purity=params[3])
    got = launch_band_kernel(img, coc, band, by, bx, radius, rule, device, 2)
    offs, dist = window_offsets(radius)
    g = gaussian_weights(dist, radius)
    flags = got[7]
    for i in range(by.size):
        a, F, B, vF, vB, near, far, ok, own = band_pixel_ref(img, coc, band, by[i], bx[i], offs, g, *params)
        assert bool(flags[i] & 1) == ok and bool(flags[i] & 2) == own
        if not ok:
            continue
        assert abs(got[0][i] - a) < 2e-4
        np.testing.assert_allclose(got[1][i], F, atol=2e-5)
        np.testing.assert_allclose(got[2][i], B, atol=2e-5)
        np.testing.assert_allclose(got[3][i], vF, atol=2e-5)
        np.testing.assert_allclose(got[4][i], vB, atol=2e-5)
        assert got[5][i] == np.float32(near) and got[6][i] == np.float32(far)


def test_threads_do_not_change_the_result(monkeypatch):
    import bokehray.edge_estimate as edge_estimate

    monkeypatch.setattr(edge_estimate, "PIXELS_PER_THREAD", 16)  # a small scene in several launches
    photo, coc, _, _, _ = two_plane(n=96, seed=2, kind="strands")
    one = split_mixed_pixels(photo, coc, threads=1)
    two = split_mixed_pixels(photo, coc, threads=3)
    for f in ("index", "alpha", "foreground", "background", "near_coc", "far_coc"):
        np.testing.assert_array_equal(getattr(one, f), getattr(two, f))


def test_a_pure_corner_over_noise_stays_whole():
    """The corners of a flat square over per-pixel noise: the model's window is mostly noise, but the pixel's
    colour is the square's: nothing inside the square is split (found by test_render_api's no-halo test)."""
    rng = np.random.default_rng(0)
    image = rng.random((80, 80, 3)).astype(np.float32)
    coc = np.full((80, 80), -12.0, np.float32)
    coc[20:60, 20:60] = 0.0
    image[20:60, 20:60] = [0.2, 0.9, 0.1]
    se = split_mixed_pixels(image, coc)
    check_contract(se, image, coc)
    y, x = np.divmod(se.index, 80)
    assert not ((y >= 20) & (y < 60) & (x >= 20) & (x < 60)).any()


def test_a_wire_over_a_flat_sky_gets_its_coverage():
    """A grey 2.5 px wire at a slant over a flat dark sky (the demo's wire): every mixed pixel the map's edge
    touches is split with its true coverage (the linear model's ridge bias alone left errors of 0.05, and pixels
    below 0.1 stayed whole: a dotted sharp trace once the wire blurs)."""
    n = 64
    yy, xx = np.mgrid[0:n, 0:n] + 0.5
    slope = 0.17
    dist = np.abs(yy - (0.5 * n + slope * xx)) / np.hypot(1.0, slope)
    alpha = np.clip(1.25 + 0.5 - dist, 0.0, 1.0).astype(np.float32)
    wire, sky = np.array([0.55, 0.55, 0.58], np.float32), np.array([0.018, 0.03, 0.065], np.float32)
    photo = (alpha[..., None] * wire + (1 - alpha[..., None]) * sky).astype(np.float32)
    coc = np.where(alpha >= 0.5, 35.0, -1.0).astype(np.float32)
    se = split_mixed_pixels(photo, coc)
    check_contract(se, photo, coc)
    truth = alpha.ravel()[se.index]
    err = np.abs(se.alpha - truth)
    assert err.max() < 0.035 and np.sqrt((err ** 2).mean()) < 0.02
    edges = depth_edges(coc, 1.0).ravel()
    faint = np.flatnonzero(edges & (alpha.ravel() >= 0.03) & (alpha.ravel() < 0.1))
    assert faint.size and np.isin(faint, se.index).all()


def _spoke_over_a_lamp(n: int = 48, width: float = 0.7, colour: float = 0.45):
    """A strand ``width`` px wide (grey ``colour``) across a small lamp (radiance 6, radius 6 px) over a dark sky,
    its map by the alpha >= 0.5 rule (strand at CoC 0, in focus; the sky and the lamp at -32). Returns the photo,
    the CoC map and the strand's coverage."""
    from bokehray.app.demo import stroke

    yy, xx = np.mgrid[0:n, 0:n] + 0.5
    sky = np.full((n, n, 3), 0.01, np.float32)
    lamp = np.clip(6.5 - np.hypot(yy - n / 2, xx - n / 2), 0, 1)[..., None]
    bg = (sky * (1 - lamp) + 6.0 * lamp).astype(np.float32)
    sl, a = stroke(np.array([[-2.0, n / 2 - 5.0], [n + 2.0, n / 2 + 3.0]]), np.full(2, width), n, n)
    alpha = np.zeros((n, n), np.float32)
    alpha[sl] = a
    photo = (alpha[..., None] * np.float32(colour) + (1 - alpha[..., None]) * bg).astype(np.float32)
    coc = np.where(alpha >= 0.5, 0.0, -32.0).astype(np.float32)
    return photo, coc, alpha, lamp[..., 0]


def test_band_kernel_matches_the_reference_with_a_light_behind_a_strand():
    """The kernel's reading of a light behind the near side against the float64 loop (the light's branch runs)."""
    from reference.matting_ref import band_pixel_ref, gaussian_weights

    from bokehray.edge_estimate import launch_band_kernel

    photo, coc, _, _ = _spoke_over_a_lamp()
    scale = float(photo.max())
    img = photo / np.float32(scale)
    edges = depth_edges(coc, 1.0)
    by, bx = np.nonzero(edges)
    rule = MattingRule()
    radius = 4
    got = launch_band_kernel(img, coc, edges, by, bx, radius, rule, "cpu", 2, scale=scale)
    offs, dist = window_offsets(radius)
    g = gaussian_weights(dist, radius)
    moved = 0
    for i in range(by.size):
        a, F, B, vF, _, _, _, ok, _ = band_pixel_ref(
            img, coc, edges, by[i], bx[i], offs, g, rule.jump_px, rule.unknown_weight, rule.ridge, rule.purity,
            rule.light_level / scale, rule.light_ratio, rule.light_reach, rule.light_thin, rule.light_share)
        plain = band_pixel_ref(img, coc, edges, by[i], bx[i], offs, g, rule.jump_px, rule.unknown_weight,
                               rule.ridge, rule.purity)
        assert bool(got[7][i] & 1) == ok
        if not ok:
            continue
        moved += int(np.abs(plain[1] - F).max() > 1e-3)
        assert abs(got[0][i] - a) < 2e-4
        np.testing.assert_allclose(got[1][i], F, atol=2e-5)
        np.testing.assert_allclose(got[2][i], B, atol=2e-5)
        np.testing.assert_allclose(got[3][i], vF, atol=2e-5)
    assert moved > 5  # the light's branch ran, and changed F


@pytest.mark.parametrize("width", [0.5, 0.6, 0.7])
def test_a_strand_across_a_light_is_not_kept_light_bright(width):
    """The regression (the dev set's lamp spoke, 0.7 px): the window's near samples of a strand across a lamp all
    hold the lamp's light, so F came out lamp-bright and the pixels stayed whole, a sharp dash of the lamp's light.
    The near part the split leaves in focus, ``alpha F``, must be near the strand's share ``coverage x colour``, not
    the lamp's (a wider strand lets too little of the light through for the rule: docs/soft-scene.md, Limits)."""
    photo, coc, alpha, lamp = _spoke_over_a_lamp(width=width)
    over = (lamp > 0.99) & (alpha > 0.3) & (coc == 0.0)  # the strand's map pixels over the lamp's core
    assert over.sum() >= 4
    truth = alpha[over] * 0.45

    def near_share(rule):
        soft = split_mixed_pixels(photo, coc, rule)
        share = photo[..., 1].copy()  # a pixel left whole is in focus all of it
        share.ravel()[soft.index] = soft.alpha * soft.foreground[:, 1]
        return share[over]

    before = near_share(MattingRule(max_ramp_px=0, light_reach=0))
    after = near_share(MattingRule(max_ramp_px=0))
    assert np.abs(before - truth).max() > 1.0  # lamp-bright
    assert np.abs(after - truth).max() < 0.2


def test_a_strand_across_a_light_has_its_own_colour():
    """The cross-sections (step 4a) over a grid of straight strands 0.4 - 1 px wide, slopes up to 40 degrees and
    random colours, across a lamp over a dark sky, with a map by the alpha >= 0.5 rule: every one of their mixed
    pixels at a depth edge over the lamp's core (coverage 0.3 - 0.8: a linear ramp's coverage is not exactly an area,
    and from 0.8 up its estimate may pass max_alpha, where a pixel stays whole by design) is split, and its F is the
    strand's colour (before: its colour times its coverage, or the lamp's light, 0.15 - 1.7 off): within 0.01 at
    the median case, 0.06 at nine in ten. A few phases of the narrowest strands are off by up to 0.17 (a
    hypothesis search of the same domain found them: an invariant at 0.06 did not hold). A strand the map does not
    hold, no pixel of it covered by half, is not split and not drawn here."""
    n = 64
    yy, xx = np.mgrid[0:n, 0:n] + 0.5
    lamp = np.clip(6.5 - np.hypot(yy - n / 2, xx - n / 2 - 0.3), 0, 1)[..., None]
    bg = np.array([0.02, 0.03, 0.06]) * (1 - lamp) + 6.0 * np.array([1.0, 0.9, 0.75]) * lamp
    rng = np.random.default_rng(1)
    errors = []
    for width, slope in itertools.product(np.linspace(0.4, 1.0, 7), np.linspace(-0.8, 0.8, 9)):
        f = rng.uniform(0.05, 0.8, 3)
        a = np.clip(width / 2 + 0.5 - np.abs((yy - n / 2 - 0.4) - (xx - n / 2) * slope) / np.hypot(1.0, slope), 0, 1)
        photo = (a[..., None] * f + (1 - a[..., None]) * bg).astype(np.float32)
        coc = np.where(a >= 0.5, 0.0, -32.0).astype(np.float32)
        over = np.flatnonzero((depth_edges(coc, 1.0) & (lamp[..., 0] > 0.99) & (a > 0.3) & (a < 0.8)).ravel())
        if (a >= 0.5).sum() < n // 2 or over.size < 3:
            continue  # the map does not hold the strand along its length, or no pixel of it is mixed over the lamp
        soft = split_mixed_pixels(photo, coc)
        k = np.searchsorted(soft.index, over).clip(0, len(soft) - 1)
        assert (soft.index[k] == over).all(), (width, slope)
        errors.append(np.abs(soft.foreground[k] - f).max())
    assert len(errors) >= 40
    assert np.median(errors) < 0.01 and np.quantile(errors, 0.9) < 0.06 and max(errors) < 0.25


def _two_strands_over_a_lamp(gap: float, slope: float, n: int = 64):
    """A 4 px opaque strand (orange, CoC 10) and, ``gap`` px below it, a 0.7 px one (blue, CoC 20, in front), both
    falling ``slope`` px across the frame, over a lamp (radiance 6, radius 9.5 px) on a dark sky; the map by the
    alpha >= 0.5 rule. Returns the photo, the CoC map, the wide strand's coverage, the lamp and its colour."""
    from bokehray.app.demo import stroke

    yy, xx = np.mgrid[0:n, 0:n] + 0.5
    lamp = np.clip(9.5 - np.hypot(yy - n / 2, xx - n / 2), 0, 1)
    photo = np.array([0.02, 0.03, 0.06]) * (1 - lamp[..., None]) + 6.0 * lamp[..., None]
    coc = np.full((n, n), -32.0)
    wide = np.array([0.6, 0.35, 0.1])
    cover = {}
    for width, colour, depth, off in ((4.0, wide, 10.0, 0.0), (0.7, np.array([0.1, 0.3, 0.6]), 20.0, gap)):
        sl, a = stroke(np.array([[-2.0, n / 2 - 2.0 + off], [n + 2.0, n / 2 - 2.0 + off + slope]]), np.full(2, width),
                       n, n)
        cover[depth] = np.zeros((n, n))
        cover[depth][sl] = a
        photo = cover[depth][..., None] * colour + (1 - cover[depth][..., None]) * photo
        coc = np.where(cover[depth] >= 0.5, depth, coc)
    return photo.astype(np.float32), coc.astype(np.float32), cover[10.0], lamp, wide


@pytest.mark.parametrize("gap, slope", [(4.0, 3.0), (4.0, 6.0), (5.0, 3.0), (5.0, 6.0), (6.0, 3.0)])
def test_a_wide_strand_beside_a_thin_one_keeps_its_own_colour(gap, slope):
    """The regression (the demo's star lamp focused far: a 5 px blade beside a 1.35 px one at another depth): the
    thin strand's cross-sections measure its colour, and the wide strand's rim pixels over the lamp took it (their F
    0.56 - 1.1 off, the split's far part too bright). A cross-section holds a strand up to 3 px across: a pixel
    whose strand is wider keeps its window's F, the wide strand's own colour."""
    photo, coc, wide, lamp, colour = _two_strands_over_a_lamp(gap, slope)
    rim = np.flatnonzero(((lamp > 0.99) & (wide > 0.05) & (wide < 0.5)).ravel())
    assert rim.size >= 10
    soft = split_mixed_pixels(photo, coc, MattingRule(max_ramp_px=0))
    k = np.searchsorted(soft.index, rim).clip(0, len(soft) - 1)
    split = soft.index[k] == rim
    assert split.sum() >= 8
    assert np.abs(soft.foreground[k[split]] - colour).max() < 0.1


def _spoke_over_a_soft_lamp(width: float, off: float, n: int = 48):
    """A ``width`` px grey (0.45) strand across a lamp (radiance 6) whose edge falls off over 3 px, ``off`` px below the
    middle: it crosses the lamp's rim where the rim is dim for being the light's edge. Returns the photo, the CoC
    map, the strand's coverage and the lamp."""
    from bokehray.app.demo import stroke

    yy, xx = np.mgrid[0:n, 0:n] + 0.5
    lamp = np.clip((8.0 - np.hypot(yy - n / 2, xx - n / 2)) / 3.0, 0, 1)
    sl, a = stroke(np.array([[-2.0, n / 2 - 5.0 + off], [n + 2.0, n / 2 + 3.0 + off]]), np.full(2, width), n, n)
    alpha = np.zeros((n, n))
    alpha[sl] = a
    photo = alpha[..., None] * 0.45 + (1 - alpha[..., None]) * (0.01 * (1 - lamp) + 6.0 * lamp)[..., None]
    return (np.repeat(photo, 3, 2).astype(np.float32), np.where(alpha >= 0.5, 0.0, -32.0).astype(np.float32),
            alpha, lamp)


@pytest.mark.parametrize("off", [-4.0, -2.0, 0.0, 3.0, 5.0])
@pytest.mark.parametrize("width", [0.5, 0.7])
def test_a_light_s_rim_beside_a_strand_is_not_read_as_strand(width, off):
    """The regression (``d3`` focused on the ring at K = 8, row 202, columns 161 and 171: 0.45 / 0.58 against the
    path tracer's 1.51 / 1.47): a pixel of a light's rim beside a thin strand is dim for being the light's edge, and
    against the light's B it read as mostly strand (split at alpha 0.5 - 0.9 where the strand covers none of it, a
    grey dot on the bokeh ball). Its cover is more than the strand's measured width leaves it after the strand's
    pixels beside it: it stays the light's. The strand's own pixels over the lamp keep its colour."""
    photo, coc, alpha, lamp = _spoke_over_a_soft_lamp(width, off)
    n = coc.shape[0]
    near = coc == 0.0
    beside = np.zeros_like(near)
    for k in (-2, -1, 1, 2):
        beside |= np.roll(near, k, axis=0)
    rim = np.flatnonzero(((lamp > 0.02) & (lamp < 0.9) & (alpha < 0.05) & beside).ravel())
    over = np.flatnonzero(((lamp > 0.99) & (alpha > 0.3) & near).ravel())
    assert rim.size >= 15 and over.size >= 3
    soft = split_mixed_pixels(photo, coc, MattingRule(max_ramp_px=0))
    a = np.zeros(n * n)
    a[soft.index] = soft.alpha
    f = np.zeros((n * n, 3))
    f[soft.index] = soft.foreground
    assert a[rim].max() < 0.45
    assert np.abs(f[over] - 0.45).max() < 0.08


@pytest.mark.parametrize("kind", ["disc", "strands"])
def test_the_edge_band_in_row_parts_is_the_band_in_one(kind, monkeypatch):
    """The band's pixels, the scaled box and the scale found on row parts (three threads) are those of one pass."""
    from bokehray import edge_estimate
    from bokehray.edge_estimate import edge_band

    photo, coc, _, _, _ = two_plane(n=40, seed=7, kind=kind)
    img, s = np.ascontiguousarray(photo, np.float32), np.ascontiguousarray(coc, np.float32)
    one = edge_band(img, s, MattingRule())
    monkeypatch.setattr(edge_estimate, "PIXELS_PER_THREAD", 1)
    monkeypatch.setattr(edge_estimate.os, "cpu_count", lambda: 3)
    assert edge_estimate.row_parts(*s.shape) != [(0, s.shape[0])]
    three = edge_band(img, s, MattingRule())
    assert one is not None and one.size > 0 and (one.box, one.scale, one.radius) == (three.box, three.scale,
                                                                                      three.radius)
    for name in ("by", "bx", "image", "coc", "band"):
        a, b = getattr(one, name), getattr(three, name)
        assert a.dtype == b.dtype
        np.testing.assert_array_equal(a, b)
