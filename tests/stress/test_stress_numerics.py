"""Numerical stress: extreme and degenerate inputs through the kernels and the public render.

What tests/test_render_api.py already covers is not repeated here (finite and in-range output
for moderate random scenes, constant images, K = 0 and in-focus identity of RGB previews,
energy of fronto-parallel scenes). This file adds the extremes: K huge relative to
the image, d_f exactly 0 and 1, disparity exactly 0 or 1 everywhere, 1 x 1, 1 x N and N x 1
images, grey and RGBA inputs, radiance 0, 1e-8, 1e4 and float32 denormals, both quality
levels; the kernels against their float64 references on such cases; and the ray tracer's
degenerate geometry (grazing planes, layers at one depth, alpha exactly 0 and 1, one ray).
The long version is benchmarks/robustness/stress_reference.py and benchmarks/robustness/soak.py (docs/robustness.md).
"""

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from reference import raytrace_ref, stress_cases

import bokehray as br
from bokehray.lens import MAX_K_PX
from bokehray.levels.raytrace import Layer, raytrace_layers
from bokehray.options import RaytraceOptions

SCALES = (0.0, 1e-40, 1e-8, 1.0, 1e4)
# float32 kernels vs float64 references, relative to the largest reference value (normal radiance):
# a few float32 roundings per deposit, summed over up to a few hundred deposits.
REFERENCE_RTOL = 5e-5
# denormal radiance (1e-40): float32 keeps only 1 to 3 significant digits down there
# (deposits of 1e-43 sit on a grid of 1.4e-45); the absolute floor is in stress_cases.
DENORMAL_RTOL = 5e-2


def _rays(quality, spp):
    """The level's options: a ray cap for the ray tracer, the defaults for the preview."""
    return RaytraceOptions(max_spp=spp) if quality == "raytrace" else None


@given(seed=st.integers(0, 2**31 - 1), kernel=st.sampled_from(sorted(stress_cases.CASES)))
def test_kernels_match_float64_references_on_extreme_cases(seed, kernel):
    err, scale, desc = stress_cases.CASES[kernel](seed)
    limit = DENORMAL_RTOL if 0.0 < scale < 1e-37 else REFERENCE_RTOL
    assert err <= limit, f"{desc} (seed {seed}): relative error {err:.3g}"


# --------------------------------------------------------------------------- public render, extremes


@st.composite
def extreme_cases(draw):
    shape = draw(st.sampled_from([(1, 1), (1, 9), (9, 1), (1, 40), (3, 2), (17, 13)]))
    h, w = shape
    channels = draw(st.sampled_from([1, 3, 4]))
    scale = draw(st.sampled_from(SCALES))
    seed = draw(st.integers(0, 2**16))
    rng = np.random.default_rng(seed)
    image = (rng.random((h, w, channels)) * scale).astype(np.float32)
    if channels == 4:
        image[..., 3] = rng.choice([0.0, 1.0, 0.5], (h, w))  # alpha exactly 0 and 1
    pattern = draw(st.sampled_from(["zero", "one", "constant", "steps", "random", "edge"]))
    d = {"zero": np.zeros((h, w)), "one": np.ones((h, w)), "constant": np.full((h, w), rng.random()),
         "steps": np.indices((h, w)).sum(0) % 2, "random": rng.random((h, w)),
         "edge": (np.arange(w)[None, :] >= w // 2) * np.ones((h, 1))}[pattern].astype(np.float32)
    k = draw(st.sampled_from([0.0, 1e-6, 0.5, 3.0, 60.0, 1e3, MAX_K_PX]))
    d_f = draw(st.sampled_from([0.0, 1.0, 0.5, float(rng.random())]))
    return image, d, br.BlurParams(k, d_f), f"{shape} C={channels} scale={scale:g} {pattern} K={k:g} d_f={d_f:.3g}"


def _check_bounded(image, out, desc):
    assert out.shape == image.shape and out.dtype == np.float32, desc
    assert np.isfinite(out).all(), desc
    lo, hi = image.min(axis=(0, 1)), image.max(axis=(0, 1))
    # every output pixel is a convex combination of input values; float32 running sums may
    # leave a relative 1e-5 of the brightest value
    tol = 1e-5 * np.abs(image).max() + 1e-6 * (1 + np.abs(lo))
    assert (out >= lo - tol).all() and (out <= hi + tol).all(), desc


@given(case=extreme_cases(), ap=st.sampled_from(stress_cases.APERTURES))
def test_preview_extremes_are_finite_and_bounded(case, ap):
    image, d, blur, desc = case
    out = br.render(image, d, blur, ap)
    _check_bounded(image, out, desc)
    if blur.k_px == 0.0 or (d == blur.focus_disparity).all():
        np.testing.assert_array_equal(out, image)  # in-focus identity, every channel count


@given(case=extreme_cases())
def test_raytrace_extremes_are_finite_and_bounded(case):
    image, d, blur, desc = case  # K up to 1e5: the CoC cap keeps the march short (cap_coc)
    out = br.render(image, d, blur, quality="raytrace", options=RaytraceOptions(max_spp=4))
    _check_bounded(image, out, desc)
    if blur.k_px == 0.0 or (d == blur.focus_disparity).all():
        np.testing.assert_allclose(out, image, rtol=1e-6, atol=0)


@pytest.mark.parametrize("quality", ["preview", "raytrace"])
@pytest.mark.parametrize("d_value,d_f", [(0.0, 0.0), (1.0, 1.0), (0.0, 1.0), (1.0, 0.0)])
def test_disparity_all_zero_or_one_with_focus_at_the_ends(quality, d_value, d_f):
    rng = np.random.default_rng(3)
    image = rng.random((24, 30, 3)).astype(np.float32)
    d = np.full((24, 30), d_value, np.float32)
    out = br.render(image, d, br.BlurParams(10.0, d_f), quality=quality, options=_rays(quality, 8))
    if d_value == d_f:
        np.testing.assert_allclose(out, image, rtol=1e-6)
    else:  # one fronto-parallel plane 10 px out of focus: a blur that keeps the mean away from borders
        assert np.isfinite(out).all() and abs(out[10:14, 12:18].mean() - image.mean()) < 0.05
        assert out.std() < 0.5 * image.std()


@pytest.mark.parametrize("scale", [1e-8, 1e4])
@pytest.mark.parametrize("shape", [(1, 64), (64, 1), (40, 40)])
def test_energy_is_conserved_at_extreme_radiance_and_thin_images(scale, shape):
    """A fronto-parallel plane with a black border as wide as the blur: every photon stays in the frame."""
    rng = np.random.default_rng(11)
    h, w = shape
    image = np.zeros((h, w, 3), np.float32)
    m = 12
    image[min(m, h // 2 if h > 1 else 0): max(h - m, 1), min(m, w // 2 if w > 1 else 0): max(w - m, 1)] = scale
    image *= rng.random((h, w, 1)).astype(np.float32)
    for blur in (br.BlurParams(5.0, 0.0), br.BlurParams(5.0, 1.0)):  # behind and in front of the focal plane
        out = br.render(image, np.full((h, w), 0.9, np.float32), blur)
        if min(h, w) == 1:  # a line: light leaves sideways, borders renormalise; still a weighted mean
            assert np.isfinite(out).all() and out.max() <= image.max() * (1 + 1e-5)
        else:
            np.testing.assert_allclose(out.sum(), image.sum(), rtol=2e-4)


@pytest.mark.parametrize("shape", [(1, 1), (3, 4), (1, 50), (40, 30)])
@pytest.mark.parametrize("aperture", [br.Aperture(), br.Aperture(blades=3)])
def test_huge_k_spreads_every_pixel_to_the_mean(shape, aperture):
    """K = 1e5: every pixel's CoC covers the frame many times over, so each output is the frame's mean.

    Found by this suite: without the CoC cap (bokehray.scene.cap_coc) the coverage fell below
    the compositing's noise floor and the preview silently returned the unblurred input.
    """
    rng = np.random.default_rng(0)
    image = rng.random((*shape, 3)).astype(np.float32) * 100
    d = np.zeros(shape, np.float32)
    out, stats = br.render_with_stats(image, d, br.BlurParams(MAX_K_PX, 1.0), aperture)
    assert stats.max_coc_px == MAX_K_PX  # reported as asked, though rendered at the cap
    np.testing.assert_allclose(out, np.broadcast_to(image.mean(axis=(0, 1)), image.shape), rtol=2e-3)


def test_coc_cap_leaves_normal_renders_alone_and_keeps_depth_order():
    from bokehray.scene import cap_coc

    s = np.linspace(-60, 60, 200 * 300, dtype=np.float32).reshape(200, 300)
    assert cap_coc(s) is s  # within twice the diagonal: untouched
    big = np.array([[-1e5, -3e3, 0.0, 10.0, 1e3, 1e5]], np.float32)  # cap: 2 hypot(1, 6) + 2 = 14.2
    capped = cap_coc(big)
    assert (np.diff(capped[0]) > 0).all() and np.abs(capped).max() < 2 * np.hypot(1, 6) + 2 + 12
    np.testing.assert_array_equal(capped[0, 2:4], big[0, 2:4])
    np.testing.assert_array_equal(cap_coc(big, 1e5), capped)  # the render passes the largest radius it found
    assert cap_coc(s, 60.0) is s


def test_denormal_and_zero_radiance_stay_finite_and_non_negative():
    image = np.full((20, 20, 3), 1e-40, np.float32)
    image[5:9, 5:9] = 0.0
    d = (np.indices((20, 20)).sum(0) % 2).astype(np.float32)
    for quality in ("preview", "raytrace"):
        out = br.render(image, d, br.BlurParams(7.0, 0.3), quality=quality, options=_rays(quality, 4))
        assert np.isfinite(out).all() and (out >= 0).all() and out.max() <= 1.0001e-40


# --------------------------------------------------------------------------- ray tracer geometry


def _fixed(spp):
    return RaytraceOptions(samples_per_px2=1e6, max_spp=spp, min_spp=spp)


def _tex(rng, h, w, alpha):
    t = np.empty((h, w, 4), np.float32)
    t[..., :3] = rng.random((h, w, 3))
    t[..., 3] = alpha
    return t


def test_layers_at_identical_depth_composite_in_the_given_order():
    rng = np.random.default_rng(4)
    front, back = _tex(rng, 10, 12, 1.0), _tex(rng, 10, 12, 1.0)
    blur = br.BlurParams(6.0, 0.0)
    both, _ = raytrace_layers([Layer(front, plane=(0, 0, 0.5)), Layer(back, plane=(0, 0, 0.5))], blur, options=_fixed(9))
    alone, _ = raytrace_layers([Layer(front, plane=(0, 0, 0.5))], blur, options=_fixed(9))
    np.testing.assert_allclose(both, alone, atol=1e-6)  # an opaque layer hides an equally deep one entirely
    half = front.copy()
    half[..., 3] = 0.5
    got, _ = raytrace_layers([Layer(half, plane=(0, 0, 0.5)), Layer(back, plane=(0, 0, 0.5))], blur, options=_fixed(9))
    want = raytrace_ref.trace([(half, (0, 0, 0.5)), (back, (0, 0, 0.5))], 6.0, 0.0, 9)
    np.testing.assert_allclose(got, want, atol=2e-5)


def test_alpha_zero_layer_is_invisible_and_alpha_one_is_opaque():
    rng = np.random.default_rng(5)
    back = _tex(rng, 9, 11, 1.0)
    ghost = _tex(rng, 9, 11, 0.0) * 1e4  # bright colour, alpha exactly 0: must add nothing
    blur = br.BlurParams(5.0, 0.2)
    with_ghost, _ = raytrace_layers([Layer(ghost, plane=(0, 0, 0.9)), Layer(back, plane=(0, 0, 0.1))], blur,
                                    options=_fixed(7))
    without, _ = raytrace_layers([Layer(back, plane=(0, 0, 0.1))], blur, options=_fixed(7))
    np.testing.assert_array_equal(with_ghost, without)
    np.testing.assert_allclose(without[..., 3], 1.0, atol=1e-6)  # alpha 1 ends every ray


@pytest.mark.parametrize("spp", [1, 2])
def test_one_ray_per_pixel_matches_the_reference(spp):
    rng = np.random.default_rng(6)
    layers = [(_tex(rng, 8, 9, (np.arange(9) >= 4) * np.ones((8, 1))), (0.0, 0.0, 0.8)),  # a hard alpha edge
              (_tex(rng, 8, 9, 1.0), (0.02, -0.01, 0.2))]
    got, st_ = raytrace_layers([Layer(t, plane=p) for t, p in layers], br.BlurParams(7.0, 0.4), options=_fixed(spp))
    assert st_.spp_max <= spp  # a cap: one box cell for 1 (and 2) rays
    np.testing.assert_allclose(got, raytrace_ref.trace(layers, 7.0, 0.4, spp), atol=2e-5)


def test_grazing_planes_give_finite_bounded_output():
    """A plane tilted so that some rays run parallel to it (1 - g . K u = 0): those rays miss it, nothing blows up."""
    rng = np.random.default_rng(7)
    k = 8.0
    tex = _tex(rng, 12, 12, 1.0)
    for g in ((1.0 / k, 0.0), (0.0, -1.0 / k), (0.7 / k, 0.7 / k), (1.0 / k + 1e-7, 0.0)):
        out, _ = raytrace_layers([Layer(tex, plane=(g[0], g[1], 0.3)), Layer(tex, plane=(0, 0, 0.0))],
                                 br.BlurParams(k, 0.3), options=_fixed(32))
        assert np.isfinite(out).all()
        assert out[..., :3].min() >= 0 and out[..., :3].max() <= 1.0 + 1e-5 and out[..., 3].max() <= 1.0 + 1e-6


def test_rays_leaving_a_one_pixel_layer_see_its_border_continued():
    """Clamp-to-edge on the smallest texture: a 1 x 1 layer is a uniform plane, whatever the rays do."""
    tex = np.array([[[0.25, 0.5, 1e4, 1.0]]], np.float32)
    out, _ = raytrace_layers([Layer(tex, plane=(0, 0, 0.0))], br.BlurParams(50.0, 1.0), options=_fixed(16))
    np.testing.assert_allclose(out[0, 0], [0.25, 0.5, 1e4, 1.0], rtol=1e-6)


@pytest.mark.parametrize("quality", ["preview", "raytrace"])
def test_radiance_near_the_float32_limit_is_refused_by_every_level(quality):
    """Finite radiance near float32's maximum would overflow a render's sums: every level refuses it up front with
    the same message (it used to render on a constant image, and give NaN in the preview on a patch)."""
    image = np.zeros((8, 8, 3), np.float32)
    image[2:5, 2:5] = 3e38  # a patch, as the adversarial run tried
    d = np.zeros((8, 8), np.float32)
    with pytest.raises(br.InputError, match="radiance up to 3e\\+38.*within \\+-1e\\+36"):
        br.render(image, d, br.BlurParams(5.0, 1.0), quality=quality)
    np.testing.assert_array_equal(br.render(image * 1e-3, d, br.BlurParams(5.0, 1.0), quality=quality) >= 0, True)


@pytest.mark.parametrize("dtype", [np.float32, np.float64, np.float16, np.int16, np.uint8])
def test_check_radiance_peak_is_the_largest_magnitude(dtype):
    """check_radiance's peak, max(max, -min), is |image|.max(): negative peaks, NaN (not refused, as before) and
    integer arrays (no wrap of -min) alike."""
    from bokehray.validate import MAX_RADIANCE, check_radiance

    rng = np.random.default_rng(3)
    big = np.finfo(np.float32).max if np.issubdtype(dtype, np.floating) and dtype != np.float16 else None
    image = (rng.standard_normal((6, 7, 3)) * 50).astype(dtype)
    check_radiance(image)
    check_radiance(np.zeros((0, 3), dtype))
    if big is not None:
        for sign in (1, -1):
            bad = image.astype(dtype)
            bad[1, 2, 0] = sign * big
            with pytest.raises(br.InputError, match="radiance up to 3.4e\\+38"):
                check_radiance(bad)
            bad[4, 4, 2] = np.nan  # |image|.max() is NaN: not refused here (the finite check says what is wrong)
            check_radiance(bad)
    assert float(np.abs(image).max()) <= MAX_RADIANCE


@pytest.mark.parametrize("depths", ["rows", "checker", "noise"])
@pytest.mark.parametrize("photo", ["stripes", "noise"])
def test_one_layer_holding_near_and_far_stays_finite_and_in_range(depths, photo):
    """``max_layers=1`` puts near and far pixels in one layer: the extended-light clusters averaged their signed CoC
    to about 0 and sent their light to a point (NaN/Inf, "preview renderer produced NaN/Inf", or up to 1.8 x the
    brightest input). Each block keeps its members' mean radius now."""
    rng = np.random.default_rng(3)
    yy, xx = np.mgrid[:64, :64]
    d = {"rows": yy % 2, "checker": (yy + xx) % 2, "noise": rng.random((64, 64)) > 0.5}[depths].astype(np.float32)
    img = (np.repeat(((xx % 2) * 0.8 + 0.1)[..., None], 3, 2) if photo == "stripes"
           else rng.random((64, 64, 3))).astype(np.float32)
    out = br.render(img, d, br.BlurParams(30.0, 0.5), layers=br.LayerOptions(max_layers=1))
    assert np.isfinite(out).all()
    assert out.min() >= img.min() - 1e-5 and out.max() <= img.max() * (1 + 1e-5)
