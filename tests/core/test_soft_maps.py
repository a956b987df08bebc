"""Soft depth maps: a ramp between two depths is rendered as an edge (bokehray.ramps, docs/soft-scene.md)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import ndimage

import bokehray as br
from bokehray.ramps import RampRule, snap_ramps
from tests.reference.ramps_ref import snap_ramps_ref
from tests.reference.two_planes_ref import TwoPlanes


def _soft_disc(n: int, sigma: float, k: float, focus: float, seed: int):
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:n, 0:n] + 0.5
    r = rng.uniform(0.2, 0.35) * n
    hard = ((yy - n / 2) ** 2 + (xx - n / 2) ** 2 <= r * r).astype(np.float32)
    fg, bg = rng.uniform(0.05, 1.0, 3), rng.uniform(0.05, 1.0, 3)
    alpha = ndimage.gaussian_filter(hard, 0.7)[..., None]
    img = (alpha * fg + (1 - alpha) * bg + rng.normal(0, 0.02, (n, n, 3))).clip(0, None).astype(np.float32)
    soft = ndimage.gaussian_filter(hard, sigma, mode="nearest")
    return img, (k * (soft - focus)).astype(np.float32)


@settings(max_examples=12, deadline=None)
@given(sigma=st.floats(0.8, 4.0), k=st.floats(4.0, 40.0), focus=st.floats(0.0, 1.0), seed=st.integers(0, 2**16))
def test_the_kernel_matches_the_float64_oracle(sigma, k, focus, seed):
    img, s = _soft_disc(40, sigma, k, focus, seed)
    rule = RampRule()
    got, n = snap_ramps(img, s, rule)
    want, moved = snap_ramps_ref(img, s, rule)
    got_moved = np.abs(got - s) > 0
    # the oracle's float64 gradient and the kernel's float32 one can fall either side of a threshold at a pixel
    # or two; every other pixel agrees, and where both snap, on the same value
    assert (got_moved != moved).mean() <= 0.01
    both = got_moved & moved
    np.testing.assert_allclose(got[both], want[both], rtol=0, atol=1e-4)
    assert n == int(got_moved.sum())


@settings(max_examples=20, deadline=None)
@given(h=st.integers(3, 40), w=st.integers(3, 40), scale=st.floats(0.05, 3.0), seed=st.integers(0, 2**16))
def test_the_plateau_pass_is_the_sobel_gradient_at_most_grad_min(h, w, scale, seed):
    """The plateau pass (three rows slid along each row, a thread a row) against the float64 Sobel / 8 with clamped
    borders: the same plateaus, but where the gradient lies within 1e-5 of ``grad_min`` (float32 rounding)."""
    import bokehray_kernels.ramps as bk_ramps
    import warp as wp

    s = (np.random.default_rng(seed).normal(0, scale, (h, w))).astype(np.float32)
    p = np.pad(s.astype(np.float64), 1, mode="edge")
    gy = (p[2:, :-2] + 2 * p[2:, 1:-1] + p[2:, 2:]) - (p[:-2, :-2] + 2 * p[:-2, 1:-1] + p[:-2, 2:])
    gx = (p[:-2, 2:] + 2 * p[1:-1, 2:] + p[2:, 2:]) - (p[:-2, :-2] + 2 * p[1:-1, :-2] + p[2:, :-2])
    g = np.hypot(gy, gx) / 8
    grad_min = RampRule().grad_min
    flat = wp.empty((h, w), dtype=wp.uint8, device="cpu")
    wp.launch(bk_ramps.ramp_plateau_kernel, dim=h, inputs=[wp.array(s, dtype=float, device="cpu"), 0, grad_min],
              outputs=[flat], device="cpu")
    sure = np.abs(g - grad_min) > 1e-5
    np.testing.assert_array_equal(flat.numpy()[sure].astype(bool), (g <= grad_min)[sure])


@pytest.mark.parametrize("sigma, k, focus, seed", [(3.0, 30.0, 0.3, 1), (5.0, 24.0, 0.7, 2)])
def test_walks_inside_the_frame_match_the_oracle(sigma, k, focus, seed):
    """A frame wide enough that most walks stay inside it (they round without clamping): the oracle's map."""
    img, s = _soft_disc(120, sigma, k, focus, seed)
    rule = RampRule()
    got, n = snap_ramps(img, s, rule)
    want, moved = snap_ramps_ref(img, s, rule)
    got_moved = np.abs(got - s) > 0
    assert moved.sum() > 100 and n == int(got_moved.sum())
    assert (got_moved != moved).mean() <= 0.01
    both = got_moved & moved
    np.testing.assert_allclose(got[both], want[both], rtol=0, atol=1e-4)


@settings(max_examples=25, deadline=None)
@given(levels=st.lists(st.floats(-30.0, 30.0), min_size=2, max_size=4), seed=st.integers(0, 2**16))
def test_a_hard_map_is_left_exactly_as_it_is(levels, seed):
    rng = np.random.default_rng(seed)
    labels = ndimage.zoom(rng.integers(0, len(levels), (6, 6)), 8, order=0)
    s = np.asarray(levels, np.float32)[labels]
    img = rng.uniform(0, 1, s.shape + (3,)).astype(np.float32)
    out, n = snap_ramps(img, s)
    assert n == 0 and out is s


@settings(max_examples=25, deadline=None)
@given(gy=st.floats(-3.0, 3.0), gx=st.floats(-3.0, 3.0), c=st.floats(-20.0, 20.0), seed=st.integers(0, 2**16))
def test_a_tilted_plane_stays_a_slope(gy, gx, c, seed):
    """A slope runs on beyond the walk: however steep, no pixel of it is snapped."""
    yy, xx = np.mgrid[0:96, 0:96].astype(np.float32)
    s = (c + gy * (yy - 48) + gx * (xx - 48)).astype(np.float32)
    img = np.random.default_rng(seed).uniform(0, 1, (96, 96, 3)).astype(np.float32)
    _, n = snap_ramps(img, s)
    assert n == 0


@settings(max_examples=12, deadline=None)
@given(sigma=st.floats(1.0, 6.0), k=st.floats(8.0, 48.0), focus=st.floats(0.0, 1.0), seed=st.integers(0, 2**16))
def test_snapped_pixels_take_a_plateau_s_value(sigma, k, focus, seed):
    """Snapping copies values of the map: no new depth, nothing beyond the map's range, and a ramp's middle is
    emptied (every pixel ends near one of the two plateaus)."""
    img, s = _soft_disc(64, sigma, k, focus, seed)
    out, n = snap_ramps(img, s)
    moved = out != s
    assert n == int(moved.sum()) > 0
    assert np.isin(out[moved], s).all()
    mid = np.abs(out - k * (0.5 - focus)) < 0.1 * k  # the ramp's middle, within 10 % of the range
    assert mid.sum() <= (np.abs(s - k * (0.5 - focus)) < 0.1 * k).sum() * 0.2


@settings(max_examples=12, deadline=None)
@given(sigma=st.floats(3.0, 8.0), k=st.floats(24.0, 60.0), seed=st.integers(0, 2**16))
def test_a_wide_ramp_leaves_no_step_inside_a_plateau(sigma, k, seed):
    """A Gaussian ramp's tails (steps below 2 % of its range a pixel, yet steeper than a plateau) go with the ramp:
    across the edge the snapped map has one jump, and no step of more than three times a plateau's gradient on either
    side (a tail kept beside its snapped neighbours was a step of a tenth of the range inside the subject: a torn
    seam). Up to a blur of 8 px, the longest docs/soft-scene.md promises: a steep ramp of 10 px (k = 51) is longer
    than ``max_walk`` and is read in part, a step of 1 px where the read part ends."""
    n = int(12 * sigma) + 16
    rng = np.random.default_rng(seed)
    x = np.arange(n, dtype=np.float32) + 0.5
    hard = (x < n / 2).astype(np.float32)
    soft = ndimage.gaussian_filter1d(hard, sigma, mode="nearest")
    s = np.repeat((k * (soft - 1.0))[None, :], 24, axis=0).astype(np.float32)  # the near side in focus
    fg, bg = rng.uniform(0.05, 1.0, 3), rng.uniform(0.05, 1.0, 3)
    img = np.where(hard[None, :, None] > 0, fg, bg).repeat(24, axis=0).astype(np.float32)
    out, _ = snap_ramps(img, s)
    steps = np.sort(np.abs(np.diff(out[12])))[::-1]
    assert steps[0] >= 0.8 * k and steps[1] <= 3 * RampRule().grad_min


def _band_psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> float:
    def srgb(x):
        x = np.clip(x, 0.0, 1.0)
        return np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)

    return float(10 * np.log10(1.0 / ((srgb(a) - srgb(b)) ** 2)[mask].mean()))


@pytest.fixture(scope="module")
def two_planes():
    sc = TwoPlanes()
    return sc, sc.photo().astype(np.float32), sc.hard_map().astype(np.float32)


@pytest.mark.parametrize("focus", [0.15, 0.5, 0.85])
def test_a_soft_map_of_two_planes_renders_within_1_5_db_of_the_hard_map(two_planes, focus):
    """The analytic seam check: a textured disc at disparity 1 over a textured plane at 0, the hard map blurred by
    a Gaussian of 4 px, K = 24. In the band within R + 4 px of the rim, against the exact float64 render, the soft
    map scores within 1.5 dB of the hard map; read as surfaces (soft_maps=False) it does not."""
    sc, photo, hard = two_planes
    k = 24.0
    ref = sc.bokeh(k, focus)
    yy, xx = np.mgrid[0 : sc.n, 0 : sc.n] + 0.5
    band = np.abs(np.hypot(yy - sc.c, xx - sc.c) - sc.radius) <= k * max(focus, 1 - focus) + 4
    soft = ndimage.gaussian_filter(hard, 4.0, mode="nearest").astype(np.float32)
    blur = br.BlurParams(k, focus)
    p_hard = _band_psnr(br.render(photo, hard, blur), ref, band)
    p_soft = _band_psnr(br.render(photo, soft, blur), ref, band)
    p_surface = _band_psnr(br.render(photo, soft, blur, layers=br.LayerOptions(soft_maps=False)), ref, band)
    assert p_soft >= p_hard - 1.5, (p_hard, p_soft)
    assert p_surface < p_soft - 1.0, (p_surface, p_soft)


def test_the_render_s_stages_sum_to_its_total():
    """Every stage of a render is on its clock: the checks, the soft maps, the edges, the level's own stages and
    the output checks are laps of one clock (a consistency check, no bound on the time)."""
    img, s = _soft_disc(64, 3.0, 24.0, 0.5, 3)
    d = (s / 24.0 + 0.5).clip(0, 1).astype(np.float32)
    _, stats = br.render_with_stats(img, d, br.BlurParams(24.0, 0.5))
    st = stats.stage_seconds
    assert {"checks", "soft maps", "strands", "edges", "plan", "layers", "output", "total"} <= set(st)
    assert sum(v for k, v in st.items() if k != "total") == pytest.approx(st["total"], rel=0.02, abs=0.002)


class _Stop(Exception):
    pass


def test_a_render_stops_in_its_scene_step_when_its_callback_says_so():
    """The soft maps, the edge estimate and the planning call ``progress(0, 1)`` between their parts: a callback
    that raises there stops the render before any layer is rendered (the page's superseded previews, a stopping
    server's export)."""
    img, s = _soft_disc(96, 3.0, 24.0, 0.5, 5)
    d = (s / 24.0 + 0.5).clip(0, 1).astype(np.float32)
    calls = []

    def stop(done, total):
        calls.append((done, total))
        raise _Stop

    with pytest.raises(_Stop):
        br.render(img, d, br.BlurParams(24.0, 0.5), progress=stop)
    assert calls == [(0, 1)]


@settings(max_examples=20, deadline=None)
@given(n=st.integers(0, 700_000), threads=st.integers(1, 3), item_px=st.sampled_from([1, 256]))
def test_in_parts_with_checks_covers_the_items_in_order(n, threads, item_px):
    """Parts of at least PIXELS_PER_THREAD pixels a thread (an item ``item_px`` pixels: the strands' tiles), at most
    CHECK_ITEMS items a part, in order, one check a round."""
    from bokehray import edge_estimate as ee

    checks = []
    spans = ee.in_parts(n, lambda a, b: (a, b), threads=threads, check=lambda: checks.append(1), item_px=item_px)
    assert spans[0][0] == 0 and spans[-1][1] == n
    assert all(spans[i][1] == spans[i + 1][0] for i in range(len(spans) - 1))
    assert all(b - a <= ee.CHECK_ITEMS for a, b in spans)
    assert len(checks) == -(-len(spans) // min(threads, max(1, -(-n * item_px // ee.PIXELS_PER_THREAD))))
    if n and item_px > 1 and threads > 1 and n * item_px >= 2 * ee.PIXELS_PER_THREAD:
        assert len(spans) >= 2  # a few hundred tiles are worth both cores


def test_the_snap_in_parts_is_the_snap_whole(monkeypatch):
    """The snap kernel runs the candidates in parts (the cores, the checks' rounds), each writing its results at its
    own offset: the same map as one part."""
    from bokehray import edge_estimate as ee

    img, s = _soft_disc(48, 2.5, 24.0, 0.4, 7)
    whole, n = snap_ramps(img, s, threads=1)
    assert n > 0
    monkeypatch.setattr(ee, "PIXELS_PER_THREAD", 16)
    monkeypatch.setattr(ee, "CHECK_ITEMS", 37)
    checks = []
    parts, m = snap_ramps(img, s, threads=3, check=lambda: checks.append(1))
    assert len(checks) > 1
    assert m == n
    np.testing.assert_array_equal(parts, whole)


def test_the_split_in_chunks_is_the_split_whole(monkeypatch):
    """The matting works a chunk of band pixels at a time (bounded temporaries): the same split pixels, the same
    values, whatever the chunk."""
    from bokehray import matting

    img, s = _soft_disc(128, 0.0 + 1e-3, 30.0, 0.3, 11)
    whole = matting.split_mixed_pixels(img, s)
    monkeypatch.setattr(matting, "SPLIT_CHUNK", 37)
    parts = matting.split_mixed_pixels(img, s)
    assert len(whole) > 37
    for f in ("index", "alpha", "foreground", "background", "near_coc", "far_coc"):
        np.testing.assert_array_equal(getattr(parts, f), getattr(whole, f))


def test_a_split_that_cannot_fit_the_budget_is_refused_before_the_matting():
    from bokehray.errors import ResourceError

    rng = np.random.default_rng(0)
    img = rng.uniform(0, 1, (256, 256, 3)).astype(np.float32)
    d = (np.indices((256, 256)).sum(0) % 2).astype(np.float32)  # a 1 px checkerboard: every pixel an edge pixel
    with pytest.raises(ResourceError, match="soft edges of the 256 x 256 px image"):
        br.render(img, d, br.BlurParams(8.0, 0.5), memory=br.MemoryOptions(memory_limit_mb=1.6))


@settings(max_examples=30, deadline=None)
@given(h=st.integers(1, 6), w=st.integers(1, 6), pads=st.tuples(*[st.integers(0, 3)] * 4), seed=st.integers(0, 999))
def test_the_replicas_are_counted_before_they_are_made(h, w, pads, seed):
    from bokehray import scene as sc

    rng = np.random.default_rng(seed)
    index = np.flatnonzero(rng.random(h * w) < 0.6).astype(np.int64)
    n = index.size
    soft = sc.SoftEdges(index, np.full(n, 0.5, np.float32), np.ones((n, 3), np.float32), np.zeros((n, 3), np.float32),
                        np.full(n, 2.0, np.float32), np.zeros(n, np.float32))
    padded = sc.pad_soft_edges(soft, (h, w), pads)
    assert len(padded) == n + sc.soft_replicas(soft, (h, w), pads)
    assert (np.diff(padded.index) > 0).all()

