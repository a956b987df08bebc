"""The hidden-region fill kernels (bokehray_kernels.fill) against their float64 NumPy oracle (reference.fill_ref).

Each kernel on small random inputs (shapes, layer ids, window offsets; odd sizes and 1 x 1
included), the whole chain as the preview launcher runs it, and the invariants docs/renderer.md
promises: the layer's own pixels pass through, the filled colour stays within the visible
colours, nothing is filled where nothing is hidden, and the distance gate holds.
All launches on the CPU device.
"""

import math

import bokehray_kernels as bk
import numpy as np
import pytest
import warp as wp
from hypothesis import assume, given
from hypothesis import strategies as st
from reference import fill_ref
from tolerances import KERNEL_VS_REFERENCE_ATOL

DEVICE = "cpu"
ATOL = KERNEL_VS_REFERENCE_ATOL
BIG = 1e8  # a kernel distance at least this large means "no pixel of the layer in the window" (about 1e9)



def _pp(total, weight, known) -> bk.PullPushLevel:
    """A pull-push level as the fill kernels take it."""
    lv = bk.PullPushLevel()
    lv.total, lv.weight, lv.known = total, weight, known
    return lv

def _colour_tol(c) -> np.ndarray:
    """KERNEL_VS_REFERENCE_ATOL in tone-mapped units, carried through c = t / (1 - t) (dc/dt = (1 + c)^2)."""
    return ATOL * (1.0 + np.abs(np.asarray(c, np.float64))) ** 2


def _wp(a, dtype):
    return wp.array(np.ascontiguousarray(a, np.float32 if dtype is not wp.int32 else np.int32), dtype=dtype,
                    device=DEVICE)


def _assert_dist(got, want):
    far = np.isinf(want)
    assert np.all(got[far] >= BIG), "a window row/column without the layer must read as far away"
    np.testing.assert_array_equal(got[~far], want[~far])


# --- inputs -------------------------------------------------------------------------------------


@st.composite
def scenes(draw, max_side: int = 12):
    """A frame with a window (the layer's bounding box) and per-pixel slice ids, colours and signed CoC.

    ``mode``: iid random ids; or discs of nearer layers over a farther one (realistic hidden regions),
    optionally with inactive (-1, copied) pixels sprinkled in.
    """
    h = draw(st.integers(1, max_side))
    w = draw(st.integers(1, max_side))
    y0, x0 = draw(st.integers(0, 3)), draw(st.integers(0, 3))
    hh, ww = y0 + h + draw(st.integers(0, 3)), x0 + w + draw(st.integers(0, 3))
    n_layers = draw(st.sampled_from([1, 2, 2, 3, 3, 4, 4]))  # one layer: nothing nearer, rarely
    # mostly a layer with nearer ones (something can hide it), sometimes any layer
    anywhere = n_layers == 1 or draw(st.integers(0, 3)) == 0
    layer = draw(st.integers(0, n_layers - 1 if anywhere else n_layers - 2))
    mode = draw(st.sampled_from(["random", "discs", "discs+inactive"]))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    if mode == "random":
        sid = rng.integers(-1, n_layers, (hh, ww))
    else:
        # mostly a visible layer (or one behind it) with nearer discs over it: a region to fill
        sid = np.full((hh, ww), rng.integers(0, layer + 1) if rng.random() < 0.8 else rng.integers(0, n_layers))
        yy, xx = np.mgrid[:hh, :ww]
        for _ in range(rng.integers(1, 4)):
            cy, cx = rng.uniform(-1, hh), rng.uniform(-1, ww)
            rad = rng.uniform(0.5, max(hh, ww) / 2)
            nearer = layer + 1 < n_layers and rng.random() < 0.7
            sid[(yy - cy) ** 2 + (xx - cx) ** 2 <= rad * rad] = (
                rng.integers(layer + 1, n_layers) if nearer else rng.integers(0, n_layers))
        if mode == "discs+inactive":
            sid[rng.random((hh, ww)) < 0.15] = -1
    # layer i holds the signed CoC range [edges[i], edges[i + 1]); inactive pixels are in focus
    edges = np.cumsum(np.concatenate([[-12.0], rng.uniform(0.5, 8.0, n_layers)]))
    ids = np.clip(sid, 0, None)
    scoc = edges[ids] + rng.uniform(0, 1, (hh, ww)) * (edges[ids + 1] - edges[ids])
    scoc[sid < 0] = rng.uniform(-0.49, 0.49, (hh, ww))[sid < 0]
    image = rng.uniform(0.0, 1.0, (hh, ww, 3))
    bright = rng.random((hh, ww)) < 0.1
    image[bright] *= 40.0  # bokeh-ball highlights: the tone map must keep them from flooding
    return {
        "image": image.astype(np.float32), "scoc": scoc.astype(np.float32), "sid": sid.astype(np.int32),
        "layer": int(layer), "bbox": (y0, y0 + h, x0, x0 + w), "n_layers": n_layers,
        "s_lo": float(edges[layer]), "s_hi": float(edges[layer + 1]),
    }


def _run_fill(scene, pull_levels, band: int = 64, rows: bool = False) -> dict:
    """The kernel chain in the launch order of ``bokehray.scene.build_layer_sources``; ``rows``: a row a thread, as
    the CPU launches them, else a pixel a thread."""

    def launch(name: str, dim: tuple[int, int], inputs: list, **kw) -> None:  # a pixel a thread, or a row
        span = max(1, dim[1]) if rows else 1
        wp.launch(getattr(bk, name), dim=(dim[0], -(-dim[1] // span)), inputs=[span, *inputs], device=DEVICE, **kw)

    y0, y1, x0, x1 = scene["bbox"]
    h, w = y1 - y0, x1 - x0
    layer = scene["layer"]
    fill = pull_levels is not None
    image, scoc, sid = _wp(scene["image"], wp.vec3), _wp(scene["scoc"], float), _wp(scene["sid"], wp.int32)
    src = wp.zeros((h, w), dtype=wp.vec4, device=DEVICE)  # the kernel writes the layer's pixels only
    coc = wp.zeros((h, w), dtype=float, device=DEVICE)
    filled = wp.zeros(scene["n_layers"], dtype=wp.int32, device=DEVICE)
    none = wp.zeros((1, 1), dtype=float, device=DEVICE)
    launch("layer_sources_kernel", (h, w), inputs=[image, scoc, sid, layer, x0, y0, 0],
           outputs=[src, coc, _pp(wp.zeros((1, 1), dtype=wp.vec4, device=DEVICE), none, none)])
    out = {}
    if fill:
        totals, weights, knowns = [], [], []  # index i: level i + 1 (level 0 is never stored)
        for lv in range(1, pull_levels + 1):
            shape = ((h + (1 << lv) - 1) >> lv, (w + (1 << lv) - 1) >> lv)
            totals.append(wp.empty(shape, dtype=wp.vec4, device=DEVICE))
            weights.append(wp.empty(shape, dtype=float, device=DEVICE))
            knowns.append(wp.empty(shape, dtype=float, device=DEVICE))
            if lv == 1:
                launch("layer_pull_kernel", shape, inputs=[image, scoc, sid, layer, x0, y0, h, w],
                       outputs=[_pp(totals[-1], weights[-1], knowns[-1])])
            else:
                wp.launch(bk.pull_kernel, dim=shape, inputs=[_pp(totals[-2], weights[-2], knowns[-2])],
                          outputs=[_pp(totals[-1], weights[-1], knowns[-1])], device=DEVICE)
        top = len(totals) - 1
        for i in range(top, -1, -1):  # as the preview: down to level 1
            c = min(i + 1, top)
            launch("push_kernel", totals[i].shape, inputs=[_pp(totals[c], weights[c], knowns[c]), int(i == top)],
                   outputs=[_pp(totals[i], weights[i], knowns[i])])
        dist = wp.empty((h, w), dtype=float, device=DEVICE)
        wp.launch(bk.row_distance_kernel, dim=h, inputs=[sid, layer, x0, y0, w], outputs=[dist], device=DEVICE)
        wp.launch(bk.column_distance_kernel, dim=(w + band - 1) // band, inputs=[dist, h, band], device=DEVICE)
        launch("fill_sources_kernel", (h, w),
               inputs=[sid, layer, x0, y0, _pp(totals[0], weights[0], knowns[0]), dist, scoc, scene["s_lo"],
                       scene["s_hi"]],
               outputs=[src, coc, filled])
        # level 0 stored and pushed as a whole (what the fill pushed texel by texel), for the comparison with the
        # oracle
        lv0 = [wp.zeros((h, w), dtype=wp.vec4, device=DEVICE), wp.zeros((h, w), dtype=float, device=DEVICE),
               wp.zeros((h, w), dtype=float, device=DEVICE)]
        wp.launch(bk.layer_sources_kernel, dim=(h, w), inputs=[1, image, scoc, sid, layer, x0, y0, 1],
                  outputs=[wp.zeros((h, w), dtype=wp.vec4, device=DEVICE), wp.zeros((h, w), dtype=float, device=DEVICE),
                           _pp(*lv0)], device=DEVICE)
        wp.launch(bk.push_kernel, dim=(h, w), inputs=[1, _pp(totals[0], weights[0], knowns[0]), 0],
                  outputs=[_pp(*lv0)], device=DEVICE)
        out.update(value=lv0[0].numpy(), density=lv0[1].numpy(), has=lv0[2].numpy(), distance=dist.numpy())
    out.update(src=src.numpy(), coc=coc.numpy(), n_filled=filled.numpy())
    return out


def _oracle(scene, pull_levels) -> dict:
    return fill_ref.layer_fill(scene["image"], scene["scoc"], scene["sid"], scene["layer"], scene["bbox"],
                               scene["s_lo"], scene["s_hi"], pull_levels, scene["n_layers"])


def _gate_is_ambiguous(scene, want) -> bool:
    """True where float32 rounding could decide the distance gate or the density cut the other way."""
    y0, y1, x0, x1 = scene["bbox"]
    hidden = scene["sid"][y0:y1, x0:x1] > scene["layer"]
    reach = fill_ref.SQRT2 * np.abs(scene["scoc"][y0:y1, x0:x1].astype(np.float64)) + 1.0
    near_gate = np.abs(want["distance"] - reach) <= 1e-5 * reach
    near_cut = np.abs(want["density"] - fill_ref.MIN_FILL_DENSITY) <= 1e-6
    return bool(np.any(hidden & (near_gate | near_cut)))


# --- each kernel against its oracle ---------------------------------------------------------------


@given(scene=scenes(), with_fill=st.booleans())
def test_layer_sources_kernel_matches_reference(scene, with_fill):
    y0, y1, x0, x1 = scene["bbox"]
    h, w = y1 - y0, x1 - x0
    layer = scene["layer"]
    src, coc = wp.zeros((h, w), dtype=wp.vec4, device=DEVICE), wp.zeros((h, w), dtype=float, device=DEVICE)
    total = wp.zeros((h, w), dtype=wp.vec4, device=DEVICE)
    weight, known = wp.zeros((h, w), dtype=float, device=DEVICE), wp.zeros((h, w), dtype=float, device=DEVICE)
    wp.launch(bk.layer_sources_kernel, dim=(h, w),
              inputs=[1, _wp(scene["image"], wp.vec3), _wp(scene["scoc"], float), _wp(scene["sid"], wp.int32), layer,
                      x0, y0, int(with_fill)],
              outputs=[src, coc, _pp(total, weight, known)], device=DEVICE)
    want = fill_ref.layer_sources(scene["image"], scene["scoc"], scene["sid"], layer, x0, y0, h, w, with_fill)
    np.testing.assert_array_equal(src.numpy(), want[0].astype(np.float32))  # a copy, no arithmetic
    np.testing.assert_array_equal(coc.numpy(), want[1].astype(np.float32))
    if with_fill:
        np.testing.assert_allclose(total.numpy(), want[2], rtol=0, atol=ATOL)
        np.testing.assert_array_equal(weight.numpy(), want[3])
        np.testing.assert_array_equal(known.numpy(), want[4])


def _level_sums(rng, h, w, depth):
    """Random sums of a level ``depth`` steps above level 0: counts 0 <= weight <= known <= 4^depth."""
    known = rng.integers(0, 4 ** depth + 1, (h, w)).astype(np.float64)
    known[rng.random((h, w)) < 0.3] = 0.0
    weight = np.floor(rng.random((h, w)) * (known + 1))
    weight[rng.random((h, w)) < 0.3] = 0.0
    total = rng.uniform(0, 1, (h, w, 4)) * weight[..., None]
    total[..., 3] = rng.uniform(-12, 12, (h, w)) * weight
    return total, weight, known


@given(h=st.integers(1, 13), w=st.integers(1, 13), depth=st.integers(0, 3), seed=st.integers(0, 2**32 - 1))
def test_pull_kernel_matches_reference(h, w, depth, seed):
    total, weight, known = _level_sums(np.random.default_rng(seed), h, w, depth)
    ch, cw = (h + 1) // 2, (w + 1) // 2
    out = [wp.empty((ch, cw), dtype=wp.vec4, device=DEVICE), wp.empty((ch, cw), dtype=float, device=DEVICE),
           wp.empty((ch, cw), dtype=float, device=DEVICE)]
    wp.launch(bk.pull_kernel, dim=(ch, cw), inputs=[_pp(_wp(total, wp.vec4), _wp(weight, float), _wp(known, float))],
              outputs=[_pp(*out)], device=DEVICE)
    want = fill_ref.pull(total, weight, known)
    for got, ref in zip(out, want):
        np.testing.assert_allclose(got.numpy(), ref, rtol=1e-6, atol=ATOL)
    # nothing is lost between levels
    np.testing.assert_allclose(out[1].numpy().sum(), weight.sum(), rtol=1e-6)


@given(scene=scenes(), pull_levels=st.sampled_from([None, 1, 2, 4]))
def test_row_kernels_store_the_pixel_kernels_values(scene, pull_levels):
    """The CPU's row-a-thread twins (layer sources, level 1's pull, push, fill sources) store what the kernels of a
    thread a pixel store, bit for bit."""
    got, want = _run_fill(scene, pull_levels, rows=True), _run_fill(scene, pull_levels)
    for name, a in want.items():
        assert got[name].tobytes() == a.tobytes(), name


@given(scene=scenes())
def test_layer_pull_kernel_matches_reference(scene):
    """Level 1 straight from the photo: the oracle's pull of its level 0, and bit for bit ``pull_kernel`` of the
    level 0 ``layer_sources_kernel`` writes (the fill's values do not change for not storing level 0)."""
    y0, y1, x0, x1 = scene["bbox"]
    h, w = y1 - y0, x1 - x0
    layer = scene["layer"]
    image, scoc, sid = _wp(scene["image"], wp.vec3), _wp(scene["scoc"], float), _wp(scene["sid"], wp.int32)
    ch, cw = (h + 1) // 2, (w + 1) // 2

    def level(shape):
        return [wp.zeros(shape, dtype=wp.vec4, device=DEVICE), wp.zeros(shape, dtype=float, device=DEVICE),
                wp.zeros(shape, dtype=float, device=DEVICE)]

    got = level((ch, cw))
    wp.launch(bk.layer_pull_kernel, dim=(ch, cw), inputs=[1, image, scoc, sid, layer, x0, y0, h, w],
              outputs=[_pp(*got)], device=DEVICE)
    lv0, pulled = level((h, w)), level((ch, cw))
    wp.launch(bk.layer_sources_kernel, dim=(h, w), inputs=[1, image, scoc, sid, layer, x0, y0, 1],
              outputs=[wp.zeros((h, w), dtype=wp.vec4, device=DEVICE), wp.zeros((h, w), dtype=float, device=DEVICE),
                       _pp(*lv0)], device=DEVICE)
    wp.launch(bk.pull_kernel, dim=(ch, cw), inputs=[_pp(*lv0)], outputs=[_pp(*pulled)], device=DEVICE)
    for a, b in zip(got, pulled):
        assert a.numpy().tobytes() == b.numpy().tobytes()
    _, _, total, weight, known = fill_ref.layer_sources(scene["image"], scene["scoc"], scene["sid"], layer, x0, y0,
                                                        h, w, True)
    want = fill_ref.pull(total, weight, known)
    np.testing.assert_allclose(got[0].numpy(), want[0], rtol=1e-6, atol=4 * ATOL)
    np.testing.assert_array_equal(got[1].numpy(), want[1])
    np.testing.assert_array_equal(got[2].numpy(), want[2])


@given(h=st.integers(1, 13), w=st.integers(1, 13), depth=st.integers(0, 3), top=st.booleans(),
       seed=st.integers(0, 2**32 - 1))
def test_push_kernel_matches_reference(h, w, depth, top, seed):
    rng = np.random.default_rng(seed)
    total, weight, known = _level_sums(rng, h, w, depth)
    ch, cw = (h + 1) // 2, (w + 1) // 2
    # an already pushed coarser level: values, densities (0 or clearly positive) and has flags
    c_value = rng.uniform(0, 1, (ch, cw, 4))
    c_value[..., 3] = rng.uniform(-12, 12, (ch, cw))
    c_density = np.where(rng.random((ch, cw)) < 0.3, 0.0, rng.uniform(0.01, 1.0, (ch, cw)))
    c_has = (rng.random((ch, cw)) < 0.7).astype(np.float64)
    arrays = [_wp(total, wp.vec4), _wp(weight, float), _wp(known, float)]
    wp.launch(bk.push_kernel, dim=(h, w), inputs=[1, _pp(_wp(c_value, wp.vec4), _wp(c_density, float), _wp(c_has, float)),
                                                  int(top)], outputs=[_pp(*arrays)], device=DEVICE)
    value, density, has = fill_ref.push(c_value, c_density, c_has, top, total, weight, known)
    np.testing.assert_allclose(arrays[0].numpy(), value, rtol=1e-6, atol=ATOL)
    np.testing.assert_allclose(arrays[1].numpy(), density, rtol=1e-6, atol=ATOL)
    np.testing.assert_array_equal(arrays[2].numpy(), has)


@given(scene=scenes())
def test_row_distance_kernel_matches_reference(scene):
    y0, y1, x0, x1 = scene["bbox"]
    h, w = y1 - y0, x1 - x0
    dist = wp.empty((h, w), dtype=float, device=DEVICE)
    wp.launch(bk.row_distance_kernel, dim=h, inputs=[_wp(scene["sid"], wp.int32), scene["layer"], x0, y0, w],
              outputs=[dist], device=DEVICE)
    _assert_dist(dist.numpy(), fill_ref.row_distance(scene["sid"], scene["layer"], x0, y0, w, h))


@given(h=st.integers(1, 13), w=st.integers(1, 13), band=st.sampled_from([1, 2, 3, 5, 64]),
       short=st.integers(0, 2), seed=st.integers(0, 2**32 - 1))
def test_column_distance_kernel_matches_reference(h, w, band, short, seed):
    """Any input (not only row distances); ``height`` below the array's rows leaves the rest alone."""
    rng = np.random.default_rng(seed)
    height = max(1, h - short)
    src = rng.integers(0, 20, (h, w)).astype(np.float64)
    src[rng.random((h, w)) < 0.3] = 1e9
    dist = _wp(src, float)
    wp.launch(bk.column_distance_kernel, dim=(w + band - 1) // band, inputs=[dist, height, band], device=DEVICE)
    np.testing.assert_array_equal(dist.numpy(), fill_ref.column_distance(src, height, band).astype(np.float32))


@given(scene=scenes(), band=st.sampled_from([1, 3, 64]))
def test_row_then_column_pass_is_the_city_block_distance(scene, band):
    """The two passes together equal the brute-force L1 distance to the layer's pixels in the window."""
    y0, y1, x0, x1 = scene["bbox"]
    h, w = y1 - y0, x1 - x0
    dist = wp.empty((h, w), dtype=float, device=DEVICE)
    wp.launch(bk.row_distance_kernel, dim=h, inputs=[_wp(scene["sid"], wp.int32), scene["layer"], x0, y0, w],
              outputs=[dist], device=DEVICE)
    wp.launch(bk.column_distance_kernel, dim=(w + band - 1) // band, inputs=[dist, h, band], device=DEVICE)
    _assert_dist(dist.numpy(), fill_ref.l1_distance(scene["sid"], scene["layer"], x0, y0, h, w))


@given(scene=scenes(), seed=st.integers(0, 2**32 - 1))
def test_fill_sources_kernel_matches_reference(scene, seed):
    """Arbitrary pushed level 1 (densities around the cut, some above 1), distances, prior sources, CoC beyond the
    layer's range: the kernel pushes each hidden texel itself (its level-0 sums are zero: no pixel of the layer
    and none visible), then fills."""
    rng = np.random.default_rng(seed)
    y0, y1, x0, x1 = scene["bbox"]
    h, w = y1 - y0, x1 - x0
    layer = scene["layer"]
    total, weight, known = np.zeros((h, w, 4)), np.zeros((h, w)), np.zeros((h, w))
    ch, cw = (h + 1) // 2, (w + 1) // 2
    c_value = rng.uniform(0, 0.98, (ch, cw, 4))
    c_value[..., 3] = rng.uniform(-20, 20, (ch, cw))
    # empty, around the MIN_FILL_DENSITY cut, partial, opaque, and above 1 (clipped to an opacity of 1)
    c_density = rng.choice([0.0, 0.04, 0.5, 1.0, 1.3], (ch, cw)) * rng.uniform(0.25, 1.0, (ch, cw))
    c_density = c_density.astype(np.float32).astype(np.float64)
    c_has = (rng.random((ch, cw)) < 0.8).astype(np.float64)
    value, density, _ = fill_ref.push(c_value, c_density, c_has, False, total, weight, known)
    dist = rng.integers(0, 12, (h, w)).astype(np.float64)
    dist[rng.random((h, w)) < 0.1] = 1e9
    src0 = rng.uniform(0, 2, (h, w, 4))
    coc0 = rng.uniform(-5, 5, (h, w))
    n0 = rng.integers(0, 5, scene["n_layers"])
    reach = fill_ref.SQRT2 * np.abs(scene["scoc"][y0:y1, x0:x1].astype(np.float64)) + 1.0
    assume(not np.any(np.abs(dist - reach) <= 1e-5 * reach))
    assume(not np.any(np.abs(density - fill_ref.MIN_FILL_DENSITY) <= 1e-5))
    src, coc, filled = _wp(src0, wp.vec4), _wp(coc0, float), wp.array(n0.astype(np.int32), device=DEVICE)
    wp.launch(bk.fill_sources_kernel, dim=(h, w),
              inputs=[1, _wp(scene["sid"], wp.int32), layer, x0, y0,
                      _pp(_wp(c_value, wp.vec4), _wp(c_density, float), _wp(c_has, float)),
                      _wp(dist, float), _wp(scene["scoc"], float), scene["s_lo"], scene["s_hi"]],
              outputs=[src, coc, filled], device=DEVICE)
    w_src, w_coc, w_n = fill_ref.fill_sources(scene["sid"], layer, x0, y0, value, density, dist, scene["scoc"],
                                              scene["s_lo"], scene["s_hi"], src0.astype(np.float32),
                                              coc0.astype(np.float32), n0)
    got = src.numpy()
    assert np.all(np.abs(got - w_src) <= _colour_tol(w_src) + 1e-5 * np.abs(w_src))
    np.testing.assert_allclose(coc.numpy(), w_coc, rtol=1e-5, atol=ATOL)
    np.testing.assert_array_equal(filled.numpy(), w_n)


# --- the chain ------------------------------------------------------------------------------------


@given(scene=scenes(), pull_levels=st.integers(1, 5), band=st.sampled_from([1, 3, 64]))
def test_composed_fill_matches_reference(scene, pull_levels, band):
    want = _oracle(scene, pull_levels)
    assume(not _gate_is_ambiguous(scene, want))
    got = _run_fill(scene, pull_levels, band)
    np.testing.assert_array_equal(got["has"], want["has"])
    np.testing.assert_allclose(got["density"], want["density"], rtol=1e-5, atol=ATOL)
    # the colour only matters where there is some layer to fill with
    some = want["density"] >= fill_ref.MIN_FILL_DENSITY
    np.testing.assert_allclose(got["value"][some], want["value"][some], rtol=1e-5, atol=ATOL)
    _assert_dist(got["distance"], want["distance"])
    assert np.all(np.abs(got["src"] - want["src"]) <= _colour_tol(want["src"]))
    np.testing.assert_allclose(got["coc"], want["coc"], rtol=1e-5, atol=ATOL)
    np.testing.assert_array_equal(got["n_filled"], want["n_filled"])


@given(scene=scenes())
def test_no_fill_gives_the_layer_pixels_only(scene):
    got, want = _run_fill(scene, None), _oracle(scene, None)
    np.testing.assert_array_equal(got["src"], want["src"].astype(np.float32))
    np.testing.assert_array_equal(got["coc"], want["coc"].astype(np.float32))
    assert not got["n_filled"].any()


def _planned_scene(seed: int, size: int = 32):
    """A blurred disc in front of a textured, tilted background: disparity -> signed CoC -> plan_layers."""
    from bokehray.options import LayerOptions
    from bokehray.scene import build_scene

    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:size, :size]
    disp = 0.2 + 0.1 * xx / size
    cy, cx, rad = rng.uniform(8, size - 8, 2).tolist() + [rng.uniform(4, 9)]
    disp[(yy - cy) ** 2 + (xx - cx) ** 2 <= rad * rad] = 0.8
    image = rng.uniform(0.0, 1.0, (size, size, 3)).astype(np.float32)
    image[rng.random((size, size)) < 0.05] *= 30.0
    scoc = (rng.uniform(6, 14) * (disp - 0.5)).astype(np.float32)
    scene = build_scene(scoc, np.ones((size, size), bool), LayerOptions(tile_px=8), level_radius_px=8.0)
    return image, scoc, scene.ids, scene.layers


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_host_layer_sources_matches_reference(seed):
    """The launcher itself (bokehray.scene.build_layer_sources) on planned layers, against the composed oracle."""
    from bokehray.scene import LayerSources, build_layer_sources, pull_levels

    image, scoc, sid, layers = _planned_scene(seed)
    n = int(sid.max()) + 1
    assert any(la.fill_reach >= 0.5 for la in layers), "the scene must exercise the fill"
    for la in layers:
        arrays = LayerSources.upload(image, scoc, sid, n, DEVICE)
        src, coc = build_layer_sources(la, arrays)
        filled = arrays.filled
        levels = pull_levels(la.fill_reach) if la.filled else None
        want = fill_ref.layer_fill(image, scoc, sid, la.index, la.bbox, la.s_lo, la.s_hi, levels, n)
        assert np.all(np.abs(src.numpy() - want["src"]) <= _colour_tol(want["src"]))
        np.testing.assert_allclose(coc.numpy(), want["coc"], rtol=1e-5, atol=ATOL)
        np.testing.assert_array_equal(filled.numpy(), want["n_filled"])
        if levels is not None:
            assert want["n_filled"][la.index] > 0, "a layer behind the blurred disc gets filled sources"


# --- invariants -----------------------------------------------------------------------------------


def _window(scene, key):
    y0, y1, x0, x1 = scene["bbox"]
    return scene[key][y0:y1, x0:x1]


@given(scene=scenes(), pull_levels=st.integers(1, 5))
def test_layer_pixels_pass_through_unchanged(scene, pull_levels):
    got = _run_fill(scene, pull_levels)
    own = _window(scene, "sid") == scene["layer"]
    np.testing.assert_array_equal(got["src"][own][:, :3], _window(scene, "image")[own])
    np.testing.assert_array_equal(got["src"][own][:, 3], 1.0)
    np.testing.assert_array_equal(got["coc"][own], _window(scene, "scoc")[own])
    # visible pixels of other (farther) layers and inactive pixels get nothing
    other = (_window(scene, "sid") <= scene["layer"]) & ~own
    assert not got["src"][other].any() and not got["coc"][other].any()


@given(scene=scenes(), pull_levels=st.integers(1, 5))
def test_filled_colour_stays_within_the_visible_colours(scene, pull_levels):
    """Pull-push of tone-mapped colour is a convex combination: every channel within the layer's range."""
    got = _run_fill(scene, pull_levels)
    own = _window(scene, "sid") == scene["layer"]
    filled = (_window(scene, "sid") > scene["layer"]) & (got["src"][..., 3] > 0)
    assume(filled.any())
    a = got["src"][filled][:, 3:4].astype(np.float64)
    assert np.all(a <= 1.0)
    colour = got["src"][filled][:, :3] / a
    visible = _window(scene, "image")[own].astype(np.float64)
    lo, hi = visible.min(axis=0), visible.max(axis=0)
    assert np.all(colour >= lo - _colour_tol(lo)), (colour.min(axis=0), lo)
    assert np.all(colour <= hi + _colour_tol(hi)), (colour.max(axis=0), hi)
    s_own = _window(scene, "scoc")[own]
    s_fill = got["coc"][filled]
    assert np.all(s_fill >= s_own.min() - ATOL) and np.all(s_fill <= s_own.max() + ATOL)


@given(scene=scenes(), pull_levels=st.integers(1, 5))
def test_no_hidden_region_no_filled_sources(scene, pull_levels):
    """The nearest layer present in the window hides nothing of itself: it gets its own pixels only."""
    sid = _window(scene, "sid")
    assume((sid >= 0).any())
    scene = dict(scene, layer=int(sid.max()))
    got, plain = _run_fill(scene, pull_levels), _run_fill(scene, None)
    assert not got["n_filled"].any()
    np.testing.assert_array_equal(got["src"], plain["src"])
    np.testing.assert_array_equal(got["coc"], plain["coc"])


@given(scene=scenes(), pull_levels=st.integers(1, 5))
def test_distance_gate(scene, pull_levels):
    """Filled sources lie where the hider is blurred enough: L1 distance <= sqrt(2) r_hider + 1, and there
    every hidden pixel with a density of at least MIN_FILL_DENSITY is filled."""
    got = _run_fill(scene, pull_levels)
    sid = _window(scene, "sid")
    hidden = sid > scene["layer"]
    dist = fill_ref.l1_distance(scene["sid"], scene["layer"], scene["bbox"][2], scene["bbox"][0], *sid.shape)
    reach = fill_ref.SQRT2 * np.abs(_window(scene, "scoc").astype(np.float64)) + 1.0
    filled = hidden & (got["src"][..., 3] > 0)
    assert np.all(dist[filled] <= reach[filled] * (1 + 1e-6))
    assert int(filled.sum()) == int(got["n_filled"][scene["layer"]])
    inside = hidden & (dist < reach * (1 - 1e-6)) & (got["density"] >= fill_ref.MIN_FILL_DENSITY + 1e-6)
    assert np.all(filled[inside])


def test_sharp_occluder_reveals_only_its_rim():
    """A sharp (r = 0) nearer layer lets through only the 1 px rim; a blurred one up to sqrt(2) r + 1."""
    size = 21
    yy, xx = np.mgrid[:size, :size]
    disc = (yy - 10) ** 2 + (xx - 10) ** 2 <= 49
    for r, deepest in [(0.0, 1), (3.0, 5)]:
        scene = {
            "image": np.full((size, size, 3), 0.25, np.float32), "sid": disc.astype(np.int32),
            "scoc": np.where(disc, r, -4.0).astype(np.float32), "layer": 0, "bbox": (0, size, 0, size),
            "n_layers": 2, "s_lo": -8.0, "s_hi": 0.0,
        }
        got = _run_fill(scene, 4)
        filled = disc & (got["src"][..., 3] > 0)
        dist = fill_ref.l1_distance(scene["sid"], 0, 0, 0, size, size)
        assert filled.any() and dist[filled].max() == deepest
        assert np.array_equal(filled, disc & (dist <= deepest))
        # a continuous surface continues opaquely with its own colour and CoC
        np.testing.assert_allclose(got["src"][filled], np.broadcast_to([0.25, 0.25, 0.25, 1.0], (filled.sum(), 4)),
                                   atol=ATOL)
        np.testing.assert_allclose(got["coc"][filled], -4.0, atol=ATOL)


def test_sparse_layer_fills_sparsely():
    """Strokes covering a quarter of the visible pixels continue behind an occluder at about that density."""
    size = 24
    sid = np.zeros((size, size), np.int32)  # layer 0: far background
    sid[:, ::4] = 1  # layer 1: thin vertical strokes, 1 px in 4
    sid[8:16, 8:16] = 2  # layer 2: a blurred occluder
    scene = {
        "image": np.full((size, size, 3), 0.5, np.float32), "sid": sid,
        "scoc": np.select([sid == 2, sid == 1], [6.0, -2.0], -5.0).astype(np.float32), "layer": 1,
        "bbox": (0, size, 0, size), "n_layers": 3, "s_lo": -3.0, "s_hi": -1.0,
    }
    got = _run_fill(scene, 4)
    behind = sid == 2
    assert np.all(got["src"][behind][:, 3] > 0)  # all reachable: 4 px deep < sqrt(2) 6 + 1
    a = got["src"][behind][:, 3]
    assert 0.15 < a.mean() < 0.35, a.mean()
    np.testing.assert_allclose(got["src"][behind][:, :3] / a[:, None], 0.5, rtol=1e-5)


def test_bright_light_beside_the_occluder_does_not_flood():
    """Tone-mapped pull-push: a 1000x light on the occluder's edge barely lifts the hidden region.

    A linear-light pull-push would spread it at about its share of the neighbourhood (1000 / 25 = 40
    on a 5 x 5 footprint); in tone-mapped form it counts as at most 1 against the dim pixels' 0.09.
    """
    size = 17
    sid = np.zeros((size, size), np.int32)
    sid[4:13, 4:13] = 1
    image = np.full((size, size, 3), 0.1, np.float32)
    image[8, 3] = 1000.0
    scene = {"image": image, "sid": sid, "scoc": np.where(sid == 1, 8.0, -3.0).astype(np.float32), "layer": 0,
             "bbox": (0, size, 0, size), "n_layers": 2, "s_lo": -8.0, "s_hi": 0.0}
    got = _run_fill(scene, 4)
    filled = (sid == 1) & (got["src"][..., 3] > 0)
    assert filled.sum() == 81  # 4 px deep at most, the gate is sqrt(2) 8 + 1
    colour = got["src"][filled][:, 0] / got["src"][filled][:, 3]
    assert colour.max() < 1.0 and np.median(colour) < 0.15, (colour.max(), np.median(colour))


@pytest.mark.parametrize("radius", [0.5, 1.0, 2.5, 4.2, 7.0, 11.0])
def test_launcher_pyramid_depth_fills_the_whole_gate(radius):
    """With the launcher's level count for a reach r, every hidden pixel inside the gate gets a source,
    even behind an occluder that leaves a single pixel of the layer visible."""
    from bokehray.scene import pull_levels

    n = int(2 * (fill_ref.SQRT2 * radius + 2)) + 3
    for visible in ("corner pixel", "left column"):
        sid = np.ones((n, n), np.int32)
        if visible == "corner pixel":
            sid[0, 0] = 0
        else:
            sid[:, 0] = 0
        scene = {"image": np.full((n, n, 3), 0.5, np.float32), "sid": sid,
                 "scoc": np.where(sid == 1, radius, -1.0).astype(np.float32), "layer": 0, "bbox": (0, n, 0, n),
                 "n_layers": 2, "s_lo": -2.0, "s_hi": 0.0}
        got = _run_fill(scene, pull_levels(radius))
        gate = (sid == 1) & (fill_ref.l1_distance(sid, 0, 0, 0, n, n) <= fill_ref.SQRT2 * radius + 1.0)
        filled = (sid == 1) & (got["src"][..., 3] > 0)
        np.testing.assert_array_equal(filled, gate, err_msg=visible)
        np.testing.assert_allclose(got["src"][filled][:, 3], 1.0, atol=ATOL)


@pytest.mark.xfail(strict=True, reason="negative radiance is filled as 0 (tone map undefined for c < 0); "
                                       "reported, the kernel is not changed here")
def test_negative_colour_fill_stays_within_the_visible_colours():
    """Out-of-gamut (negative) linear channels: the fill should stay within the visible range too."""
    size = 9
    sid = np.zeros((size, size), np.int32)
    sid[3:6, 3:6] = 1
    image = np.full((size, size, 3), [0.5, -0.1, 0.2], np.float32)
    scene = {"image": image, "sid": sid, "scoc": np.where(sid == 1, 4.0, -4.0).astype(np.float32), "layer": 0,
             "bbox": (0, size, 0, size), "n_layers": 2, "s_lo": -8.0, "s_hi": 0.0}
    got = _run_fill(scene, 3)
    filled = (sid == 1) & (got["src"][..., 3] > 0)
    assert filled.any()
    colour = got["src"][filled][:, :3] / got["src"][filled][:, 3:4]
    np.testing.assert_allclose(colour, np.broadcast_to([0.5, -0.1, 0.2], colour.shape), atol=1e-4)


def test_tone_map_round_trip_and_oracle_sanity():
    c = np.array([0.0, 0.1, 1.0, 7.5, 40.0])
    np.testing.assert_allclose(fill_ref.untonemap(fill_ref.tonemap(c)), c, rtol=1e-12)
    taps = fill_ref.bilinear_taps(0.25, 1.75, 3, 2)  # clamped in x to the last column
    assert math.isclose(sum(b for *_, b in taps), 1.0)
    assert all(x == 1 for _, x, b in taps if b > 0)
