"""The layered ray tracer against a NumPy ray tracer, the exact convolution limit, and photo mode."""

import numpy as np
import pytest

import bokehray as br
from bokehray.levels.raytrace import Layer, raytrace_layers
from bokehray.options import RaytraceOptions
from reference import raytrace_ref


def _fixed(spp: int, seed: int = 0) -> RaytraceOptions:
    return RaytraceOptions(samples_per_px2=1e6, max_spp=spp, min_spp=spp, seed=seed)


def test_two_layers_match_numpy_ray_tracer_including_partial_occlusion(device):
    rng = np.random.default_rng(5)
    h, w = 12, 14
    back = np.concatenate([rng.random((h, w, 3)), np.ones((h, w, 1))], 2).astype(np.float32)
    front = np.zeros((h, w, 4), np.float32)
    front[3:9, 4:10] = [1.0, 0.2, 0.1, 1.0]  # an opaque square ...
    front[3:9, 9] = [1.0, 0.2, 0.1, 0.5]  # ... with a half-transparent column
    layers = [(front, (0.0, 0.0, 0.9)), (back, (0.01, -0.02, 0.2))]  # tilted background
    blur = br.BlurParams(6.0, 0.2)  # background in focus, square blurred: its edge shows the background
    got, _ = raytrace_layers([Layer(t, plane=p) for t, p in layers], blur, options=_fixed(24), device=device)
    want = raytrace_ref.trace(layers, 6.0, 0.2, 24)
    np.testing.assert_allclose(got, want, atol=2e-5)
    back_only, _ = raytrace_layers([Layer(back, plane=layers[1][1])], blur, options=_fixed(24), device=device)
    # just outside the square the blurred red spreads over the background ...
    assert got[6, 11, 0] > back_only[6, 11, 0] + 0.05
    # ... and just inside its edge the background shows through the blurred foreground
    inside = got[6, 4, :3]
    assert np.abs(inside - [1.0, 0.2, 0.1]).max() > 0.1
    np.testing.assert_allclose(got[..., 3], 1.0, atol=1e-6)  # the opaque background ends every ray


def test_single_fronto_parallel_layer_converges_to_the_disc_convolution():
    rng = np.random.default_rng(1)
    h, w = 48, 48
    tex = np.concatenate([rng.random((h, w, 3)), np.ones((h, w, 1))], 2).astype(np.float32)
    blur = br.BlurParams(8.0, 0.5)  # layer at d = 0: radius 4 px
    truth, _ = raytrace_layers([Layer(tex, plane=(0, 0, 0.0))], blur, options=_fixed(4096))
    errors = []
    for spp in (16, 64, 256):
        got, _ = raytrace_layers([Layer(tex, plane=(0, 0, 0.0))], blur, options=_fixed(spp, seed=3))
        errors.append(np.sqrt(np.mean((got[8:-8, 8:-8, :3] - truth[8:-8, 8:-8, :3]) ** 2)))
    assert errors[0] > errors[1] > errors[2]
    # stratified (spiral) sampling: error falls faster than Monte Carlo's 1/sqrt(N) (a factor 4 over 16x)
    assert errors[0] / errors[2] > 6.0
    # and the converged image is the preview's disc convolution up to texture filtering (bilinear vs box)
    preview = br.render(tex[..., :3], np.zeros((h, w), np.float32), blur,
                        options=br.PreviewOptions(level_radius_px=1e6))
    assert np.abs(truth[8:-8, 8:-8, :3] - preview[8:-8, 8:-8]).mean() < 0.01


def test_map_layer_equals_plane_layer():
    rng = np.random.default_rng(2)
    h, w = 20, 24
    tex = np.concatenate([rng.random((h, w, 3)), np.ones((h, w, 1))], 2).astype(np.float32)
    plane = (0.004, 0.002, 0.3)
    yy, xx = np.mgrid[0:h, 0:w] + 0.5
    d = (plane[0] * xx + plane[1] * yy + plane[2]).astype(np.float32)
    blur = br.BlurParams(10.0, 0.8)
    a, _ = raytrace_layers([Layer(tex, plane=plane)], blur, options=_fixed(32))
    b, _ = raytrace_layers([Layer(tex, disparity=d)], blur, options=_fixed(32))
    np.testing.assert_allclose(a, b, atol=5e-3)  # the march refines a linear crossing: near-exact on a plane


def test_adaptive_sampling_and_determinism():
    h, w = 16, 16
    tex = np.ones((h, w, 4), np.float32)
    d = np.zeros((h, w), np.float32)
    d[:, 8:] = 1.0
    blur = br.BlurParams(8.0, 0.0)  # left half in focus (1 ray), right half r = 8
    opts = RaytraceOptions(samples_per_px2=0.5, max_spp=64)
    a, st = raytrace_layers([Layer(tex, disparity=d)], blur, options=opts)
    b, _ = raytrace_layers([Layer(tex, disparity=d)], blur, options=opts)
    np.testing.assert_array_equal(a, b)
    assert st.spp_max == 64 and st.samples_total == 8 * 16 * 1 + 8 * 16 * 64


def test_photo_mode_is_close_to_the_preview_and_identity_in_focus():
    scene = __import__("bokehray.demo", fromlist=["build_demo_scene"]).build_demo_scene(width=128, height=96)
    blur = br.BlurParams(scene.k_px, scene.focus_near)
    rt, stats = br.render_with_stats(scene.image, scene.disparity, blur, quality="raytrace",
                                     options=RaytraceOptions(max_spp=64))
    pv = br.render(scene.image, scene.disparity, blur)
    assert np.isfinite(rt).all() and stats.layers >= 3
    srgb = lambda x: br.io.linear_to_srgb(np.clip(x, 0, 1))  # noqa: E731
    assert 10 * np.log10(1 / np.mean((srgb(rt) - srgb(pv)) ** 2)) > 28
    same = br.render(scene.image, scene.disparity, br.BlurParams(0.0, 0.5), quality="raytrace")
    np.testing.assert_array_equal(same, scene.image)


@pytest.mark.parametrize(
    ("layers", "match"),
    [
        ([], "at least one"),
        ([Layer(np.zeros((4, 4, 3), np.float32), plane=(0, 0, 0))], "RGBA"),
        ([Layer(np.zeros((4, 4, 4), np.float32))], "exactly one"),
        ([Layer(np.zeros((4, 4, 4), np.float32), disparity=np.full((4, 4), np.nan, np.float32))], "NaN"),
        ([Layer(np.zeros((4, 4, 4), np.float32), plane=(0, 0, 0)),
          Layer(np.zeros((5, 4, 4), np.float32), plane=(0, 0, 0))], "size"),
    ],
)
def test_bad_layers_are_rejected(layers, match):
    with pytest.raises(br.InputError, match=match):
        raytrace_layers(layers, br.BlurParams(1.0, 0.5))


@pytest.mark.parametrize("d_f", [0.0, 1.0])  # the light in front of focus, then behind it
def test_preview_and_ray_tracer_agree_on_the_aperture_orientation(d_f):
    h = w = 41
    img = np.zeros((h, w, 3), np.float32)
    img[20, 20] = 100.0
    layer_d = 0.5
    blur = br.BlurParams(24.0, d_f)  # radius 12, a triangle that points one way
    ap = br.Aperture(blades=3, rotation_deg=90.0)
    preview = br.render(img, np.full((h, w), layer_d, np.float32), blur, ap,
                        options=br.PreviewOptions(level_radius_px=1e6))[..., 0]
    rgba = np.concatenate([img, np.ones((h, w, 1), np.float32)], axis=2)
    traced, _ = raytrace_layers([Layer(rgba, plane=(0.0, 0.0, layer_d))], blur, ap, options=_fixed(512))
    traced = traced[..., 0]
    corr = lambda a, b: float(np.corrcoef(a.ravel(), b.ravel())[0, 1])  # noqa: E731
    assert corr(preview, traced) > 0.9 > corr(preview[::-1, ::-1], traced)
