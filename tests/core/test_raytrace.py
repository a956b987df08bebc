"""The layered ray tracer against a NumPy ray tracer, exact convolutions and apertures, and photo mode."""

import itertools
import os
import signal
import threading
import time

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from reference import raytrace_ref
from scipy.ndimage import binary_erosion
from tolerances import HANG_S

import bokehray as br
from bokehray.levels.quadrature import cells
from bokehray.levels.raytrace import Layer, raytrace_layers
from bokehray.levels.raytrace_launch import strip_cap
from bokehray.options import RaytraceOptions

APERTURES = [br.Aperture(), br.Aperture(blades=6, rotation_deg=10.0), br.Aperture(blades=5, curvature=0.3)]


def _psnr_lin(a, b):
    return float(10 * np.log10(1.0 / np.mean((np.asarray(a, np.float64) - b) ** 2)))


@pytest.mark.parametrize("aperture", APERTURES[:2])
def test_two_layers_match_numpy_ray_tracer_including_partial_occlusion(device, aperture):
    rng = np.random.default_rng(5)
    h, w = 12, 14
    back = np.concatenate([rng.random((h, w, 3)), np.ones((h, w, 1))], 2).astype(np.float32)
    front = np.zeros((h, w, 4), np.float32)
    front[3:9, 4:10] = [1.0, 0.2, 0.1, 1.0]  # an opaque square ...
    front[3:9, 9] = [1.0, 0.2, 0.1, 0.5]  # ... with a half-transparent column
    layers = [(front, (0.0, 0.0, 0.9)), (back, (0.01, -0.02, 0.2))]  # tilted background
    blur = br.BlurParams(6.0, 0.2)  # background in focus, square blurred: its edge shows the background
    opts = RaytraceOptions(samples_per_px2=1e6, max_spp=40, min_spp=40)  # the same cells everywhere
    got, st_ = raytrace_layers([Layer(t, plane=p) for t, p in layers], blur, aperture, options=opts, device=device)
    want = raytrace_ref.trace(layers, 6.0, 0.2, opts, aperture)
    assert st_.spp_max <= 40 and all(g <= 7 for g, _ in st_.partitions)  # at most sqrt(4 * 40 / pi) = 7.1 strips
    np.testing.assert_allclose(got, want, atol=2e-5)
    back_only, _ = raytrace_layers([Layer(back, plane=layers[1][1])], blur, aperture, options=opts, device=device)
    # just outside the square the blurred red spreads over the background ...
    assert got[6, 11, 0] > back_only[6, 11, 0] + 0.05
    # ... and just inside its edge the background shows through the blurred foreground
    assert np.abs(got[6, 4, :3] - [1.0, 0.2, 0.1]).max() > 0.1
    np.testing.assert_allclose(got[..., 3], 1.0, atol=1e-6)  # the opaque background ends every ray


@pytest.mark.parametrize("aperture", APERTURES)
@pytest.mark.parametrize("strips", [2, 5, 12, 24])
def test_cells_partition_the_aperture(aperture, strips):
    """Boxes do not overlap, weights are their areas and sum to 1, and their union is the aperture
    to within the outline tolerance of its area."""
    outline = 0.02
    c = cells(aperture, strips, sub_rows=max(2, int(np.ceil(1.0 / strips / outline))), tol=outline)
    np.testing.assert_allclose(c[:, 4].sum(), 1.0, rtol=1e-12)
    area = 4 * c[:, 2] * c[:, 3]
    np.testing.assert_allclose(c[:, 4], area / area.sum(), rtol=1e-9)
    n = 797  # not a multiple of the strip counts: no grid point on a shared edge
    g = (np.arange(n) + 0.5) / n * 2 - 1
    xx, yy = np.meshgrid(g, g)
    count = np.zeros((n, n), np.int32)
    for ux, uy, hx, hy, _ in c:
        count += (np.abs(xx - ux) < hx) & (np.abs(yy - uy) < hy)
    assert count.max() == 1  # no overlaps
    truth = raytrace_ref.inside(aperture)(xx, yy)
    sym_diff = np.mean((count > 0) != truth) * 4.0
    assert sym_diff < 1.5 * outline * np.pi  # outline tolerance, in unit-circumradius units times the perimeter


@pytest.mark.parametrize("aperture", APERTURES)
def test_one_strip_is_one_box_of_the_apertures_area_on_its_centroid(aperture):
    (ux, uy, hx, hy, weight), = cells(aperture, 1)
    n = 2001
    g = (np.arange(n) + 0.5) / n * 2 - 1
    xx, yy = np.meshgrid(g, g)
    inside = raytrace_ref.inside(aperture)(xx, yy)
    np.testing.assert_allclose(4 * hx * hy, inside.mean() * 4.0, rtol=2e-3)
    np.testing.assert_allclose([ux, uy], [xx[inside].mean(), yy[inside].mean()], atol=2e-3)
    assert hx == hy and weight == 1.0


def test_single_fronto_parallel_layer_is_the_exact_disc_convolution_at_defaults(device):
    """A random texture at r = 10 px >= 45 dB against the exact disc convolution (no noise)."""
    rng = np.random.default_rng(1)
    h = w = 48
    tex = np.concatenate([rng.random((h, w, 3)), np.ones((h, w, 1))], 2).astype(np.float32)
    blur = br.BlurParams(20.0, 0.5)  # layer at d = 0: radius 10 px, behind focus
    got, _ = raytrace_layers([Layer(tex, plane=(0, 0, 0.0))], blur, device=device)
    want = raytrace_ref.disc_convolution(tex[..., :3], 10.0, raytrace_ref.inside(br.Aperture()))
    assert _psnr_lin(got[..., :3], want) > 45.0
    srgb = lambda x: br.colour.linear_to_srgb(np.clip(x, 0, 1))  # noqa: E731
    assert _psnr_lin(srgb(got[..., :3]), srgb(want)) > 45.0
    # and it is the preview's disc convolution up to the preview's own filtering
    preview = br.render(tex[..., :3], np.zeros((h, w), np.float32), blur,
                        options=br.PreviewOptions(level_radius_px=1e6))
    assert np.abs(got[..., :3] - preview).mean() < 0.01


@pytest.mark.parametrize("aperture", APERTURES)
@pytest.mark.parametrize("radius", [16, 64])
def test_point_light_spread_is_the_exact_aperture(aperture, radius):
    """A point light's spread within 4 % L1 of the exact aperture (R = 256: benchmarks/renderer/bench_raytrace.py)."""
    n = 2 * radius + 9
    c = n // 2
    tex = np.zeros((n, n, 4), np.float32)
    tex[..., 3] = 1.0
    tex[c, c, :3] = 1000.0
    got, _ = raytrace_layers([Layer(tex, plane=(0, 0, 0.0))], br.BlurParams(float(radius), 1.0), aperture)
    spread = got[..., 0] / 1000.0
    light = np.zeros((n, n, 1))
    light[c, c] = 1.0
    want = raytrace_ref.disc_convolution(light, float(radius), raytrace_ref.inside(aperture), sub=8)[..., 0]
    np.testing.assert_allclose(spread.sum(), 1.0, atol=1e-4)  # energy conserved
    assert np.abs(spread - want).sum() < 0.04
    # two pixels inside the outline: a flat plateau of the right height
    inner = binary_erosion(want > 0.999 * want.max(), iterations=2)
    np.testing.assert_allclose(spread[inner], want[inner], rtol=1e-2)  # 1 / the polygonised area


@given(k=st.floats(0.5, 40.0), d_f=st.floats(0.0, 1.0), d=st.floats(0.0, 1.0), blades=st.sampled_from([0, 3, 5, 8]),
       colour=st.floats(0.0, 50.0))
def test_a_flat_opaque_layer_keeps_its_colour_for_any_blur(k, d_f, d, blades, colour):
    """Energy conservation: every cell table integrates to 1, at any radius, for any aperture."""
    tex = np.ones((9, 9, 4), np.float32)
    tex[..., :3] = colour
    got, _ = raytrace_layers([Layer(tex, plane=(0.0, 0.0, d))], br.BlurParams(k, d_f), br.Aperture(blades=blades))
    np.testing.assert_allclose(got[..., :3], colour, rtol=2e-5, atol=1e-6)
    np.testing.assert_allclose(got[..., 3], 1.0, atol=1e-6)


def test_map_layer_equals_plane_layer():
    rng = np.random.default_rng(2)
    h, w = 20, 24
    tex = np.concatenate([rng.random((h, w, 3)), np.ones((h, w, 1))], 2).astype(np.float32)
    plane = (0.004, 0.002, 0.3)
    yy, xx = np.mgrid[0:h, 0:w] + 0.5
    d = (plane[0] * xx + plane[1] * yy + plane[2]).astype(np.float32)
    blur = br.BlurParams(10.0, 0.8)
    opts = RaytraceOptions(max_spp=32)
    a, _ = raytrace_layers([Layer(tex, plane=plane)], blur, options=opts)
    b, _ = raytrace_layers([Layer(tex, disparity=d)], blur, options=opts)
    np.testing.assert_allclose(a, b, atol=5e-3)  # the march refines a linear crossing: near-exact on a plane


def test_adaptive_cells_determinism_and_stats():
    h, w = 16, 16
    tex = np.ones((h, w, 4), np.float32)
    d = np.zeros((h, w), np.float32)
    d[:, 8:] = 1.0
    blur = br.BlurParams(8.0, 0.0)  # left half in focus (1 ray), right half r = 8
    opts = RaytraceOptions(samples_per_px2=0.5, max_spp=64)
    a, st_ = raytrace_layers([Layer(tex, disparity=d)], blur, options=opts)
    b, _ = raytrace_layers([Layer(tex, disparity=d)], blur, options=opts)
    np.testing.assert_array_equal(a, b)
    assert 20 < st_.spp_max <= 64  # the cap holds, outline cells included
    assert st_.samples_total == 8 * 16 * 1 + 8 * 16 * st_.spp_max  # 1 ray in focus, the same cells at r = 8
    assert len(st_.partitions) == 1 and st_.partitions[0][0] <= strip_cap(64) == 9
    np.testing.assert_allclose(a[..., :3], 1.0, rtol=1e-5)
    assert set(st_.stage_seconds) >= {"setup", "trace", "total"}


def test_more_cells_converge_on_a_three_layer_stack():
    """Occlusion between two blurred layers is resolved per cell: 16x the cells changes little."""
    rng = np.random.default_rng(3)
    n = 64
    yy, xx = np.mgrid[0:n, 0:n] + 0.5
    back = np.concatenate([rng.random((n, n, 3)), np.ones((n, n, 1))], 2).astype(np.float32)
    mid = np.zeros((n, n, 4), np.float32)
    mid[(xx - 30) ** 2 + (yy - 34) ** 2 < 15**2] = [0.2, 0.7, 0.3, 1.0]
    front = np.zeros((n, n, 4), np.float32)
    front[..., :3] = [1.0, 0.9, 0.6]
    front[..., 3] = np.clip(1.2 - np.abs(xx - 40 - 0.2 * yy), 0, 1)  # a thin strand
    layers = [Layer(front, plane=(0, 0, 0.9)), Layer(mid, plane=(0.002, 0, 0.5)), Layer(back, plane=(0, 0, 0.1))]
    blur = br.BlurParams(20.0, 0.1)  # strand r = 16, disc r = 8, background in focus
    a, _ = raytrace_layers(layers, blur)
    b, _ = raytrace_layers(layers, blur, options=RaytraceOptions(samples_per_px2=8.0, max_spp=2048))
    srgb = lambda x: br.colour.linear_to_srgb(np.clip(x, 0, 1))  # noqa: E731
    assert _psnr_lin(srgb(a[..., :3]), srgb(b[..., :3])) > 45.0


def test_progress_is_reported_and_an_interrupt_stops_the_trace():
    tex = np.ones((256, 256, 4), np.float32)
    calls = []
    raytrace_layers([Layer(tex, plane=(0, 0, 0.0))], br.BlurParams(30.0, 1.0),
                    progress=lambda done, total: calls.append((done, total)))
    assert len(calls) > 2 and calls[-1][0] == calls[-1][1] and all(a[0] < b[0] for a, b in itertools.pairwise(calls))

    seen = []

    def stop(done, total):
        seen.append(done)
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        raytrace_layers([Layer(tex, plane=(0, 0, 0.0))], br.BlurParams(30.0, 1.0), progress=stop)
    assert len(seen) == 1 and seen[0] < calls[-1][1]  # stopped at the first report, long before the end


def _photo_case(tmp_path=None):
    rng = np.random.default_rng(0)
    img = rng.random((768, 1024, 3)).astype(np.float32)
    disp = np.tile(np.linspace(0, 1, 1024, dtype=np.float32), (768, 1))  # 16 slices, CoC up to 30 px
    return img, disp


@pytest.mark.slow
@pytest.mark.parametrize("after_s", [1.5, 6.0])  # while the layers are built, then while tracing
def test_ctrl_c_stops_a_photo_raytrace(after_s):
    img, disp = _photo_case()
    sent = []

    def interrupt():
        time.sleep(after_s)
        sent.append(time.perf_counter())
        os.kill(os.getpid(), signal.SIGINT)

    threading.Thread(target=interrupt, daemon=True).start()
    with pytest.raises(KeyboardInterrupt):
        br.render(img, disp, br.BlurParams(60.0, 0.5), quality="raytrace")  # takes far longer than 6 s
    assert time.perf_counter() - sent[0] < HANG_S  # the whole render takes longer; the figure: docs/robustness.md


def test_photo_mode_is_close_to_the_preview_and_identity_in_focus():
    scene = __import__("bokehray.app.demo", fromlist=["build_demo_scene"]).build_demo_scene(width=128, height=96)
    blur = br.BlurParams(scene.k_px, scene.focus_near)
    rt, stats = br.render_with_stats(scene.image, scene.disparity, blur, quality="raytrace",
                                     options=RaytraceOptions(max_spp=64))
    pv = br.render(scene.image, scene.disparity, blur)
    assert np.isfinite(rt).all() and stats.layers >= 3
    srgb = lambda x: br.colour.linear_to_srgb(np.clip(x, 0, 1))  # noqa: E731
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
    traced, _ = raytrace_layers([Layer(rgba, plane=(0.0, 0.0, layer_d))], blur, ap)
    traced = traced[..., 0]
    corr = lambda a, b: float(np.corrcoef(a.ravel(), b.ravel())[0, 1])  # noqa: E731
    assert corr(preview, traced) > 0.95 and corr(preview, traced) > corr(preview[::-1, ::-1], traced) + 0.2
