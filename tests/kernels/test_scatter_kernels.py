"""Warp kernels of the preview renderer against the float64 NumPy reference (tests/reference)."""

import bokehray_kernels as bk
import numpy as np
import pytest
import warp as wp
from hypothesis import given
from hypothesis import strategies as st
from reference import scatter_ref
from tolerances import (
    ENERGY_RTOL,
    FOOTPRINT_L1,
    POINT_LIGHT_L1,
    PYRAMID_INNER_ENERGY_RTOL,
    PYRAMID_REL_MAE,
    SCATTER_VS_REFERENCE_ATOL,
    SHAPE_L1_LEVEL0,
)

from bokehray import Aperture, LayerOptions, PreviewOptions
from bokehray.lens import aperture_area
from bokehray.levels.preview import (
    MERGE_COC_CELLS,
    aperture_shape,
    no_routing,
    prefix_rows,
    pyramid_buffers,
    render_signed_coc,
)
from bokehray.scene import LayerSupport, layer_edges

APERTURES = [
    Aperture(),
    Aperture(blades=5, rotation_deg=0.0),
    Aperture(blades=6, rotation_deg=17.0, curvature=0.4),
    Aperture(blades=3, rotation_deg=90.0),
    Aperture(blades=9, curvature=1.0),
]


@wp.kernel
def _chord_probe(ys: wp.array(dtype=float), rhos: wp.array(dtype=float), blades: wp.array(dtype=wp.vec4),
                 n: int, out: wp.array(dtype=wp.vec2)):
    i = wp.tid()
    out[i] = bk.chord(ys[i], rhos[i], blades, n)


def _blades_wp(ap: Aperture, device: str):
    rows = ap.blade_discs()
    return wp.array(rows if len(rows) else np.zeros((1, 4), np.float32), dtype=wp.vec4, device=device), len(rows)


@pytest.mark.parametrize("ap", APERTURES, ids=str)
def test_chord_matches_reference(ap, device, rng):
    ys = rng.uniform(-12, 12, 500).astype(np.float32)
    rhos = rng.uniform(0.1, 12, 500).astype(np.float32)
    blades, n = _blades_wp(ap, device)
    out = wp.empty(500, dtype=wp.vec2, device=device)
    wp.launch(_chord_probe, dim=500, inputs=[wp.array(ys, device=device), wp.array(rhos, device=device), blades, n],
              outputs=[out], device=device)
    got = out.numpy()
    for i in range(500):
        lo, hi = scatter_ref.chord(float(ys[i]), float(rhos[i]), ap.blade_discs())
        if hi > lo + 1e-4:
            np.testing.assert_allclose(got[i], [lo, hi], atol=1e-4)
        else:
            assert got[i][1] - got[i][0] < 1e-3


def _route(src: np.ndarray, coc: np.ndarray, n_levels: int, device: str, ap: Aperture | None = None):
    """``route_salient`` of a layer's sources at r0 = 8: its routing and the level-0 difference plane its clusters
    were scattered into."""
    from bokehray.levels.preview import route_salient

    ap = ap or Aperture()
    h, w = coc.shape
    buf0 = wp.zeros((h, w + 2), dtype=wp.vec4, device=device)
    routing = route_salient(wp.array(np.ascontiguousarray(src), dtype=wp.vec4, device=device),
                            wp.array(np.ascontiguousarray(coc), device=device), n_levels, 8.0, device,
                            aperture_shape(ap, ap.blade_discs(), device), buf0)
    return routing, buf0


def _point_response(ap: Aperture, radius: float, size: int, device: str, offset=(0, 0), r0: float = 1e6,
                    levels: int = 1) -> np.ndarray:
    """The kernel of one source: scatter, prefix sums and level resolve, no compositing."""
    src = np.zeros((size, size, 4), np.float32)
    src[size // 2 + offset[0], size // 2 + offset[1]] = 1.0
    radius_map = np.full((size, size), radius, np.float32)
    bufs = [wp.zeros(((size + (1 << lv) - 1) >> lv, ((size + (1 << lv) - 1) >> lv) + 2), dtype=wp.vec4,
                     device=device) for lv in range(levels)]
    bufs += [bufs[0]] * (bk.MAX_LEVELS - levels)
    shape = aperture_shape(ap, ap.blade_discs(), device)
    wp.launch(bk.scatter_kernel, dim=(size, size),
              inputs=[1, wp.array(src, dtype=wp.vec4, device=device), wp.array(radius_map, device=device),
                      LayerSupport.everywhere(device).struct(), no_routing(device).struct(), shape, r0, levels, pyramid_buffers(bufs), 0], device=device)
    for lv in range(levels):
        prefix_rows(bufs[lv], device)
    out = wp.empty((size, size), dtype=wp.vec4, device=device)
    wp.launch(bk.resolve_levels_kernel, dim=(size, size),
              inputs=[1, levels, 0, pyramid_buffers(bufs), LayerSupport.everywhere(device).struct()], outputs=[out],
              device=device)
    return out.numpy()[..., 0]


@pytest.mark.parametrize("ap", APERTURES, ids=str)
@pytest.mark.parametrize("radius", [0.0, 0.1, 0.49, 0.5, 0.75, 1.0, 1.7, 3.3, 7.9])
def test_aperture_kernel_integrates_to_one(ap, radius, device):
    out = _point_response(ap, radius, 33, device)
    np.testing.assert_allclose(out.sum(), 1.0, rtol=ENERGY_RTOL)
    assert out.min() >= -1e-6


@pytest.mark.parametrize("ap", APERTURES, ids=str)
@pytest.mark.parametrize("radius", [2.6, 6.3])
def test_footprint_close_to_exact_area_coverage(ap, radius, device):
    size = 21
    got = _point_response(ap, -radius, size, device)  # behind focus: the aperture as described
    # exact coverage by 64 x 64 supersampling of every pixel
    n = 64
    c = size // 2 + 0.5
    sub = (np.arange(size * n) + 0.5) / n
    px, py = np.meshgrid(sub - c, sub - c)
    cov = scatter_ref.inside(px, py, radius, ap.blade_discs()).reshape(size, n, size, n).mean(axis=(1, 3))
    cov /= cov.sum()
    err = np.abs(got - cov).sum()
    assert err < FOOTPRINT_L1, err


@pytest.mark.parametrize("ap", APERTURES[1:4], ids=str)
def test_front_bokeh_is_the_point_reflection_of_back_bokeh(ap, device):
    """A thin lens images the aperture point-reflected in front of the focal plane (as the ray tracer does)."""
    back = _point_response(ap, -5.3, 21, device)
    front = _point_response(ap, 5.3, 21, device)
    np.testing.assert_allclose(front, back[::-1, ::-1], atol=1e-6)


@pytest.mark.parametrize("ap", APERTURES[:3], ids=str)
def test_scatter_matches_reference(ap, device, rng):
    h, w = 14, 17
    src = rng.random((h, w, 4)).astype(np.float32)
    src[..., 3] = 1.0
    radius = rng.uniform(0, 5, (h, w)).astype(np.float32)
    radius[rng.random((h, w)) < 0.2] = 0.3  # sub-pixel sources take the copy path
    bufs = [wp.zeros((h, w + 2), dtype=wp.vec4, device=device)]
    bufs += [bufs[0]] * (bk.MAX_LEVELS - 1)
    wp.launch(bk.scatter_kernel, dim=(h, w),
              inputs=[1, wp.array(src, dtype=wp.vec4, device=device), wp.array(radius, device=device),
                      LayerSupport.everywhere(device).struct(), no_routing(device).struct(), aperture_shape(ap, ap.blade_discs(), device), 1e6, 1,
                      pyramid_buffers(bufs), 0], device=device)
    prefix_rows(bufs[0], device)
    got = bufs[0].numpy()[:, :w]
    want = scatter_ref.scatter(src.astype(np.float64), radius, ap.blade_discs(), ap.vertical_extent())
    np.testing.assert_allclose(got, want, atol=SCATTER_VS_REFERENCE_ATOL)


@pytest.mark.parametrize("ap", APERTURES[:2], ids=str)
def test_layered_preview_matches_reference(ap, device, rng):
    h, w = 20, 24
    image = rng.random((h, w, 3)).astype(np.float32)
    disparity = np.zeros((h, w), np.float32)
    disparity[:, :] = np.linspace(0, 0.4, w)[None, :]
    disparity[5:14, 6:15] = 0.9  # a near square over a tilted background
    s = (8.0 * (disparity - 0.5)).astype(np.float32)
    layers = LayerOptions(max_layer_px=1.5, fill=False, tile_px=8)
    got, stats = render_signed_coc(image, s, ap, layers=layers, options=PreviewOptions(level_radius_px=1e6),
                                   device=device)
    edges = layer_edges(s, layers)
    assert 4 <= stats.layers <= len(edges) - 1  # empty layers are skipped
    want = scatter_ref.layered(image.astype(np.float64), s.astype(np.float64), edges, ap.blade_discs(),
                               ap.vertical_extent())
    np.testing.assert_allclose(got, want, atol=1e-4)


def test_pyramid_levels_approximate_level_zero(device):
    h, w = 96, 128
    yy, xx = np.mgrid[0:h, 0:w]
    image = np.stack([0.5 + 0.3 * np.sin(xx / 9.0), 0.5 + 0.3 * np.cos(yy / 7.0), np.full((h, w), 0.4)], -1)
    image = image.astype(np.float32)
    s = np.full((h, w), 13.0, np.float32)
    exact, _ = render_signed_coc(image, s, Aperture(), options=PreviewOptions(level_radius_px=1e6), device=device)
    approx, st_ = render_signed_coc(image, s, Aperture(), options=PreviewOptions(level_radius_px=4.0),
                                   device=device)
    assert st_.pyramid_levels == 3
    inner = (slice(16, -16), slice(16, -16))
    mae = np.abs(exact[inner] - approx[inner]).mean() / image.mean()
    assert mae < PYRAMID_REL_MAE
    np.testing.assert_allclose(approx[inner].sum(), exact[inner].sum(), rtol=PYRAMID_INNER_ENERGY_RTOL)


def _merged_level(src: np.ndarray, coc: np.ndarray, ap: Aperture, r0: float, n_levels: int, lev: int,
                  device: str) -> tuple[np.ndarray, np.ndarray]:
    """(level ``lev``'s values, level 0's) after ``scatter_merged_kernel`` (nothing routed) and the prefix sums."""
    h, w = coc.shape
    bufs = [wp.zeros(((h + (1 << lv) - 1) >> lv, ((w + (1 << lv) - 1) >> lv) + 2), dtype=wp.vec4, device=device)
            for lv in range(n_levels)]
    bufs += [bufs[0]] * (bk.MAX_LEVELS - n_levels)
    side = 1 << lev
    wp.launch(bk.scatter_merged_kernel, dim=((h + side - 1) // side, (w + side - 1) // side),
              inputs=[wp.array(src, dtype=wp.vec4, device=device), wp.array(coc, device=device),
                      LayerSupport.everywhere(device).struct(), no_routing(device).struct(),
                      aperture_shape(ap, ap.blade_discs(), device), r0, n_levels, lev, MERGE_COC_CELLS * side,
                      pyramid_buffers(bufs)], device=device)
    for lv in (0, lev):
        prefix_rows(bufs[lv], device)
    return bufs[lev].numpy()[:, : bufs[lev].shape[1] - 2], bufs[0].numpy()[:, :w]


@pytest.mark.parametrize("ap", APERTURES[:3], ids=str)
@pytest.mark.parametrize("lev", [1, 2])
def test_merged_scatter_matches_reference(ap, lev, device, rng):
    """scatter_merged_kernel against the reference's merged sources drawn with the sharp rule: cells of near-equal
    CoCs merge (to one source or a few, a colour apart from the coverage where it is not centred with it),
    cells of scattered CoCs (the right half) scatter every source."""
    h, w, r0, n_levels = 27, 34, 4.0, 3
    src = rng.random((h, w, 4)).astype(np.float32)
    src[..., 3] = rng.uniform(0.2, 1.0, (h, w))
    src[..., :3] *= src[..., 3:]
    src[rng.random((h, w)) < 0.1] = 0.0  # holes: not sources
    src[: h // 3] = (0.3, 0.2, 0.1, 1.0)  # one colour: light and coverage merge at one centroid
    yy, xx = np.mgrid[0:h, 0:w]
    coc = 3.5 + 11.0 * yy / h + rng.normal(0.0, 0.2, (h, w)) + np.where(xx >= w // 2, rng.uniform(-3, 3, (h, w)), 0.0)
    coc = (coc * np.where(xx % 7 < 4, -1.0, 1.0)).astype(np.float32)  # in front of the focus and behind it
    got, level0 = _merged_level(src, coc, ap, r0, n_levels, lev, device)
    merged = scatter_ref.merged_sources(src, coc, r0, n_levels, lev, MERGE_COC_CELLS * (1 << lev))
    on_level = sum(scatter_ref.level_of(abs(c), r0, n_levels) == lev for c in coc[(src[..., 3] > 0) & (abs(coc) >= 0.5)])
    groups = sum(v[3] > 0 for *_, v in merged)  # a merged group's coverage is one source
    assert 0.8 * on_level > groups > on_level / (1 << (2 * lev))  # merged where the CoCs agree, not elsewhere
    assert 0 < len(merged) - groups < groups  # textured cells: a channel's light at its own centroid
    scale = 1.0 / (1 << lev)
    want = np.zeros(got.shape)
    for x, y, c, v in merged:
        fp = scatter_ref.sharp_footprint(x * scale, y * scale, c * scale, ap.blade_discs(), *got.shape[:2],
                                         ap.vertical_extent(), aperture_area(ap))
        want += fp[..., None] * v
    np.testing.assert_allclose(got, want, atol=SCATTER_VS_REFERENCE_ATOL)
    assert not level0.any()  # nothing routed: nothing at level 0


def _each_level_sum(src: np.ndarray, coc: np.ndarray, r0: float, n_levels: int) -> np.ndarray:
    """The summed values of every pyramid level after ``scatter_kernel`` scattering each source."""
    h, w = coc.shape
    bufs = [wp.zeros(((h + (1 << lv) - 1) >> lv, ((w + (1 << lv) - 1) >> lv) + 2), dtype=wp.vec4)
            for lv in range(n_levels)]
    bufs += [bufs[0]] * (bk.MAX_LEVELS - n_levels)
    wp.launch(bk.scatter_kernel, dim=(h, w),
              inputs=[1, wp.array(src, dtype=wp.vec4), wp.array(coc), LayerSupport.everywhere("cpu").struct(),
                      no_routing("cpu").struct(), aperture_shape(Aperture(), np.zeros((0, 4)), "cpu"), r0, n_levels,
                      pyramid_buffers(bufs), 0])
    for lv in range(n_levels):
        prefix_rows(bufs[lv], "cpu")
    return sum(bufs[lv].numpy()[:, :-2].astype(np.float64).sum(axis=(0, 1)) for lv in range(n_levels))


@given(lev=st.integers(1, 3), spread=st.floats(0.0, 30.0), seed=st.integers(0, 2**32 - 1))
def test_merged_scatter_keeps_every_sources_value(lev, spread, seed):
    """Whatever the cells' CoCs, the merged scatter deposits the level's sources' summed value (away from the
    frame's edges), at every level: as closely as scattering each source does (the pyramid's float32 sums lose up
    to a few 1e-4 either way, tolerances.PYRAMID_ENERGY_RTOL)."""
    rng = np.random.default_rng(seed)
    h = w = 24
    src = np.zeros((72, 72, 4), np.float32)
    src[24:48, 24:48] = rng.random((h, w, 4))
    coc = np.zeros((72, 72), np.float32)
    r = 8.0 * 2 ** (lev - 1) + 0.01 + rng.uniform(0.0, min(spread, 8.0 * 2 ** (lev - 1) - 0.02), (h, w))
    coc[24:48, 24:48] = r * rng.choice([-1.0, 1.0], (h, w))
    got, _ = _merged_level(src, coc, Aperture(), 8.0, 4, lev, "cpu")
    total = src.astype(np.float64).sum(axis=(0, 1))
    each = _each_level_sum(src, coc, 8.0, 4)
    assert np.all(np.abs(got.sum(axis=(0, 1)) - total) <= np.abs(each - total) + 1e-4 * total)


def test_merged_render_is_the_unmerged_one_where_lights_are_routed(device, rng):
    """A textured layer with lights at R = 13 and 40: merging its pyramid sources changes the render by less than
    the pyramid itself does (against every source exact), and each routed light keeps its exact outline."""
    h, w = 150, 170
    yy, xx = np.mgrid[0:h, 0:w]
    image = np.stack([0.5 + 0.3 * np.sin(xx / 9.0), 0.5 + 0.3 * np.cos(yy / 7.0), 0.4 + 0.2 * rng.random((h, w))], -1)
    image = image.astype(np.float32)
    image[40, 50] = image[100, 120] = 60.0  # lights
    for radius in (13.0, 40.0):
        s = np.full((h, w), -radius, np.float32)
        exact, _ = render_signed_coc(image, s, Aperture(), options=PreviewOptions(level_radius_px=1e6), device=device)
        each, _ = render_signed_coc(image, s, Aperture(), options=PreviewOptions(merge_sources=False), device=device)
        merged, _ = render_signed_coc(image, s, Aperture(), device=device)
        pyramid_err = np.abs(each - exact).mean()
        assert np.abs(merged - each).mean() < pyramid_err
        assert np.abs(merged - exact).mean() < 1.5 * pyramid_err


def _random_support(rng, h: int, w: int, shift: int) -> LayerSupport:
    """A random tile mask of ``2^shift`` px tiles over an ``h x w`` box at a random scene offset."""
    oy, ox = (int(v) for v in rng.integers(0, 1 << shift, 2))
    mask = (rng.random((((h + oy) >> shift) + 1, ((w + ox) >> shift) + 1)) < 0.6).astype(np.uint8)
    return LayerSupport(wp.array(mask, dtype=wp.uint8), shift, oy, ox)


@given(h=st.integers(1, 30), w=st.integers(1, 30), merged=st.integers(0, 1), routed=st.booleans(),
       seed=st.integers(0, 2**32 - 1))
def test_scatter_rows_deposits_what_the_pixel_kernel_deposits(h, w, merged, routed, seed):
    """scatter_kernel a row a thread (the CPU's launch, span = w) and 3 pixels a thread against a pixel a thread, bit
    for bit (the same deposits in the same order), on levels 0-2, with and without routed lights, in a random
    support."""
    rng = np.random.default_rng(seed)
    src = rng.random((h, w, 4)).astype(np.float32)
    src[rng.random((h, w)) < 0.05, :3] *= 300.0  # lights
    coc = (rng.uniform(0.0, 30.0, (h, w)) * rng.choice([-1.0, 1.0], (h, w))).astype(np.float32)
    src_wp, coc_wp = wp.array(src, dtype=wp.vec4), wp.array(coc)
    routing = _route(src, coc, 3, "cpu")[0] if routed else no_routing("cpu")
    support = _random_support(rng, h, w, 2).struct()
    got = []
    for span in (1, w, 3):
        bufs = [wp.zeros(((h + (1 << lv) - 1) >> lv, ((w + (1 << lv) - 1) >> lv) + 2), dtype=wp.vec4) for lv in range(3)]
        wp.launch(bk.scatter_kernel, dim=(h, -(-w // span)), inputs=[span, src_wp, coc_wp, support, routing.struct(),
                                           aperture_shape(Aperture(), np.zeros((0, 4)), "cpu"), 8.0, 3,
                                           pyramid_buffers(bufs + [bufs[0]] * (bk.MAX_LEVELS - 3)), merged])
        got.append(b"".join(b.numpy().tobytes() for b in bufs))
    assert got[0] == got[1] == got[2]


@given(h=st.integers(1, 40), w=st.integers(1, 40), n_levels=st.integers(1, 4), first=st.integers(0, 3),
       seed=st.integers(0, 2**32 - 1))
def test_resolve_rows_stores_what_the_pixel_kernel_stores(h, w, n_levels, first, seed):
    """resolve_levels_kernel a row a thread (the CPU's launch, span = w) against a pixel a thread, bit for bit,
    within a random support."""
    rng = np.random.default_rng(seed)
    bufs = [wp.array(rng.random(((h + (1 << lv) - 1) >> lv, ((w + (1 << lv) - 1) >> lv) + 2, 4)).astype(np.float32),
                     dtype=wp.vec4) for lv in range(n_levels)]
    levels = pyramid_buffers(bufs + [bufs[0]] * (bk.MAX_LEVELS - n_levels))
    support = _random_support(rng, h, w, 2).struct()
    start = rng.random((h, w, 4)).astype(np.float32)
    pixel, rows = wp.array(start, dtype=wp.vec4), wp.array(start, dtype=wp.vec4)
    wp.launch(bk.resolve_levels_kernel, dim=(h, w), inputs=[1, n_levels, first, levels, support], outputs=[pixel])
    wp.launch(bk.resolve_levels_kernel, dim=(h, 1), inputs=[w, n_levels, first, levels, support], outputs=[rows])
    assert rows.numpy().tobytes() == pixel.numpy().tobytes()
    yy, xx = np.mgrid[0:h, 0:w]
    inside = support.mask.numpy()[(yy + support.oy) >> support.shift, (xx + support.ox) >> support.shift] != 0
    np.testing.assert_array_equal(pixel.numpy()[~inside], start[~inside])  # nothing stored outside the support
    if n_levels <= max(first, 1):  # no coarser level read: level 0 as it is
        np.testing.assert_array_equal(pixel.numpy()[inside], bufs[0].numpy()[:, :w][inside])


@given(h=st.integers(1, 30), w=st.integers(1, 30), seed=st.integers(0, 2**32 - 1))
def test_composite_kernels_match_reference(h, w, seed):
    """composite_kernel a pixel a thread and a row a thread (the CPU's launch, span = w) against the reference's
    "over", within a random support (the accumulator untouched outside it), the two launches bit for bit."""
    rng = np.random.default_rng(seed)
    layer = rng.random((h, w, 4)).astype(np.float32) * 2
    layer[rng.random((h, w)) < 0.2] = 0.0  # no light there
    acc0 = rng.random((h + 5, w + 7, 4)).astype(np.float32)
    opaque = (rng.random(acc0.shape[:2]) < 0.3).astype(np.uint8)  # the frame's opaque map and layer ids
    ids = rng.integers(0, 2, acc0.shape[:2]).astype(np.int32)
    support = _random_support(rng, h, w, 3)
    got = {}
    for span in (1, w):
        acc = wp.array(acc0, dtype=wp.vec4)
        wp.launch(bk.composite_kernel, dim=(h, -(-w // span)),
                  inputs=[span, wp.array(layer, dtype=wp.vec4), support.struct(), 7, 5,
                          wp.array(opaque, dtype=wp.uint8), wp.array(ids, dtype=wp.int32), 1], outputs=[acc])
        got[span] = acc.numpy()
    assert got[w].tobytes() == got[1].tobytes()
    yy, xx = np.mgrid[0:h, 0:w]
    inside = support.mask.numpy()[(yy + support.oy) >> support.shift, (xx + support.ox) >> support.shift] != 0
    whole = ((opaque != 0) & (ids == 1))[5:, 7:]
    want = acc0.astype(np.float64)
    want[5:, 7:] = np.where(inside[..., None], scatter_ref.over(layer, want[5:, 7:], whole), want[5:, 7:])
    np.testing.assert_allclose(got[1], want, rtol=1e-5, atol=1e-6)


@given(
    radius=st.floats(0.0, 40.0),
    blades=st.sampled_from([0, 3, 5, 6, 8]),
    rotation=st.floats(0.0, 360.0),
    curvature=st.floats(0.0, 1.0),
    dy=st.integers(-3, 3),
    dx=st.integers(-3, 3),
    pyramid=st.booleans(),
)
def test_every_aperture_integrates_to_one_property(radius, blades, rotation, curvature, dy, dx, pyramid):
    ap = Aperture(blades=blades, rotation_deg=rotation, curvature=curvature)
    # 97 px: the largest disc (r = 40) plus the 3 px offset stays inside the image
    kw = {"r0": 8.0, "levels": 4} if pyramid else {}
    out = _point_response(ap, radius, 97, "cpu", offset=(dy, dx), **kw)
    np.testing.assert_allclose(out.sum(), 1.0, rtol=ENERGY_RTOL if not pyramid else 1e-4)
    assert np.isfinite(out).all()
    assert out.min() >= -1e-6


@given(values=st.lists(st.floats(-40, 40), min_size=1, max_size=200), max_px=st.floats(1.0, 16.0),
       max_layers=st.integers(1, 16))
def test_layer_edges_cover_all_values_and_respect_limits(values, max_px, max_layers):
    s = np.asarray(values, np.float32)
    opts = LayerOptions(max_layer_px=max_px, max_layers=max_layers)
    edges = layer_edges(s, opts)
    assert np.all(np.diff(edges) > 0)
    assert edges[0] < s.min() and edges[-1] > s.max()
    assert len(edges) - 1 <= max(1, max_layers)


def test_layer_edges_cut_at_gaps_and_around_focus():
    s = np.concatenate([np.linspace(-20, -12, 50), np.linspace(-3, 0.3, 50), np.linspace(5, 9, 50)])
    edges = layer_edges(s.astype(np.float32), LayerOptions(max_layer_px=100.0))
    inner = edges[1:-1]
    assert any(-12 < e < -3 for e in inner) and any(0.3 < e < 5 for e in inner)  # the two depth gaps
    assert -0.5 in inner and 0.5 in inner  # the in-focus layer is its own


def test_layer_edges_keep_the_in_focus_layer_when_the_budget_is_tight():
    """Review finding: a 200 px CoC span used to fall back to even spacing and lose the focus cuts."""
    s = np.linspace(-100, 100, 5000).astype(np.float32)
    edges = layer_edges(s, LayerOptions(max_layers=12))
    assert len(edges) - 1 <= 12
    assert -0.5 in edges and 0.5 in edges


def test_small_bright_layer_over_black_keeps_its_energy():
    """A large pyramid-level bokeh ball of a small layer arrives whole (nothing cut at its layer box)."""
    n = 480
    img = np.zeros((n, n, 3), np.float32)
    img[232:248, 232:248] = 10.0
    s = np.full((n, n), -110.0, np.float32)  # a black background layer ...
    s[232:248, 232:248] = -100.0  # ... behind a small bright layer of its own, r = 100 (pyramid level 4)
    out, stats = render_signed_coc(img, s, Aperture())
    assert stats.layers == 2
    # all the light arrives: none is cut off at the edge of the small layer's box
    np.testing.assert_allclose(out.sum(), img.sum(), rtol=1e-3)


# --------------------------------------------------------------------- exact shapes at every radius


def test_analytic_aperture_area_matches_the_shape():
    """The scatter's normalisation (the aperture's area) against point-in-shape counting."""
    for ap in APERTURES + [Aperture(blades=3, curvature=0.9, rotation_deg=20.0), Aperture(blades=7, curvature=0.3)]:
        want = scatter_ref.unit_area(ap.blade_discs())
        assert abs(aperture_area(ap) - want) < 2e-5 * want, ap
        assert abs(scatter_ref.rows_area(ap.blade_discs()) - aperture_area(ap)) < 1e-6


@pytest.mark.parametrize("ap", [Aperture(), Aperture(blades=6, rotation_deg=15.0),
                                Aperture(blades=5, rotation_deg=10.0, curvature=0.3)], ids=str)
@pytest.mark.parametrize("radius", [-4.3, 5.1, -6.3, 7.7])
def test_level0_footprint_is_area_exact(ap, radius, device):
    """Level-0 spans vs the analytic shape integrated over each pixel, behind and in front of the focus."""
    size = 21
    got = _point_response(ap, radius, size, device)
    want = scatter_ref.area_coverage(size // 2 + 0.5, size // 2 + 0.5, radius, ap.blade_discs(), size, size)
    assert np.abs(got - want).sum() < SHAPE_L1_LEVEL0, np.abs(got - want).sum()


def _point_light(ap: Aperture, radius: float, size: int, centre: tuple[int, int], options=None):
    image = np.zeros((size, size, 3), np.float32)
    image[centre] = 1.0
    out, _ = render_signed_coc(image, np.full((size, size), radius, np.float32), ap, options=options)
    want = scatter_ref.area_coverage(centre[1] + 0.5, centre[0] + 0.5, radius, ap.blade_discs(), size, size)
    return out[..., 0].astype(np.float64), want


@pytest.mark.parametrize("ap", [Aperture(), Aperture(blades=6, rotation_deg=15.0),
                                Aperture(blades=7, rotation_deg=5.0, curvature=0.4)], ids=str)
@pytest.mark.parametrize("radius", [-12.0, 21.0, -40.0])
def test_point_light_has_the_exact_shape_at_pyramid_radii(ap, radius):
    """A light on black at radii of pyramid levels 1-3: the exact outline, a flat plateau, its energy."""
    size = int(2 * abs(radius)) + 25
    got, want = _point_light(ap, radius, size, (size // 2, size // 2))
    assert np.abs(got - want).sum() < POINT_LIGHT_L1
    full = want >= want.max() * (1 - 1e-9)
    assert got[full].max() / got[full].mean() < 1.01
    assert abs(got.sum() - 1.0) < 1e-3
    # the fast mode keeps the pyramid's blurred outline: the test above can fail
    fast, _ = _point_light(ap, radius, size, (size // 2, size // 2), PreviewOptions(exact_highlights=False))
    assert np.abs(fast - want).sum() > 10 * POINT_LIGHT_L1


@pytest.mark.parametrize("ap", [Aperture(), Aperture(blades=5, rotation_deg=30.0)], ids=str)
def test_light_near_the_border_keeps_what_the_frame_cuts_of_it(ap):
    """Clamped border: a light 6 px inside the frame at R = 20 is the analytic shape cut by the frame,
    no brighter at its rim (the renormalising rule amplified it there)."""
    size = 90
    got, want = _point_light(ap, -20.0, size, (45, 6))
    assert np.abs(got - want).sum() < POINT_LIGHT_L1
    np.testing.assert_allclose(got.sum(), want.sum(), rtol=1e-3)
    assert want.sum() < 0.9  # a good part of it falls outside
    old, _ = _point_light(ap, -20.0, size, (45, 6), PreviewOptions(clamp_border=False))
    assert old.sum() > want.sum() * 1.05  # the rule before invented light


@pytest.mark.parametrize("supported", [False, True])
def test_radiance_pyramid_matches_reference(device, rng, supported):
    """radiance_mean_kernel and halve_mean_kernel: each level's means, pixels and the pyramid levels its cells'
    sources may scatter on (which route_cells_kernel reads to skip the cells holding none of its level), against the
    plain-loop reference; the planes come uninitialised but level 1 of the means (outside the support)."""
    h, w, n_levels, r0 = 45, 53, 5, 8.0
    src = rng.random((h, w, 4)).astype(np.float32)
    src[..., 3] = (rng.random((h, w)) < 0.8).astype(np.float32)
    # radii on every level, at its edges too (r0 2^l exactly and one ulp above), in patches: cells of one level
    edges = np.array([r0 * 2.0 ** k for k in range(n_levels)], np.float32)
    pool = np.concatenate([rng.uniform(0.0, 200.0, 64).astype(np.float32), edges, np.nextafter(edges, np.inf),
                           np.float32([0.4999, 0.5])])
    patches = rng.choice(pool, (h // 4 + 1, w // 4 + 1))
    coc = np.repeat(np.repeat(patches, 4, 0), 4, 1)[:h, :w] * rng.choice([-1, 1], (h, w)).astype(np.float32)
    coc[rng.random((h, w)) < 0.1] = rng.choice(pool, 1)[0]
    mask = (rng.random((3, 4)) < 0.6).astype(np.uint8) if supported else np.ones((1, 1), np.uint8)
    support = LayerSupport(wp.array(mask, dtype=wp.uint8, device=device), 4 if supported else 30, 0, 0)
    inside = np.ones((h, w), bool) if not supported else np.repeat(np.repeat(mask, 16, 0), 16, 1)[:h, :w] != 0
    n_means, h1, w1 = n_levels - 1, (h + 1) // 2, (w + 1) // 2
    means = wp.array(np.full((n_means, h1, w1, 4), np.nan, np.float32), dtype=wp.vec4, device=device)
    means[0].zero_()
    counts = wp.array(np.full((n_means, h1, w1), np.nan, np.float32), dtype=float, device=device)
    present = wp.array(np.full((n_means, h1, w1), 0xAA, np.uint8), dtype=wp.uint8, device=device)
    wp.launch(bk.radiance_mean_kernel, dim=(h1, 1),
              inputs=[w1, wp.array(src, dtype=wp.vec4, device=device), wp.array(coc, device=device),
                      support.struct(), r0, n_levels], outputs=[means, counts, present], device=device)
    fh, fw = h1, w1
    for k in range(1, n_means):
        ch, cw = (fh + 1) // 2, (fw + 1) // 2
        wp.launch(bk.halve_mean_kernel, dim=(ch, cw), inputs=[means, counts, present, k, fh, fw], device=device)
        fh, fw = ch, cw
    want = scatter_ref.radiance_pyramid(src.astype(np.float64), coc, inside, r0, n_levels)
    assert len({int(b) for _, _, bits in want for b in np.unique(bits)}) > 6  # cells of one level, of several, none
    for k, (m, px, bits) in enumerate(want):
        hk, wk = px.shape
        np.testing.assert_array_equal(present.numpy()[k, :hk, :wk], bits)
        np.testing.assert_array_equal(counts.numpy()[k, :hk, :wk], px)
        np.testing.assert_allclose(means.numpy()[k, :hk, :wk], m, rtol=1e-5, atol=1e-6)


def test_salient_routing_matches_reference(device, rng):
    """route_salient (radiance pyramid, salience, per-cell cap) against the plain-loop reference."""
    from bokehray.levels.preview import SALIENT_FLOOR, SALIENT_VISIBLE

    h, w = 37, 45
    src = np.zeros((h, w, 4), np.float32)
    src[..., :3] = rng.random((h, w, 3)) * 0.1
    src[..., 3] = (rng.random((h, w)) < 0.8).astype(np.float32)
    lights = rng.random((h, w)) < 0.15
    src[lights, :3] += rng.uniform(1, 400, (lights.sum(), 1))
    src[..., :3] *= src[..., 3:]
    coc = (rng.uniform(0.3, 60, (h, w)) * rng.choice([-1, 1], (h, w))).astype(np.float32)
    exact = _route(src, coc, 4, device)[0].exact
    score, want = scatter_ref.salient(src.astype(np.float64), coc, 8.0, 4, SALIENT_VISIBLE, SALIENT_FLOOR)
    assert want.sum() > 20 and (score > 0).sum() > want.sum()  # the cap binds somewhere
    np.testing.assert_array_equal(exact.numpy() == 1, want)


@pytest.mark.parametrize("ap", APERTURES[:3], ids=str)
@pytest.mark.parametrize("depths", ["halves", "stripes"])
def test_extended_lights_are_gathered_like_the_reference(ap, device, rng, depths):
    """route_cells_kernel: blobs of lights, each pixel too faint alone to be routed, are gathered per block and
    scattered at level 0 as the reference's sources (members, positions, radii, light) drawn with their exact
    footprints. ``stripes``: near and far columns in one layer (``max_layers=1``): a block's signed CoC averaged to
    about 0, and its light went to a point (NaN or 1.8x the brightest input); its radius is the members' mean
    radius now."""
    from bokehray.levels.preview import SALIENT_FLOOR, SALIENT_VISIBLE

    h, w = 40, 52
    src = np.zeros((h, w, 4), np.float32)
    src[..., :3] = rng.random((h, w, 3)) * 0.05
    src[..., 3] = 1.0
    for y, x in ((9, 11), (25, 30), (30, 8)):  # 5 x 5 lamps of many dim-ish pixels
        src[y:y + 5, x:x + 5, :3] += rng.uniform(0.5, 3.0, 3).astype(np.float32)
    coc = np.full((h, w), -30.0, np.float32)
    if depths == "halves":
        coc[:, w // 2:] = 20.0
    else:
        coc[:, ::2] = 30.0
    routing, buf0 = _route(src, coc, 3, device, ap)
    exact = routing.exact.numpy()
    members, sources = scatter_ref.clusters(src.astype(np.float64), coc, exact == 1, 8.0, 3, SALIENT_VISIBLE,
                                            SALIENT_FLOOR)
    assert members.sum() > 30 and len(sources) > 5  # the lamps' pixels are gathered
    np.testing.assert_array_equal(exact == 2, members)
    if depths == "stripes":
        assert all(abs(c) > 29.9 for _, _, c, _ in sources)
    want = np.zeros((h, w, 3))
    for x, y, c, rgb in sources:
        want += scatter_ref.footprint(x, y, c, ap.blade_discs(), h, w, ap.vertical_extent(),
                                      aperture_area(ap))[..., None] * rgb
    got = np.cumsum(buf0.numpy()[:, :w].astype(np.float64), axis=1)
    assert np.abs(got[..., 3]).max() == 0.0  # light only: the coverage stays on the pyramid
    # positions lie on a 1/256 px grid: a float32 sum may round to the grid point next to the reference's
    assert np.abs(got[..., :3] - want).sum() < 2e-3 * np.abs(want).sum()


def test_an_extended_light_keeps_its_energy_and_round_shape(device):
    """A 5 x 5 lamp of moderate radiance at R = 40: the preview's ball is the exact one (pyramid off) to 1 %."""
    size = 141
    image = np.full((size, size, 3), 0.02, np.float32)
    image[68:73, 68:73] = 2.0
    s = np.full((size, size), -40.0, np.float32)
    got, _ = render_signed_coc(image, s, Aperture(), device=device)
    exact, _ = render_signed_coc(image, s, Aperture(), options=PreviewOptions(level_radius_px=1000), device=device)
    pyramid, _ = render_signed_coc(image, s, Aperture(), options=PreviewOptions(exact_highlights=False), device=device)
    err = np.abs(got - exact).sum() / np.abs(exact - 0.02).sum()
    assert err < 0.01
    assert np.abs(pyramid - exact).sum() / np.abs(exact - 0.02).sum() > 3 * err  # the pyramid alone is worse


def test_a_small_lamp_keeps_its_outline(device):
    """A lamp of radius 3 px at R = 33 (its clusters gathered per 2 px block): against the pyramid-free render its
    largest error stays below 8.5 % of the peak (10 % with the pyramid levels' sharp spans for the cluster
    sources, which was tried and dropped: docs/design/radius-pyramid.md)."""
    size = 121
    yy, xx = np.mgrid[:size, :size]
    image = np.full((size, size, 3), 0.05, np.float32)
    image[np.hypot(yy - 60, xx - 60) <= 3] = 50.0
    s = np.full((size, size), -33.0, np.float32)
    got, _ = render_signed_coc(image, s, Aperture(), device=device)
    exact, _ = render_signed_coc(image, s, Aperture(), options=PreviewOptions(level_radius_px=1000), device=device)
    assert np.abs(got - exact).max() < 0.085 * exact.max()
    assert np.abs(got - exact).sum() < 0.0105 * np.abs(exact - 0.05).sum()


def _sparse_differences(rows: list[list[tuple[int, int]]], w: int) -> np.ndarray:
    """Difference rows as the scatter leaves them: +v at a span's start, -v at its end (the running sum returns to
    zero after it, exactly or up to rounding)."""
    d = np.zeros((len(rows), w + 2, 4), np.float32)
    for y, spans in enumerate(rows):
        for a, b in spans:
            v = np.float32([0.1 * (a + 1), 0.3, 1.0 / (b + 3), 0.7])
            d[y, min(a, b)] += v
            d[y, max(a, b) + 1] -= v
    return d


@given(rows=st.lists(st.lists(st.tuples(st.integers(0, 40), st.integers(0, 40)), max_size=3), min_size=1,
                     max_size=6))
def test_prefix_sums_are_the_sequential_running_sums(rows):
    """``prefix_rows_kernel`` against NumPy's running sum in float32, bit for bit (rows left zero, spans that
    cancel exactly and ones that leave rounding behind)."""
    d = _sparse_differences(rows, 41)
    buf = wp.array(d, dtype=wp.vec4, device="cpu")
    prefix_rows(buf, "cpu")
    np.testing.assert_array_equal(buf.numpy(), np.cumsum(d, axis=1, dtype=np.float32))


@given(rows=st.lists(st.lists(st.tuples(st.integers(0, 40), st.integers(0, 40)), max_size=3), min_size=1,
                     max_size=6), mask=st.lists(st.lists(st.booleans(), min_size=7, max_size=7), min_size=1, max_size=1),
       oy=st.integers(0, 7), ox=st.integers(0, 7), width=st.integers(0, 43),
       store=st.one_of(st.none(), st.lists(st.booleans(), min_size=7, max_size=7)),
       span=st.tuples(st.integers(0, 6), st.integers(0, 6)))
def test_prefix_sums_store_the_running_sums_within_the_support_only(rows, mask, oy, ox, width, store, span):
    """With a support (8 px tiles, the box at an offset in the scene), a width, a store mask (None: everywhere;
    else some columns of tiles, as the frame without its clamped border) and a range of rows: where the light lies
    (in the support, and the step down one column after a run of it), the elements of those rows in the support
    and the store hold the running sums bit for bit; the others keep their differences (``resolve_levels_kernel``
    never reads them) and are not read."""
    d = _sparse_differences(rows, 41)
    h, w = d.shape[:2]
    width = min(width, w)
    r0, r1 = min(span[0], h), min(max(span), h)
    n_ty = -(-(h + oy) // 8)
    tiles = np.array(mask * n_ty, bool)  # every tile row alike: the hypothesis draws one
    inside = np.repeat(np.repeat(tiles, 8, 0), 8, 1)[oy : oy + h, ox : ox + w]
    inside[:, width:] = False
    lit = inside.copy()
    lit[:, 1:] |= inside[:, :-1]  # where deposits may lie
    lit[: r0], lit[r1:] = False, False  # rows not summed
    d[~lit] = np.nan  # never read: a NaN there would spread through the sums
    support = LayerSupport(wp.array(tiles.astype(np.uint8), dtype=wp.uint8, device="cpu"), 3, oy, ox)
    kept = None
    stored = inside & lit
    if store is not None:
        keep_tiles = np.array([store] * n_ty, bool)
        kept = LayerSupport(wp.array(keep_tiles.astype(np.uint8), dtype=wp.uint8, device="cpu"), 3, oy, ox)
        stored &= np.repeat(np.repeat(keep_tiles, 8, 0), 8, 1)[oy : oy + h, ox : ox + w]
    buf = wp.array(d, dtype=wp.vec4, device="cpu")
    prefix_rows(buf, "cpu", support, width, kept, (r0, r1))
    sums = np.cumsum(np.where(lit[..., None], d, 0), axis=1, dtype=np.float32)
    np.testing.assert_array_equal(buf.numpy(), np.where(stored[..., None], sums, d))


@given(mask=st.lists(st.lists(st.booleans(), min_size=5, max_size=5), min_size=4, max_size=4),
       oy=st.integers(0, 7), ox=st.integers(0, 7), h=st.integers(1, 24), w=st.integers(1, 32))
def test_clear_support_zeroes_the_support_and_nothing_else(mask, oy, ox, h, w):
    """``clear_support_kernel`` a pixel a thread and a row a thread (the CPU's launch) against the mask blown up to
    pixels (8 px tiles, the box at an offset)."""
    tiles = np.array(mask, bool)
    support = LayerSupport(wp.array(tiles.astype(np.uint8), dtype=wp.uint8, device="cpu"), 3, oy, ox)
    before = np.arange(h * (w + 2) * 4, dtype=np.float32).reshape(h, w + 2, 4) + 1.0
    inside = np.zeros((h, w + 2), bool)
    inside[:, :w] = np.repeat(np.repeat(tiles, 8, 0), 8, 1)[oy : oy + h, ox : ox + w]
    for span in (1, w):
        buf = wp.array(before, dtype=wp.vec4, device="cpu")
        wp.launch(bk.clear_support_kernel, dim=(h, -(-w // span)), inputs=[span, support.struct(), w], outputs=[buf],
                  device="cpu")
        np.testing.assert_array_equal(buf.numpy(), np.where(inside[..., None], 0.0, before))


def _anonymous_kb(ptr: int) -> int | None:
    """The private pages (kB) of the mapping holding address ``ptr`` (``/proc/self/smaps``: the kernel's shared zero
    page, which reading an untouched page maps, is not counted); None where there is no smaps."""
    try:
        text = open("/proc/self/smaps").read().splitlines()
    except OSError:
        return None
    inside = False
    for line in text:
        head = line.split()[0]
        if "-" in head and ":" not in head:
            lo, hi = (int(v, 16) for v in head.split("-"))
            inside = lo <= ptr < hi
        elif inside and head == "Anonymous:":
            return int(line.split()[1])
    return None


def test_prefix_sums_leave_a_lazy_buffers_empty_rows_untouched():
    """On a lazily zeroed buffer the prefix sums store nothing before a row's first deposit: rows without one take
    no page, and the values are the running sums."""
    from bokehray.levels.buffers import lazy_zeros

    h, w = 64, 4094  # 4 MiB, a row 64 KiB
    buf = lazy_zeros((h, w + 2), wp.vec4, "cpu")
    host = buf.numpy()  # aliases the mapping
    d = _sparse_differences([[(3, 500)] if y % 8 == 5 else [] for y in range(h)], w)
    host[5::8] = d[5::8]  # the deposited rows only
    before = _anonymous_kb(buf.ptr)  # (the mapping may share its smaps entry with neighbouring ones)
    prefix_rows(buf, "cpu")
    after = _anonymous_kb(buf.ptr)
    np.testing.assert_array_equal(host, np.cumsum(d, axis=1, dtype=np.float32))
    if before is None or after is None:
        pytest.skip("no /proc/self/smaps")
    # storing every element would take all 4096 kB, the empty rows' 3584 of them; a neighbouring mapping that shares
    # the smaps entry can grow by about a MB meanwhile (seen once in eight runs under xdist: 1048 kB)
    assert after - before < 2048


@wp.kernel
def _exact_probe(xc: float, yc: float, rho: float, sgn: float, shape: bk.Shape, buf: wp.array2d(dtype=wp.vec4)):
    bk.spans.scatter_exact(buf, xc, yc, rho, wp.vec4(1.0, 2.0, 3.0, 0.0), shape, sgn)


def _cluster_deposit(xc: float, yc: float, s: float, shape: bk.Shape, h: int, w: int) -> np.ndarray:
    """The level-0 difference buffer a cluster source (``route_cells_kernel``'s exact spans) at ``(xc, yc)`` with
    signed CoC ``s`` leaves in an ``h x w`` box."""
    buf = wp.zeros((h, w + 2), dtype=wp.vec4, device="cpu")
    wp.launch(_exact_probe, dim=1, inputs=[xc, yc, abs(s), -1.0 if s > 0 else 1.0, shape], outputs=[buf],
              device="cpu")
    return buf.numpy()


@given(m=st.integers(1, 40), frac=st.integers(0, 255), ulps=st.integers(-3, 3), end=st.sampled_from([-1, 1]),
       sgn=st.sampled_from([-1.0, 1.0]), dy=st.integers(1, 3000), blades=st.sampled_from([0, 6]))
def test_a_cluster_is_cut_into_the_same_rows_wherever_its_box_starts(m, frac, ulps, end, sgn, dy, blades):
    """Regression (the strict xfail of test_stress_tiling's all-edges map): a cluster source's first or last row
    came from ``floor(yc + u)``, which float32 rounds at ``yc``'s magnitude; with its end within a few ulps of a row
    edge (a mean radius of 12.000002 at a centre on the 1/256 px grid) a tile's window cut it into other rows than
    the whole frame (its graded end row one row off: 1e-4 of the brightest value). Moved down by whole rows, as a
    tile's window moves it, it deposits the very same values."""
    fy = frac / 256.0
    rho = np.float32(m + (fy if end < 0 else -fy))  # the top (end -1) or bottom (+1) edge on a row edge ...
    for _ in range(abs(ulps)):  # ... up to a few ulps
        rho = np.nextafter(rho, np.float32(np.inf if ulps > 0 else -np.inf))
    rho = max(float(rho), 0.5)
    ap = Aperture(blades=blades) if blades else Aperture()
    shape = aperture_shape(ap, ap.blade_discs(), "cpu")
    yc = m + 2 + fy
    h, w = 2 * m + 6, 2 * m + 6
    near = _cluster_deposit(w / 2, yc, sgn * rho, shape, h, w)
    far = _cluster_deposit(w / 2, yc + dy, sgn * rho, shape, h + dy, w)
    np.testing.assert_array_equal(far[dy:], near)
    assert not far[:dy].any()


@given(seed=st.integers(0, 2**31 - 1), oy=st.integers(0, 2), ox=st.integers(0, 2), cut_y=st.integers(0, 20),
       cut_x=st.integers(0, 20), mixed=st.booleans())
def test_clusters_do_not_depend_on_where_a_tiles_window_starts(seed, oy, ox, cut_y, cut_x, mixed):
    """A tile's window starts a multiple of the coarsest pyramid cell (8 px here) after the layer's box and may be cut
    anywhere at its end: every routing decision of a cell whose 3 x 3 neighbourhood lies whole in both (the salient
    sources, the clusters' members) is the same as in the whole box, and so is the clusters' light at level 0 where
    only such cells' clusters reach (their positions, radii and light)."""
    rng = np.random.default_rng(seed)
    hh, ww, side = 128, 136, 8
    src = np.zeros((hh, ww, 4), np.float32)
    src[..., :3] = rng.random((hh, ww, 3)) ** 3 * 0.5
    src[..., 3] = 1.0
    for _ in range(8):  # lamps of dim-ish pixels: clusters
        y, x, n = rng.integers(0, hh - 6), rng.integers(0, ww - 6), rng.integers(2, 7)
        src[y:y + n, x:x + n, :3] += rng.uniform(0.5, 3.0, 3).astype(np.float32)
    coc = rng.uniform(8.5, 12.0, (hh, ww)).astype(np.float32)  # level 1 ...
    far = rng.random((hh, ww)) < 0.3
    coc[far] = rng.uniform(16.5, 20.0, far.sum())  # ... and level 2: the clusters reach 21 px
    if mixed:  # near and far pixels in one layer (a checkerboard of signs, as soft edges on an all-edges map make)
        coc *= np.where((np.add.outer(np.arange(hh), np.arange(ww)) % 2) == 0, 1.0, -1.0).astype(np.float32)
    reach = int(np.ceil(np.abs(coc).max())) + 1
    y0, x0 = oy * side, ox * side
    y1, x1 = hh - cut_y, ww - cut_x
    whole, whole0 = _route(src, coc, 3, "cpu")
    part, part0 = _route(src[y0:y1, x0:x1], coc[y0:y1, x0:x1], 3, "cpu")
    # the cells of level 2 (and so of level 1) whose 3 x 3 neighbours are whole cells of the window: not at its start
    # (unless the box's), not within two cells of its cut end (unless the box's)
    py0 = 4 if y0 else 0
    px0 = 4 if x0 else 0
    py1 = y1 - y0 if y1 == hh else ((y1 - y0) // 4 - 1) * 4
    px1 = x1 - x0 if x1 == ww else ((x1 - x0) // 4 - 1) * 4
    got, want = part.exact.numpy()[py0:py1, px0:px1], whole.exact.numpy()[y0 + py0:y0 + py1, x0 + px0:x0 + px1]
    np.testing.assert_array_equal(got, want)
    # the light where only those cells' clusters reach
    qy0, qx0 = py0 + (reach if y0 else 0), px0 + (reach if x0 else 0)
    qy1, qx1 = py1 - (reach if y1 < hh else 0), px1 - (reach if x1 < ww else 0)
    got = np.cumsum(part0.numpy()[:, : x1 - x0].astype(np.float64), axis=1)[qy0:qy1, qx0:qx1]
    want = np.cumsum(whole0.numpy()[:, :ww].astype(np.float64), axis=1)[y0 + qy0:y0 + qy1, x0 + qx0:x0 + qx1]
    assert want.size and np.abs(want).max() > 0  # clusters land there
    # to float32 rounding: a span's ends are rounded at the window's magnitude (its rows are the same)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-5 * float(np.abs(want).max()))
