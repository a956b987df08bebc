"""Public render API: invariants (hypothesis), occlusion behaviour, validation errors."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from tolerances import IDENTITY_ATOL, IMAGE_ENERGY_RTOL, PYRAMID_ENERGY_RTOL

import bokehray as br
from bokehray import LayerOptions, PreviewOptions

finite_radiance = st.floats(0.0, 50.0, allow_nan=False, width=32)


@st.composite
def scenes(draw, max_side=24):
    h = draw(st.integers(1, max_side))
    w = draw(st.integers(1, max_side))
    image = draw(arrays(np.float32, (h, w, 3), elements=finite_radiance))
    kind = draw(st.sampled_from(["random", "steps", "constant", "edges"]))
    if kind == "random":
        d = draw(arrays(np.float32, (h, w), elements=st.floats(0.0, 1.0, width=32)))
    elif kind == "constant":
        d = np.full((h, w), draw(st.floats(0.0, 1.0, width=32)), np.float32)
    elif kind == "edges":
        d = np.where(np.arange(w)[None, :] < w // 2, 0.0, 1.0).repeat(h, 0).astype(np.float32)
    else:
        d = (np.indices((h, w)).sum(0) % 2).astype(np.float32)  # one-pixel steps between 0 and 1
    return image, d


blurs = st.builds(br.BlurParams, k_px=st.floats(0.0, 30.0), focus_disparity=st.floats(0.0, 1.0))
apertures = st.sampled_from([br.Aperture(), br.Aperture(blades=6, rotation_deg=15.0),
                             br.Aperture(blades=5, curvature=0.5)])


@given(scene=scenes(), blur=blurs, ap=apertures)
def test_output_is_finite_and_within_input_range(scene, blur, ap):
    image, d = scene
    out = br.render(image, d, blur, ap)
    assert out.shape == image.shape and out.dtype == np.float32
    assert np.isfinite(out).all()
    # a convex combination of input radiances per channel: never outside the input range
    lo, hi = image.min(axis=(0, 1)), image.max(axis=(0, 1))
    assert (out >= lo - 1e-4 * (1 + np.abs(lo))).all() and (out <= hi + 1e-4 * (1 + hi)).all()


@given(scene=scenes(), blur=blurs, value=st.floats(0.0, 100.0, width=32))
def test_constant_image_stays_constant(scene, blur, value):
    _, d = scene
    image = np.full(d.shape + (3,), value, np.float32)
    out = br.render(image, d, blur)
    np.testing.assert_allclose(out, value, rtol=1e-4, atol=1e-6)


@given(scene=scenes(), d_f=st.floats(0.0, 1.0))
def test_k_zero_is_identity(scene, d_f):
    image, d = scene
    out = br.render(image, d, br.BlurParams(0.0, d_f))
    np.testing.assert_allclose(out, image, atol=IDENTITY_ATOL)


@given(scene=scenes(), k=st.floats(0.0, 50.0))
def test_in_focus_everywhere_is_identity(scene, k):
    image, d = scene
    d_f = float(d.flat[0])
    flat = np.full_like(d, d_f)
    out = br.render(image, flat, br.BlurParams(k, d_f))
    np.testing.assert_allclose(out, image, atol=IDENTITY_ATOL)


@given(scene=scenes(max_side=20), blur=blurs)
def test_horizontal_mirror_symmetry(scene, blur):
    image, d = scene
    opts = {"layers": LayerOptions(fill=False), "options": PreviewOptions(level_radius_px=1e6)}
    out = br.render(image, d, blur, **opts)
    mirrored = br.render(image[:, ::-1].copy(), d[:, ::-1].copy(), blur, **opts)
    np.testing.assert_allclose(mirrored[:, ::-1], out, rtol=1e-4, atol=1e-4)


def test_mirror_symmetry_with_fill_and_pyramid_is_close(rng):
    scene = br_demo_small()
    blur = br.BlurParams(scene.k_px, scene.focus_near)
    out = br.render(scene.image, scene.disparity, blur)
    mirrored = br.render(scene.image[:, ::-1].copy(), scene.disparity[:, ::-1].copy(), blur)[:, ::-1]
    mse = np.mean((np.clip(out, 0, 1) - np.clip(mirrored, 0, 1)) ** 2)
    assert 10 * np.log10(1 / mse) > 40  # pyramid grids are anchored at the top-left: not bit-exact


def br_demo_small():
    from bokehray.app.demo import build_demo_scene

    return build_demo_scene(width=256, height=160)


@given(r=st.floats(0.0, 12.0), value=st.floats(1e-8, 1e4), seed=st.integers(0, 2**16))
def test_energy_conserved_for_fronto_parallel_scene(r, value, seed):
    rng = np.random.default_rng(seed)
    size, margin = 64, 26  # content at least 2 r + 1 px away from the border
    image = np.zeros((size, size, 3), np.float32)
    image[margin:-margin, margin:-margin] = rng.random((size - 2 * margin, size - 2 * margin, 3)) * value
    d = np.full((size, size), 0.25, np.float32)
    out = br.render(image, d, br.BlurParams(r / 0.5, 0.75))
    np.testing.assert_allclose(out.sum(axis=(0, 1)), image.sum(axis=(0, 1)), rtol=IMAGE_ENERGY_RTOL)


@pytest.mark.parametrize("r", [40, 48, 64, 400])
def test_energy_of_a_fronto_parallel_plane_at_pyramid_radii(r):
    """The promise docs/robustness.md states (the hypothesis test above stops at r = 12): the light a plane loses
    stays within PYRAMID_ENERGY_RTOL (r <= 64, and up to r = 400), with a black border wider than the blur."""
    rng = np.random.default_rng(r)
    c, m = 32, r + 3
    image = np.zeros((c + 2 * m, c + 2 * m, 3), np.float32)
    image[m:m + c, m:m + c] = rng.random((c, c, 3))
    d = np.full(image.shape[:2], 0.25, np.float32)
    out = br.render(image, d, br.BlurParams(r / 0.5, 0.75))
    rtol = PYRAMID_ENERGY_RTOL[64 if r <= 64 else 400]
    np.testing.assert_allclose(out.sum(axis=(0, 1), dtype=np.float64), image.sum(axis=(0, 1), dtype=np.float64),
                               rtol=rtol)


def test_energy_conserved_on_pyramid_levels(device):
    size = 256
    image = np.zeros((size, size, 3), np.float32)
    image[100:156, 100:156] = 1.0
    image[128, 128] = 50.0
    d = np.zeros((size, size), np.float32)
    out = br.render(image, d, br.BlurParams(40.0, 1.0), device=device)  # r = 40: pyramid level 3
    np.testing.assert_allclose(out.sum(axis=(0, 1)), image.sum(axis=(0, 1)), rtol=1e-3)


def test_sharp_subject_is_not_smeared_by_blurred_background(device):
    """No halo: an in-focus subject keeps its pixels, the background behind it blurs."""
    h, w = 80, 80
    rng = np.random.default_rng(0)
    image = rng.random((h, w, 3)).astype(np.float32)
    d = np.zeros((h, w), np.float32)
    d[20:60, 20:60] = 1.0
    image[20:60, 20:60] = [0.2, 0.9, 0.1]
    out = br.render(image, d, br.BlurParams(12.0, 1.0), device=device)
    np.testing.assert_allclose(out[20:60, 20:60], image[20:60, 20:60], atol=1e-6)
    # and the background just outside the subject carries none of the subject's green
    ring = out[14:19, 25:55]
    assert abs(ring[..., 1].mean() - image[..., 1][d == 0].mean()) < 0.08


def test_blurred_foreground_spreads_over_sharp_background(device):
    h, w = 80, 80
    image = np.zeros((h, w, 3), np.float32)
    image[..., 2] = 1.0  # blue background, in focus
    d = np.zeros((h, w), np.float32)
    d[30:50, 30:50] = 1.0
    image[30:50, 30:50] = [1.0, 0.0, 0.0]  # red square in front, out of focus
    out = br.render(image, d, br.BlurParams(8.0, 0.0), device=device)
    # just outside the square the red foreground is semi-transparent over the blue background
    px = out[40, 27]
    assert 0.1 < px[0] < 0.9 and 0.1 < px[2] < 0.9
    # far from it, the background is untouched
    np.testing.assert_allclose(out[5, 5], [0, 0, 1], atol=1e-6)
    # the foreground loses opacity at its edge: total red is spread, not lost
    assert out[..., 0].sum() == pytest.approx(400.0, rel=0.05)


def test_highlight_stays_bright_and_takes_the_aperture_shape():
    size = 101
    image = np.full((size, size, 3), 0.05, np.float32)
    image[50, 50] = 500.0
    d = np.zeros((size, size), np.float32)
    ap = br.Aperture(blades=6)
    out = br.render(image, d, br.BlurParams(15.0, 1.0), ap)
    plateau = 500.0 / 584.6  # a hexagon of circumradius 15: area 3 sqrt(3)/2 r^2 = 584.6 px
    ball = out[..., 0] > 0.05 + 0.5 * plateau  # half-maximum contour
    assert abs(ball.sum() - 584.6) < 25
    # hexagon, not disc: its vertical extent (flat top/bottom, rotation 0 puts vertices left/right) is r sqrt(3)
    rows = np.flatnonzero(ball.any(axis=1))
    assert abs((rows[-1] - rows[0] + 1) - 15 * np.sqrt(3)) <= 2
    assert out[..., 0].max() > 0.5  # 500 / 584.6 + 0.05: bright, not clipped away


def test_channels_grey_and_rgba(rng):
    d = rng.random((16, 16)).astype(np.float32)
    blur = br.BlurParams(4.0, 0.5)
    grey = rng.random((16, 16, 1)).astype(np.float32)
    out = br.render(grey, d, blur)
    assert out.shape == (16, 16, 1)
    rgba = rng.random((16, 16, 4)).astype(np.float32)
    out4 = br.render(rgba, d, blur)
    assert out4.shape == (16, 16, 4)
    np.testing.assert_allclose(out4[..., :3], br.render(rgba[..., :3], d, blur), atol=1e-6)


def test_stats_report_skipped_tiles():
    h, w = 128, 128
    image = np.ones((h, w, 3), np.float32)
    d = np.zeros((h, w), np.float32)
    d[:16, :16] = 1.0  # one blurred corner, the rest in focus
    _, stats = br.render_with_stats(image, d, br.BlurParams(4.0, 0.0))
    assert stats.tiles_total == 64
    assert 0 < stats.tiles_copied < 64
    assert stats.max_coc_px == pytest.approx(4.0)
    _, stats = br.render_with_stats(image, np.zeros((h, w), np.float32), br.BlurParams(4.0, 0.0))
    assert stats.tiles_copied == 64 and stats.layers == 0


# --- validation -----------------------------------------------------------------------------------

@pytest.mark.parametrize(
    ("image", "d", "match"),
    [
        (np.zeros((4, 4, 2), np.float32), np.zeros((4, 4), np.float32), "C in"),
        (np.zeros((4, 4, 3), np.uint8), np.zeros((4, 4), np.float32), "floating-point"),
        (np.zeros((0, 4, 3), np.float32), np.zeros((0, 4), np.float32), "non-empty"),
        (np.full((4, 4, 3), np.nan, np.float32), np.zeros((4, 4), np.float32), "NaN/Inf"),
        (np.zeros((4, 4, 3), np.float32), np.zeros((4, 5), np.float32), "shape"),
        (np.zeros((4, 4, 3), np.float32), np.full((4, 4), np.inf, np.float32), "NaN/Inf"),
        (np.zeros((4, 4, 3), np.float32), np.full((4, 4), 1.5, np.float32), r"\[0, 1\]"),
        (np.zeros((4, 4, 3), np.float32), np.full((4, 4), -0.1, np.float32), r"\[0, 1\]"),
    ],
)
def test_bad_arrays_are_rejected(image, d, match):
    with pytest.raises(br.InputError, match=match):
        br.render(image, d, br.BlurParams(1.0, 0.5))


def test_bad_parameters_are_rejected():
    with pytest.raises(br.InputError, match="K"):
        br.BlurParams(-1.0, 0.5)
    with pytest.raises(br.InputError, match="focus disparity"):
        br.BlurParams(1.0, 1.5)
    with pytest.raises(br.InputError, match="blades"):
        br.Aperture(blades=2)
    with pytest.raises(br.InputError, match="curvature"):
        br.Aperture(blades=6, curvature=2.0)
    img, d = np.zeros((4, 4, 3), np.float32), np.zeros((4, 4), np.float32)
    with pytest.raises(br.InputError, match="quality"):
        br.render(img, d, br.BlurParams(1.0, 0.5), quality="best")
    with pytest.raises(br.InputError, match="device"):
        br.render(img, d, br.BlurParams(1.0, 0.5), device="tpu")


def test_focus_at_uses_a_robust_median():
    d = np.full((50, 50), 0.3, np.float32)
    d[20, 20] = 0.9  # a stray pixel under the cursor
    assert br.focus_at(d, 20, 20) == pytest.approx(0.3)
    with pytest.raises(br.InputError, match="focus point"):
        br.focus_at(d, 60, 2)


def test_fill_reveals_the_background_behind_a_blurred_edge(device):
    """Behind a defocused foreground edge the thin lens sees background: the fill supplies it."""
    h, w = 64, 64
    image = np.zeros((h, w, 3), np.float32)
    image[..., 2] = 1.0
    image[:, 32:] = [1.0, 0.0, 0.0]  # red, near, blurred
    d = np.zeros((h, w), np.float32)
    d[:, 32:] = 1.0
    blur = br.BlurParams(8.0, 0.0)
    px = br.render(image, d, blur, device=device)[32, 34]  # 2 px inside the red edge
    assert 0.5 < px[0] < 0.95
    assert px[0] + px[2] == pytest.approx(1.0, abs=0.02)  # the rest is blue background: no dark or red halo
    unfilled = br.render(image, d, blur, layers=LayerOptions(fill=False), device=device)[32, 34]
    assert unfilled[2] < 0.05  # without the fill only the foreground's own colour is left


def test_sparse_layer_fills_sparsely():
    """Thin strokes over a background continue behind an occluder at their density, not as a solid sheet."""
    h, w = 64, 96
    image = np.zeros((h, w, 3), np.float32)
    d = np.zeros((h, w), np.float32)
    image[:, ::4] = 1.0  # white vertical lines, one column in four, in focus at d = 0.5
    d[:, ::4] = 0.5
    image[:, 48:] = 0.5  # a grey occluder, near and blurred
    d[:, 48:] = 1.0
    out = br.render(image, d, br.BlurParams(16.0, 0.5))  # occluder r = 8
    inside = out[20:44, 50:53].mean()  # 2-4 px inside the occluder edge: partly transparent
    # hidden lines at density 1/4 give about 0.7 * 0.5 + 0.3 * 0.25 = 0.43; a solid white fill would give 0.65
    assert inside < 0.5


def test_highlight_boost_inflates_only_clipped_pixels():
    image = np.array([[[0.5, 0.5, 0.5], [1.0, 1.0, 1.0], [1.0, 0.2, 0.2]]], np.float32)
    out = br.boost_highlights(image, strength=4.0)
    np.testing.assert_array_equal(out[0, 0], image[0, 0])  # below the threshold: untouched
    np.testing.assert_allclose(out[0, 1], 5.0)  # fully clipped: 1 + 4 * 1^2
    np.testing.assert_allclose(out[0, 2], image[0, 2] * 5.0)  # hue kept: the whole pixel scales
    d = np.zeros((1, 3), np.float32)
    plain = br.render(image, d, br.BlurParams(0.0, 0.0))
    boosted = br.render(image, d, br.BlurParams(0.0, 0.0), highlight_boost=4.0)
    np.testing.assert_array_equal(plain, image)  # off by default
    np.testing.assert_allclose(boosted, out)


def test_bright_sources_never_give_negative_output():
    """Soak regression (benchmarks/robustness/soak.py seed 0 case 114): float32 row sums next to radiance 1e4."""
    rng = np.random.default_rng(980325484)
    image = (rng.random((33, 64, 3)) * 1e4).astype(np.float32)
    margin = 6
    image[:margin] = image[-margin:] = 0
    image[:, :margin] = image[:, -margin:] = 0
    out = br.render(image, np.ones((33, 64), np.float32), br.BlurParams(2.0, 0.5))
    assert out.min() >= 0.0


def test_highlight_boost_leaves_alpha_alone():
    rgba = np.full((8, 8, 4), 0.2, np.float32)
    rgba[..., 3] = 1.0
    out = br.render(rgba, np.zeros((8, 8), np.float32), br.BlurParams(0.0, 0.0), highlight_boost=4.0)
    np.testing.assert_allclose(out, rgba)  # alpha 1 is not a clipped highlight


@pytest.mark.parametrize(
    "cls,kwargs",
    [(LayerOptions, {"max_layers": 0}), (LayerOptions, {"tile_px": 0}), (LayerOptions, {"max_layer_px": 0.0}),
     (LayerOptions, {"max_layers": 1.5}), (PreviewOptions, {"level_radius_px": 0.0}),
     (PreviewOptions, {"level_radius_px": float("nan")}), (PreviewOptions, {"threads": 0})],
)
def test_bad_preview_options_are_rejected(cls, kwargs):
    with pytest.raises(br.InputError):
        cls(**kwargs)


# --- argument types (the adversarial run found each escaping as a bare TypeError/AttributeError) ----------------

_IMG, _D = np.zeros((4, 4, 3), np.float32), np.zeros((4, 4), np.float32)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"options": {"max_layers": 2}}, "options: quality 'preview' takes a bokehray.PreviewOptions, got dict"),
        ({"options": br.RaytraceOptions()}, "takes a bokehray.PreviewOptions, got RaytraceOptions"),
        ({"quality": "raytrace", "options": PreviewOptions()}, "takes a bokehray.RaytraceOptions"),
        ({"layers": {"fill": False}}, "layers: expected a bokehray.LayerOptions, got dict"),
        ({"memory": 100}, "memory: expected a bokehray.MemoryOptions, got int"),
        ({"highlight_boost": "4"}, "highlight_boost: expected a finite number"),
        ({"highlight_boost": None}, "highlight_boost: expected a finite number"),
        ({"highlight_boost": 1e39}, "highlight_boost: expected a value within float32"),
        ({"highlight_boost": 1e37}, "highlight_boost: expected a boost that keeps radiance within"),
        ({"refine": 1}, "refine: expected True, False or a path"),
        ({"quality": 3}, "quality: expected one of preview, raytrace"),
        ({"device": None}, "device: expected a Warp device name"),
        ({"progress": "yes"}, "progress: expected a callable"),
    ],
)
def test_wrong_argument_types_raise_input_error_naming_the_argument(kwargs, match):
    image = np.ones((4, 4, 3), np.float32) if "highlight_boost" in kwargs else _IMG
    with pytest.raises(br.InputError, match=match):
        br.render(image, _D, br.BlurParams(1.0, 0.5), **kwargs)


@pytest.mark.parametrize(
    ("call", "match"),
    [
        (lambda: br.focus_at(_D, 1.5, 2.7), "integer pixel coordinates"),
        (lambda: br.focus_at(np.zeros(5, np.float32), 1, 0), "non-empty H x W map"),
        (lambda: br.RaytraceOptions(max_spp=2.5), "max_spp: expected an integer"),
        (lambda: br.BlurParams(True, 0.5), "K .*expected a number, got True"),
        (lambda: br.BlurParams("4", 0.5), "K .*expected a number"),
        (lambda: br.render(_IMG, _D, (1.0, 0.5)), "blur: expected a bokehray.BlurParams, got tuple"),
        (lambda: br.render(_IMG, _D, br.BlurParams(1.0, 0.5), "disc"), "aperture: expected a bokehray.Aperture"),
        (lambda: br.raytrace_layers(br.Layer(np.zeros((2, 2, 4), np.float32), plane=(0, 0, 0)),
                                    br.BlurParams(1.0, 0.5)), "layers: expected a list of bokehray.Layer"),
    ],
)
def test_public_constructors_and_helpers_check_their_types(call, match):
    with pytest.raises(br.InputError, match=match):
        call()


def test_a_routed_light_keeps_a_constant_channel_constant():
    """The case hypothesis found: routed lights once sent all their RGB to full resolution but their coverage to
    the pyramid, and the constant channels drifted by 3e-4."""
    image = np.array([[[1, 1, 1], [3, 1, 1]], [[1, 1, 1], [1, 1, 1]]], np.float32)
    d = np.array([[0, 1], [1, 0]], np.float32)
    out = br.render(image, d, br.BlurParams(9.0, 0.0))
    np.testing.assert_allclose(out[..., 1:], 1.0, rtol=1e-5)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), k=st.floats(8.0, 40.0), level=st.floats(0.05, 2.0))
def test_lights_leave_a_constant_channel_constant(seed, k, level):
    """Bright lights in red only, on a layered scene whose green channel is one constant: green stays constant
    wherever the lights are routed to full resolution."""
    rng = np.random.default_rng(seed)
    h, w = 40, 56
    image = np.empty((h, w, 3), np.float32)
    image[..., 0] = rng.uniform(0, 0.3, (h, w))
    image[..., 1] = level
    image[..., 2] = rng.uniform(0, 0.3, (h, w))
    lights = rng.random((h, w)) < 0.03
    image[lights, 0] = rng.uniform(10, 500, lights.sum())
    d = np.where(rng.random((h, w)) < 0.5, 0.1, 0.9).astype(np.float32)
    out = br.render(image, d, br.BlurParams(k, 0.5))
    np.testing.assert_allclose(out[..., 1], level, rtol=1e-4)


def test_tiles_gather_extended_lights_like_the_whole_frame():
    """Regression (found by benchmarks/robustness/soak.py): gathered light sources at arbitrary centroids were cut into other
    sub-rows in a tile's window than in the whole frame (float32 rounding of y - yc), 1.2e-4 apart; centroids now
    lie on a 1/256 px grid."""
    rng = np.random.default_rng(2026998898)
    image = np.zeros((64, 16, 4), np.float32)
    image[..., 3] = rng.choice([0.0, 1.0, 0.3], (64, 16))  # alpha renders like a grey channel: clusters everywhere
    lamps = np.zeros((80, 60, 3), np.float32) + 0.02
    lamps[20:25, 13:18] = lamps[41:47, 30:35] = 1.5  # lamps that straddle the tiles' edges
    d = np.zeros((64, 16), np.float32)
    for img, disp in ((image, d), (lamps, np.zeros((80, 60), np.float32))):
        whole = br.render(img, disp, br.BlurParams(9.0, 1.0))
        tiled = br.render(img, disp, br.BlurParams(9.0, 1.0), memory=br.MemoryOptions(tile_size=24))
        np.testing.assert_allclose(tiled, whole, rtol=0, atol=2e-5 * float(np.abs(whole).max()))
