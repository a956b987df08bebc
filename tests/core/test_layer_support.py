"""A layer's support (``bokehray.scene``): the tiles its sources and light can reach; the preview skips the rest."""

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bokehray import Aperture, LayerOptions, MemoryOptions, edge_estimate
from bokehray import _memory as memory
from bokehray.edge_estimate import dilate
from bokehray.levels import preview as pv


def _dilate_loops(mask: np.ndarray, k: int) -> np.ndarray:
    out = np.zeros_like(mask)
    for y, x in zip(*np.nonzero(mask)):
        out[max(0, y - k) : y + k + 1, max(0, x - k) : x + k + 1] = True
    return out


@settings(max_examples=60, deadline=None)
@given(st.integers(1, 9), st.integers(1, 9), st.integers(0, 6), st.integers(0, 2**31 - 1))
def test_dilate_matches_plain_loops(h, w, k, seed):
    mask = np.random.default_rng(seed).random((h, w)) < 0.15
    np.testing.assert_array_equal(dilate(mask, k), _dilate_loops(mask, k))


def _scene(seed: int, size: int = 240) -> tuple[np.ndarray, np.ndarray]:
    """A far textured plane with lights, two near discs in opposite corners, each in a thin ring of mixed depth
    (the sparse layers a depth jump cuts, their boxes spanning the frame), signed CoC up to about 20 px."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:size, :size]
    image = rng.uniform(0.05, 1.0, (size, size, 3)).astype(np.float32)
    image[rng.random((size, size)) < 0.02] *= 50.0
    s = np.full((size, size), -rng.uniform(12, 20), np.float32)
    near = rng.uniform(2, 8)
    for cy, cx in ((40, 40), (size - 40, size - 40)):
        d = np.hypot(yy - cy - rng.uniform(-5, 5), xx - cx - rng.uniform(-5, 5))
        rad = rng.uniform(12, 20)
        s[d <= rad] = near
        ring = (d > rad) & (d <= rad + 1.5)
        s[ring] = rng.uniform(-9, -1, ring.sum())  # intermediate depths: thin layers of their own
    return image, s


def _layer_outputs(monkeypatch, image, s, tile_size=None):
    """Every layer's scatter output rendered without its support, with the support it would have had."""
    seen = []
    render_layer = pv.render_layer

    def everywhere(layer, arrays, scatter, kept=None):  # resolved everywhere: composited where ``kept`` says
        out = render_layer(dataclasses.replace(layer, support=None), arrays, scatter)
        seen.append((layer, out.numpy()))
        return out

    monkeypatch.setattr(pv, "render_layer", everywhere)
    memory = MemoryOptions(tile_size=tile_size)
    out, _ = pv.render_signed_coc(image, s, Aperture(), layers=LayerOptions(tile_px=16), memory=memory)
    return out, seen


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("tile_size", [None, 64])
def test_a_layers_light_stays_inside_its_support(monkeypatch, seed, tile_size):
    """Outside its support a layer's scattered light and coverage are nothing but the prefix sums' rounding."""
    image, s = _scene(seed)
    _, seen = _layer_outputs(monkeypatch, image, s, tile_size)
    sparse = 0
    for layer, out in seen:
        assert layer.support is not None
        y0, y1, x0, x1 = layer.bbox
        ys = (np.arange(y0, y1) + layer.origin[0]) // layer.tile_px
        xs = (np.arange(x0, x1) + layer.origin[1]) // layer.tile_px
        inside = layer.support[ys][:, xs]
        sparse += inside.mean() < 0.7
        scale = max(float(np.abs(out).max()), 1e-30)
        assert np.abs(out[~inside]).max(initial=0.0) <= 1e-6 * scale
    assert sparse > 0  # some layer's support is much smaller than its box


@pytest.mark.parametrize("seed", [0, 1])
def test_skipping_outside_the_support_leaves_the_render(monkeypatch, seed):
    image, s = _scene(seed)
    want, _ = _layer_outputs(monkeypatch, image, s)
    monkeypatch.undo()
    got, _ = pv.render_signed_coc(image, s, Aperture(), layers=LayerOptions(tile_px=16))
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("tile_size", [None, 64, 40])
@pytest.mark.parametrize("tile_px", [16, 12])
def test_the_clamped_border_is_resolved_and_composited_nowhere(monkeypatch, seed, tile_size, tile_px):
    """The frame (a tile's core) is bit for bit the crop of its whole window rendered, clamped border and halo
    resolved and composited (on a tile grid without support, 12 px, the accumulator is the whole window; cores of
    40 px are not aligned to the 16 px tiles the accumulator spans)."""
    image, s = _scene(seed)
    options = LayerOptions(tile_px=tile_px)
    memory = MemoryOptions(tile_size=tile_size)
    got, _ = pv.render_signed_coc(image, s, Aperture(), layers=options, memory=memory)
    window = pv._render_window
    crops = []

    def whole(*args):
        out, filled = window(*args[:8])  # no box to keep: every pixel of the window
        y0, y1, x0, x1 = args[8]
        crops.append(out.shape != (y1 - y0, x1 - x0))
        return np.ascontiguousarray(out[y0:y1, x0:x1]), filled

    monkeypatch.setattr(pv, "_render_window", whole)
    want, _ = pv.render_signed_coc(image, s, Aperture(), layers=options, memory=memory)
    assert all(crops) and (len(crops) == 1) == (tile_size is None)  # a border (halos) cut away every time
    assert got.tobytes() == want.tobytes()


@pytest.mark.parametrize("tile_px", [12, 4])
def test_a_tile_grid_not_a_power_of_two_or_too_fine_has_no_support(tile_px):
    from bokehray.scene import build_scene

    _, s = _scene(0)
    scene = build_scene(s, np.ones(s.shape, bool), LayerOptions(tile_px=tile_px), 8.0)
    assert all(layer.support is None for layer in scene.layers)
    got, _ = pv.render_signed_coc(*_scene(0), Aperture(), layers=LayerOptions(tile_px=tile_px))
    assert np.isfinite(got).all()


@settings(max_examples=80, deadline=None)
@given(st.lists(st.floats(-300, 300, allow_nan=False), min_size=2, max_size=9, unique=True), st.integers(0, 2**31 - 1))
def test_float32_edges_assign_every_pixel_the_float64_layer(edges, seed):
    """The layer ids from float32 edges equal those from the float64 ones, also right at the edges."""
    from bokehray.scene import float32_edges

    e = np.sort(np.array(edges, np.float64))
    rng = np.random.default_rng(seed)
    near = e.astype(np.float32)
    values = np.concatenate([rng.uniform(e[0] - 1, e[-1] + 1, 500).astype(np.float32), near,
                             np.nextafter(near, np.float32(-np.inf)), np.nextafter(near, np.float32(np.inf))])
    np.testing.assert_array_equal(np.searchsorted(float32_edges(e), values, side="right"),
                                  np.searchsorted(e, values, side="right"))


# --------------------------------------------------------------------------- the banded whole-map passes


@settings(max_examples=60, deadline=None)
@given(st.integers(1, 40), st.integers(1, 40), st.integers(1, 9), st.sampled_from(["f4", "i4", "u4", "bool"]),
       st.integers(0, 2**31 - 1))
def test_tile_reduce_equals_padding_the_map(h, w, tile, dtype, seed):
    """Rows of each cell then columns: the values of the padded (th, tile, tw, tile) reduction, partial cells
    (padded with ``fill``), NaN and the uint32 view of -1 included."""
    from bokehray.scene import tile_max, tile_reduce, tile_reduce_in_parts

    rng = np.random.default_rng(seed)
    v = rng.integers(-3, 5, (h, w)).astype(dtype) if dtype != "bool" else rng.random((h, w)) < 0.1
    if dtype == "f4":
        v[rng.random((h, w)) < 0.05] = np.nan
    th, tw = -(-h // tile), -(-w // tile)
    for fill, op, name in ((0, np.maximum, "max"), (np.iinfo(np.int32).max if dtype == "i4" else 1, np.minimum, "min")):
        fill = np.array(fill).astype(v.dtype)
        pad = np.full((th * tile, tw * tile), fill, v.dtype)
        pad[:h, :w] = v
        want = getattr(pad.reshape(th, tile, tw, tile), name)(axis=(1, 3))
        got = tile_reduce(v, tile, fill, op)
        assert got.dtype == want.dtype
        np.testing.assert_array_equal(got, want)
        with pytest.MonkeyPatch.context() as m:  # whole tile rows a part, on up to four threads
            _in_parts(m, rng)
            in_parts = tile_reduce_in_parts(v, tile, fill, op)
        assert in_parts.dtype == want.dtype
        np.testing.assert_array_equal(in_parts, want)
    np.testing.assert_array_equal(tile_max(v, tile), tile_reduce(v, tile, 0, np.maximum))


def _in_parts(m: pytest.MonkeyPatch, rng: np.random.Generator) -> None:
    """Small frames cut into 1 to 4 row parts on as many threads (``edge_estimate.row_parts``)."""
    m.setattr(edge_estimate, "PIXELS_PER_THREAD", int(rng.integers(1, 300)))
    cores = int(rng.integers(1, 5))
    m.setattr(edge_estimate.os, "cpu_count", lambda: cores)


@settings(max_examples=40, deadline=None)
@given(st.integers(1, 60), st.integers(1, 50), st.integers(1, 9), st.integers(1, 400), st.integers(0, 2**31 - 1))
def test_layer_ids_and_histogram_in_bands_equal_the_whole_map(h, w, n_edges, band_px, seed):
    """The banded ids, counts and histogram equal the whole-map expressions they replace, bands cut mid-row."""
    import bokehray.scene as sc

    rng = np.random.default_rng(seed)
    s = (rng.standard_normal((h, w)) * 30).astype(np.float32)
    active = rng.random((h, w)) < 0.8
    e = np.sort(rng.uniform(-40, 40, n_edges + 1))
    e32 = sc.float32_edges(e)
    want = np.clip((np.searchsorted(e32, s, side="right") - 1).astype(np.int32), 0, n_edges - 1)
    want[~active] = -1
    values = s[active]
    lo = float(values.min()) if values.size else 0.0
    n_bins = int(np.ceil((float(s.max()) - lo) / 0.25)) + 1
    with pytest.MonkeyPatch.context() as m:
        m.setattr(memory, "BAND_PX", band_px)
        _in_parts(m, rng)
        ids, counts = sc._layer_ids(s, active, e32, n_edges)
        hist = sc._histogram([values[:7], values[7:]], lo, 0.25, n_bins)
    assert ids.dtype == np.int32
    np.testing.assert_array_equal(ids, want)
    np.testing.assert_array_equal(counts, np.bincount(want[active], minlength=n_edges))
    np.testing.assert_array_equal(hist, np.bincount(((values - lo) / 0.25).astype(np.int64), minlength=n_bins))


@settings(max_examples=40, deadline=None)
@given(st.integers(1, 60), st.integers(1, 50), st.integers(0, 30), st.integers(1, 400), st.booleans(),
       st.integers(0, 2**31 - 1))
def test_layer_edges_of_the_active_values_in_bands_equal_the_gathered_ones(h, w, n_extra, band_px, wide, seed):
    """split_scene and build_scene cut the layers on s[active] (and the near parts) read band by band: the
    extremes and edges of the gathered array, float64 maps (cast to float32 by layer_edges) included."""
    import bokehray.scene as sc

    rng = np.random.default_rng(seed)
    s = (rng.standard_normal((h, w)) * rng.uniform(0.3, 40)).astype(np.float64 if wide else np.float32)
    active = rng.random((h, w)) < 0.7
    active.ravel()[0] = True
    extra = (rng.standard_normal(n_extra) * 20).astype(np.float32)
    values = np.concatenate([s[active], extra])
    opts = LayerOptions(max_layers=int(rng.integers(1, 12)), max_layer_px=float(rng.uniform(0.5, 10)))
    with pytest.MonkeyPatch.context() as m:
        m.setattr(memory, "BAND_PX", band_px)
        _in_parts(m, rng)
        parts, lo, hi, lo32, hi32 = sc._active_values(s, active, extra)
        got = sc._layer_edges_of(parts, lo32, hi32, opts)
        assert np.array_equal(np.concatenate([v for group in parts for v in group()]), values.astype(np.float32))
    assert (lo, hi) == (float(values.min()), float(values.max()))
    v32 = values.astype(np.float32)
    assert (lo32, hi32) == (float(v32.min()), float(v32.max()))
    np.testing.assert_array_equal(got, sc.layer_edges(values, opts))


@settings(max_examples=40, deadline=None)
@given(st.integers(1, 70), st.integers(1, 50), st.sampled_from([1, 2, 4, 8, 16]), st.integers(1, 400),
       st.integers(0, 40), st.integers(0, 2**31 - 1))
def test_radius_tile_max_and_rims_equal_the_soft_radius_map(h, w, tile, band_px, n_split, seed):
    """The copied tiles and the clamped border read the radius a pixel's light can have (``soft_radius``) without
    the frame-sized map: its tile maxima in bands of tile rows on row parts, its rims from the rims."""
    import bokehray.scene as sc

    rng = np.random.default_rng(seed)
    s = (rng.standard_normal((h, w)) * rng.uniform(0.1, 20)).astype(np.float32)
    index = np.unique(rng.integers(0, h * w, n_split)).astype(np.int64)
    n = index.size
    f = rng.standard_normal(n).astype(np.float32) * 30
    soft = sc.SoftEdges(index, np.full(n, 0.5, np.float32), np.zeros((n, 3), np.float32),
                        np.zeros((n, 3), np.float32), f, f - 3) if n else None
    r = sc.soft_radius(s, soft)
    with pytest.MonkeyPatch.context() as m:
        m.setattr(memory, "BAND_PX", band_px)
        _in_parts(m, rng)
        got = sc.radius_tile_max(s, soft, tile)
        rims = sc.rim_radii(s, soft)
    assert got.dtype == r.dtype
    np.testing.assert_array_equal(got, sc.tile_max(r, tile))
    np.testing.assert_array_equal(sc.copy_tiles_of(got, tile), sc.copy_tiles(r, tile))
    for rim, want in zip(rims, (r[0], r[-1], r[:, 0], r[:, -1]), strict=True):
        np.testing.assert_array_equal(rim, want)
    radii = [float(np.abs(v).max()) for v in (s[0], s[-1], s[:, 0], s[:, -1])]  # the pads as the rims define them
    want = (0,) * 4 if max(radii) > 0.5 * max(h, w) else tuple(
        -(-(int(np.ceil(v)) + 1) // tile) * tile if v >= 0.5 else 0 for v in radii)
    assert pv.border_pad(s, tile) == want
