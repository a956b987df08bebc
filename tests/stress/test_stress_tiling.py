"""Tiled rendering equals the untiled render; memory budgets refuse early with ResourceError."""

import re

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

import bokehray as br
from bokehray import scene as sc
from bokehray import tiling
from bokehray.app.demo import build_demo_scene
from bokehray.errors import ResourceError

# Tiles and the untiled render do the same arithmetic except where a row's prefix sum starts
# (another column), so they differ by float32 rounding relative to the brightest value.
TILE_RTOL = 2e-5


@pytest.fixture(scope="module")
def scene():
    return build_demo_scene(160, 112)


def _blur(scene, radius):
    f = scene.focus_near
    return br.BlurParams(radius / max(float(np.abs(scene.disparity - f).max()), 1e-6), f)


def _rel(a, b):
    return float(np.abs(a - b).max() / max(float(np.abs(a).max()), 1e-30))


@pytest.mark.parametrize("radius,tile,aperture", [
    (3.0, 16, br.Aperture()), (12.0, 40, br.Aperture(blades=5, rotation_deg=10.0, curvature=0.3)),
    (30.0, 64, br.Aperture()), (12.0, 24, br.Aperture(blades=6))])
def test_tiled_preview_equals_untiled(scene, radius, tile, aperture):
    blur = _blur(scene, radius)
    ref, st_ref = br.render_with_stats(scene.image, scene.disparity, blur, aperture)
    got, st_got = br.render_with_stats(scene.image, scene.disparity, blur, aperture,
                                       memory=br.MemoryOptions(tile_size=tile))
    assert st_ref.image_tiles == 1 and st_got.image_tiles == -(-160 // tile) * -(-112 // tile)
    assert _rel(ref, got) <= TILE_RTOL


def test_tiles_without_the_halo_or_the_alignment_would_differ(scene, monkeypatch):
    """The halo and the pyramid alignment are what make tiles exact (this test fails if either is dropped)."""
    blur = _blur(scene, 16.0)
    ref = br.render(scene.image, scene.disparity, blur)
    halo = sc.scatter_halo  # the one place a layer's reach is defined: bokehray.scene
    for broken in (lambda lyr, r0: (int(lyr.max_radius) + 2, halo(lyr, r0)[1]),  # scatter reach only, no fill
                   lambda lyr, r0: (halo(lyr, r0)[0], 1)):  # no alignment of the pyramids
        monkeypatch.setattr(sc, "scatter_halo", broken)
        got = br.render(scene.image, scene.disparity, blur, memory=br.MemoryOptions(tile_size=32))
        assert _rel(ref, got) > 100 * TILE_RTOL
    monkeypatch.setattr(sc, "scatter_halo", halo)


@given(seed=st.integers(0, 2**16), k=st.floats(0.0, 40.0), d_f=st.floats(0.0, 1.0), tile=st.integers(16, 48),
       fill=st.booleans())
def test_tiled_preview_equals_untiled_on_random_scenes(seed, k, d_f, tile, fill):
    rng = np.random.default_rng(seed)
    h, w = int(rng.integers(1, 70)), int(rng.integers(1, 70))
    image = (rng.random((h, w, 3)) ** 3 * 20).astype(np.float32)
    d = np.where(rng.random((h, w)) < 0.5, rng.random((h, w)), (np.arange(w)[None] > w // 3) * 0.8)
    d = np.clip(d, 0, 1).astype(np.float32)
    layers = br.LayerOptions(fill=fill)
    ref = br.render(image, d, br.BlurParams(k, d_f), layers=layers)
    got = br.render(image, d, br.BlurParams(k, d_f), layers=layers, memory=br.MemoryOptions(tile_size=tile))
    assert _rel(ref, got) <= TILE_RTOL


@pytest.mark.parametrize("radius", [3.0, 10.0])
def test_tiled_raytrace_equals_untiled(scene, radius):
    blur = _blur(scene, radius)
    rays = br.RaytraceOptions(max_spp=8)
    ref, st_ref = br.render_with_stats(scene.image, scene.disparity, blur, quality="raytrace", options=rays)
    got, st_got = br.render_with_stats(scene.image, scene.disparity, blur, quality="raytrace", options=rays,
                                       memory=br.MemoryOptions(tile_size=32))
    assert st_got.image_tiles == 20 and st_got.samples_total == st_ref.samples_total  # the same rays
    assert _rel(ref, got) <= TILE_RTOL


def test_rgba_and_grey_tile_too(scene):
    rgba = np.concatenate([scene.image, np.linspace(0, 1, 160)[None, :, None].repeat(112, 0)], 2).astype(np.float32)
    blur = _blur(scene, 8.0)
    for img in (rgba, scene.image[..., :1]):
        ref = br.render(img, scene.disparity, blur)
        got = br.render(img, scene.disparity, blur, memory=br.MemoryOptions(tile_size=48))
        assert got.shape == img.shape and _rel(ref, got) <= TILE_RTOL


def test_automatic_tiling_when_the_untiled_render_does_not_fit(scene):
    blur = _blur(scene, 6.0)
    # no fill: a halo of ~12 px instead of ~100, so tiles pay off even on this small image
    no_fill = br.LayerOptions(fill=False)
    ref, st_ref = br.render_with_stats(scene.image, scene.disparity, blur, layers=no_fill)
    assert st_ref.image_tiles == 1 and st_ref.memory_estimate_mb > 0
    # a budget below the untiled estimate but above what a small tile needs
    budget = 0.6 * st_ref.memory_estimate_mb
    got, st_got = br.render_with_stats(scene.image, scene.disparity, blur,
                                       layers=no_fill, memory=br.MemoryOptions(memory_limit_mb=budget))
    assert st_got.image_tiles > 1 and st_got.memory_estimate_mb <= budget
    assert _rel(ref, got) <= TILE_RTOL


@pytest.mark.parametrize("quality", ["preview", "raytrace"])
def test_a_render_that_cannot_fit_fails_early_with_a_clear_message(scene, quality):
    blur = _blur(scene, 20.0)
    with pytest.raises(ResourceError, match=r"needs about [\d,]+ MB, but the memory budget is 0 MB"):
        br.render(scene.image, scene.disparity, blur, quality=quality, memory=br.MemoryOptions(memory_limit_mb=0.01))
    # the whole-image arrays fit, no tile does
    with pytest.raises(ResourceError, match="tiles do not fit") as refused:
        br.render(scene.image, scene.disparity, blur, quality=quality, memory=br.MemoryOptions(memory_limit_mb=1.0))
    if quality == "preview":  # it names the image's size (the clamped border is dropped first when it cannot fit)
        h, w = scene.disparity.shape
        assert re.search(rf"of (the )?{w} x {h} px", str(refused.value))
    assert isinstance(ResourceError("x"), MemoryError)  # callers catching MemoryError see it too


def test_forced_tile_too_large_for_the_budget_is_refused(scene):
    with pytest.raises(ResourceError, match="in 160 px tiles.*choose a smaller tile_size"):
        br.render(scene.image, scene.disparity, _blur(scene, 20.0),
                  memory=br.MemoryOptions(tile_size=160, memory_limit_mb=1.5))


@pytest.mark.parametrize("quality", ["preview", "raytrace"])
def test_enormous_request_is_refused_before_allocating(quality):
    """A 100 000 x 100 000 render (1e10 px) is refused from its shape: no array of that size is ever made,
    neither through the public API nor through the preview's signed-CoC seam."""
    from bokehray.levels.preview import render_signed_coc

    s = np.broadcast_to(np.float32(5.0), (100_000, 100_000))  # a view: no memory
    img = np.broadcast_to(np.float32(1.0), (100_000, 100_000, 3))
    with pytest.raises(ResourceError, match="100000 x 100000 px.*whole-image arrays alone do not fit"):
        br.render(img, s, br.BlurParams(5.0, 0.0), quality=quality)
    with pytest.raises(ResourceError, match="100000 x 100000 px.*whole-image arrays alone do not fit"):
        render_signed_coc(img, s, br.Aperture())


@pytest.mark.parametrize("kwargs", [{"tile_size": 0}, {"tile_size": 8}, {"tile_size": True}, {"tile_size": 3.5},
                                    {"memory_limit_mb": 0}, {"memory_limit_mb": float("nan")},
                                    {"memory_limit_mb": -1.0}, {"memory_limit_mb": "1G"}])
def test_bad_tiling_options_are_rejected(kwargs):
    with pytest.raises(br.InputError, match=next(iter(kwargs))):
        # a tile smaller than the layer grid (tile_px = 16) is valid alone and refused with the layers
        br.render(np.zeros((4, 4, 3), np.float32), np.zeros((4, 4), np.float32), br.BlurParams(1.0, 0.5),
                  memory=br.MemoryOptions(**kwargs))


def test_available_memory_is_read():
    assert tiling.available_bytes() > 0
    assert tiling.budget_bytes(br.MemoryOptions(memory_limit_mb=10)) == 10 * 2**20


def test_tiles_equal_untiled_on_an_all_edges_map_with_soft_edges():
    """Regression: 10 pixels of one row of a 16 px tile differed by 9.6e-5 of the brightest value. A cluster source of
    mean radius 12.000002 centred on a row edge reaches 2e-6 px above the row edge 12 rows up: ``floor(yc - rho)``
    rounded onto that edge in the whole frame (y = 113) and not in the tile's window (y = 39), so the graded top
    row was one row apart (``bokehray_kernels.spans.rows_of`` counts rows from the centre's fraction now)."""
    rng = np.random.default_rng(1)
    h, w = 96, 112
    img = (rng.random((h, w, 3)) ** 3 * 20).astype(np.float32)
    yy, xx = np.mgrid[:h, :w]
    d = ((xx + yy) % 2).astype(np.float32)
    ref = br.render(img, d, br.BlurParams(24.0, 0.5))
    got = br.render(img, d, br.BlurParams(24.0, 0.5), memory=br.MemoryOptions(tile_size=16))
    assert _rel(ref, got) <= TILE_RTOL
