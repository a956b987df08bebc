"""The soft layered scene (``bokehray.scene.split_scene``): mixed pixels at depth edges split into a near part
(``alpha F`` at the near CoC) and a far part (B at the far CoC), rendered alike by the preview and the ray tracer.

- exactness: a two-plane stack flattened to a photo, given its exact split, renders like the exact trace of the
  true stack (silhouette ring, the strands' own pixels, the whole image), far better than one depth a pixel;
- the scene: where the near parts go (their layer's sources, boxes, supports, pixel counts, copied tiles), the
  split dropped where both parts fall in one layer or in a copied tile, and the sources of a split pixel summing
  to the photo's pixel (hypothesis);
- a split pixel whose alpha goes to 0 renders like its far part (hypothesis);
- no split pixel: every render bit for bit what it was; tiled renders equal untiled ones with split pixels;
- bad split pixels are refused in one line.
"""

import dataclasses

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from reference import soft_ref as R

import bokehray as br
from bokehray import scene as sc
from bokehray.app.demo import build_demo_scene
from bokehray.errors import InputError
from bokehray.levels import RenderContext, get_level

K, D_FAR, R_NEAR = 40.0, 0.2, 24.0
D_NEAR = D_FAR + R_NEAR / K
NO_MATTING = br.LayerOptions(soft_edges=False)


def _render(quality, image, disparity, blur, soft, *, layers=NO_MATTING, memory=None, options=None):
    """A level's render of a given split (the pipeline's matting bypassed)."""
    level = get_level(quality)
    s = sc.cap_coc(blur.signed_coc(disparity))
    ctx = RenderContext(np.ascontiguousarray(image, np.float32), disparity, s, blur, br.Aperture(), layers,
                        memory or br.MemoryOptions(), options or level.options_type(), "cpu", None, soft)
    return level.render(ctx)


@pytest.fixture(scope="module")
def two_planes():
    scene = R.two_plane_scene()
    h, w = scene["alpha"].shape
    blur = br.BlurParams(K, D_FAR)  # the far plane in focus, the near one blurred 24 px in front of it
    near = np.concatenate([scene["near_rgb"], scene["alpha"][..., None]], axis=-1)
    far = np.concatenate([scene["far_rgb"], np.ones((h, w, 1), np.float32)], axis=-1)
    ex, _ = br.raytrace_layers([br.Layer(near, plane=(0.0, 0.0, D_NEAR)), br.Layer(far, plane=(0.0, 0.0, D_FAR))],
                               blur)
    disparity = np.where(scene["alpha"] >= 0.5, D_NEAR, D_FAR).astype(np.float32)  # one depth a pixel
    soft = sc.SoftEdges(**R.exact_split(scene, R_NEAR, 0.0))
    return dict(scene=scene, blur=blur, exact=ex[..., :3] / np.maximum(ex[..., 3:], 1e-12), disparity=disparity,
                soft=soft, ring=R.silhouette_ring(h, w, scene["disc"]), strands=scene["strands"])


@pytest.mark.parametrize("quality", ["preview", "raytrace"])
def test_an_exact_split_renders_like_the_true_layer_stack(two_planes, quality):
    t = two_planes
    today, _ = _render(quality, t["scene"]["photo"], t["disparity"], t["blur"], None)
    split, _ = _render(quality, t["scene"]["photo"], t["disparity"], t["blur"], t["soft"])
    for name, mask, floor in (("ring", t["ring"], 45.0), ("strands", t["strands"], 40.0), ("whole", None, 45.0)):
        got, before = R.psnr(split, t["exact"], mask), R.psnr(today, t["exact"], mask)
        assert got >= floor, f"{quality} {name}: {got:.1f} dB with the exact split (floor {floor})"
        assert before < floor - 5.0, f"{quality} {name}: {before:.1f} dB with one depth a pixel already"


def test_the_preview_and_the_ray_tracer_render_the_same_soft_scene(two_planes):
    t = two_planes
    pv, _ = _render("preview", t["scene"]["photo"], t["disparity"], t["blur"], t["soft"])
    rt, _ = _render("raytrace", t["scene"]["photo"], t["disparity"], t["blur"], t["soft"],
                    options=br.RaytraceOptions(max_spp=512))
    assert R.psnr(pv, rt) >= 45.0


@pytest.mark.parametrize("quality,tile", [("preview", 48), ("raytrace", 64)])
def test_tiled_renders_of_a_soft_scene_equal_untiled(two_planes, quality, tile):
    t = two_planes
    opts = br.RaytraceOptions(max_spp=16) if quality == "raytrace" else None
    ref, st_ref = _render(quality, t["scene"]["photo"], t["disparity"], t["blur"], t["soft"], options=opts)
    got, st_got = _render(quality, t["scene"]["photo"], t["disparity"], t["blur"], t["soft"], options=opts,
                          memory=br.MemoryOptions(tile_size=tile))
    assert st_ref.image_tiles == 1 and st_got.image_tiles > 4
    assert float(np.abs(ref - got).max()) <= 2e-5 * float(np.abs(ref).max())


# --------------------------------------------------------------------------- the scene


def _two_regions(rng, h, w, far_coc, near_coc):
    """A signed CoC map with a near disc over a far plane, its boundary pixels split with random parts."""
    yy, xx = np.mgrid[0:h, 0:w]
    cy, cx, r = rng.uniform(0, h), rng.uniform(0, w), rng.uniform(0.5, max(h, w) * 0.6 + 1.0)
    dist = np.hypot(yy + 0.5 - cy, xx + 0.5 - cx) - r
    s = np.where(dist < 0, near_coc, far_coc).astype(np.float32)
    edge = np.abs(dist) < 1.0
    edge[[0, -1], :] = edge[:, [0, -1]] = False  # none on the border (whose pad width is the rims' largest CoC)
    idx = np.flatnonzero(edge).astype(np.int64)
    n = len(idx)
    soft = sc.SoftEdges(idx, rng.uniform(0.01, 0.99, n).astype(np.float32), rng.random((n, 3)).astype(np.float32),
                        rng.random((n, 3)).astype(np.float32), np.full(n, near_coc, np.float32),
                        np.full(n, far_coc, np.float32))
    return s, soft


@given(seed=st.integers(0, 2**16), h=st.integers(1, 40), w=st.integers(1, 40),
       far_coc=st.floats(-12.0, 3.0), gap=st.floats(1.5, 20.0), tile_px=st.sampled_from([4, 8, 16]))
def test_a_split_pixels_sources_sum_to_the_photo_and_its_layers_hold_them(seed, h, w, far_coc, gap, tile_px):
    rng = np.random.default_rng(seed)
    near_coc = far_coc + gap
    s, soft = _two_regions(rng, h, w, far_coc, near_coc)
    a = soft.alpha[:, None]
    image = rng.random((h, w, 3)).astype(np.float32)
    image.reshape(-1, 3)[soft.index] = a * soft.foreground + (1 - a) * soft.background  # the photo: their sum
    options = br.LayerOptions(tile_px=tile_px)
    active = np.ones((h, w), bool)
    img, s2, scene = sc.split_scene(image, s, soft, active, options, 8.0)
    near = scene.near
    kept = np.isin(soft.index, near.y.astype(np.int64) * w + near.x)
    # every split here has its parts in two layers (a CoC gap wider than min_layer_px is cut), so it is kept
    layer_of = {lyr.index: lyr for lyr in scene.layers}
    far_ids = scene.ids.reshape(-1)[soft.index]
    assert kept.all() and (near.layer > far_ids).all()
    lo, hi = image.min(axis=(0, 1)), image.max(axis=(0, 1))
    inside = ((soft.foreground >= lo) & (soft.foreground <= hi) & (soft.background >= lo)
              & (soft.background <= hi)).all(axis=1)  # F and B are kept inside the photo's range
    np.testing.assert_array_equal(img.reshape(-1, 3)[soft.index][inside], soft.background[inside])
    assert (img >= lo).all() and (img <= hi).all() and (near.value[:, :3] >= lo * near.value[:, 3:] - 1e-6).all()
    assert (near.value[:, :3] <= hi * near.value[:, 3:] + 1e-6).all()
    np.testing.assert_array_equal(s2.reshape(-1)[soft.index], soft.far_coc)
    img_r, _, scene_r = sc.split_scene(image, s, soft, active, options, 8.0, photo_range=(lo, hi))  # as the preview
    np.testing.assert_array_equal(img_r, img)
    np.testing.assert_array_equal(scene_r.near.value, near.value)
    counts = np.bincount(scene.ids[scene.ids >= 0], minlength=scene.n_slots) + np.bincount(near.layer,
                                                                                            minlength=scene.n_slots)
    for lyr in scene.layers:
        assert lyr.pixels == counts[lyr.index] > 0
    arrays = sc.LayerSources.upload(img, s2, scene.ids, scene.n_slots, "cpu", near)
    sources = {}
    for lyr in scene.layers:
        src, coc = sc.build_layer_sources(lyr.moved((0, h, 0, w)), arrays)
        sources[lyr.index] = (src.numpy(), coc.numpy())
    for i in range(len(near)):
        y, x, ln, lf = int(near.y[i]), int(near.x[i]), int(near.layer[i]), int(scene.ids[near.y[i], near.x[i]])
        y0, y1, x0, x1 = layer_of[ln].bbox  # the near part lies in its layer's box and support
        assert y0 <= y < y1 and x0 <= x < x1
        if layer_of[ln].support is not None:
            assert layer_of[ln].support[y // tile_px, x // tile_px]
        sn, cn = sources[ln][0][y, x], sources[ln][1][y, x]
        sf = sources[lf][0][y, x]
        np.testing.assert_array_equal(sn, near.value[i])
        assert cn == near.coc[i] and sf[3] == 1.0
        over = sn[:3] + (1.0 - sn[3]) * sf[:3]  # the near part over the far part, unblurred
        np.testing.assert_allclose(over, image[y, x], atol=2e-6)


@given(seed=st.integers(0, 2**16), h=st.integers(1, 9), w=st.integers(1, 9), pads=st.tuples(*[st.integers(0, 4)] * 4))
def test_split_pixels_are_padded_like_the_image(seed, h, w, pads):
    rng = np.random.default_rng(seed)
    idx = np.flatnonzero(rng.random(h * w) < 0.5).astype(np.int64)
    n = len(idx)
    soft = sc.SoftEdges(idx, rng.uniform(0.1, 0.9, n).astype(np.float32), rng.random((n, 3)).astype(np.float32),
                        rng.random((n, 3)).astype(np.float32), rng.random(n).astype(np.float32) + 2,
                        rng.random(n).astype(np.float32))
    got = sc.pad_soft_edges(soft, (h, w), pads)
    pt, pb, pl, pr = pads
    dense = np.full(h * w, -1, np.int64)
    dense[idx] = np.arange(n)
    want = np.pad(dense.reshape(h, w), ((pt, pb), (pl, pr)), mode="edge").ravel()  # which split pixel each is
    np.testing.assert_array_equal(got.index, np.flatnonzero(want >= 0))
    k = want[want >= 0]
    for field in ("alpha", "foreground", "background", "near_coc", "far_coc"):
        np.testing.assert_array_equal(getattr(got, field), getattr(soft, field)[k])


def test_a_near_part_alone_makes_its_layer_present_and_its_tile_not_copied():
    h, w = 64, 64
    s = np.zeros((h, w), np.float32)  # all in focus: every tile copied today
    idx = np.array([20 * w + 40], np.int64)
    soft = sc.SoftEdges(idx, np.array([0.3], np.float32), np.ones((1, 3), np.float32), np.zeros((1, 3), np.float32),
                        np.array([6.0], np.float32), np.array([0.0], np.float32))
    assert sc.copy_tiles(np.abs(s), 16).all()
    copy = sc.copy_tiles(sc.soft_radius(s, soft), 16)
    assert not copy[1, 2] and not copy[0, 1] and copy[0, 0] and copy[3, 3]  # its tile and one tile around (7 px)
    active = ~sc.grid_to_pixels(copy, 16, (h, w))
    _, _, scene = sc.split_scene(np.zeros((h, w, 3), np.float32), s, soft, active, br.LayerOptions(), 8.0)
    near = [lyr for lyr in scene.layers if lyr.index == scene.near.layer[0]]
    assert len(near) == 1 and near[0].pixels == 1 and near[0].s_lo <= 6.0 <= near[0].s_hi
    assert scene.max_coc == 6.0


def test_a_split_in_one_layer_or_a_copied_tile_stays_the_photos_pixel():
    h, w = 32, 32
    s = np.zeros((h, w), np.float32)
    s[:, 16:] = 3.0
    soft = sc.SoftEdges(np.array([5 * w + 15, 5 * w + 2], np.int64), np.array([0.4, 0.4], np.float32),
                        np.ones((2, 3), np.float32), np.zeros((2, 3), np.float32),
                        np.array([3.2, 0.3], np.float32), np.array([2.9, 0.0], np.float32))
    image = np.full((h, w, 3), 0.5, np.float32)
    active = np.ones((h, w), bool)
    active[:, :8] = False  # pixel (5, 2) copied
    img, s2, scene = sc.split_scene(image, s, soft, active, br.LayerOptions(), 8.0)
    assert len(scene.near) == 0  # 2.9 and 3.2 fall in one layer, the other split is copied
    np.testing.assert_array_equal(img, image)
    np.testing.assert_array_equal(s2, s)


@given(seed=st.integers(0, 2**16), h=st.integers(1, 30), w=st.integers(1, 30), far_coc=st.floats(-12.0, 3.0),
       gap=st.floats(0.0, 20.0))
def test_split_scene_in_place_equals_the_copies(seed, h, w, far_coc, gap):
    """overwrite=True writes the far parts into the caller's arrays: the same colours, CoCs and scene as the
    copies, splits kept in one layer (a small gap) and splits on inactive pixels included."""
    rng = np.random.default_rng(seed)
    s, soft = _two_regions(rng, h, w, far_coc, far_coc + gap)
    image = rng.random((h, w, 3)).astype(np.float32)
    active = rng.random((h, w)) < 0.9
    active.ravel()[0] = True
    options = br.LayerOptions(tile_px=8)
    img, s2, scene = sc.split_scene(image, s, soft, active, options, 8.0)
    image2, s_in = image.copy(), s.copy()
    img_in, s2_in, scene_in = sc.split_scene(image2, s_in, soft, active, options, 8.0, overwrite=True)
    if len(soft):
        assert img_in is image2 and s2_in is s_in
    np.testing.assert_array_equal(img_in, img)
    np.testing.assert_array_equal(s2_in, s2)
    np.testing.assert_array_equal(scene_in.ids, scene.ids)
    np.testing.assert_array_equal(scene_in.edges, scene.edges)
    assert scene_in.layers == scene.layers and scene_in.max_coc == scene.max_coc
    for f in ("y", "x", "value", "coc", "layer"):
        np.testing.assert_array_equal(getattr(scene_in.near, f), getattr(scene.near, f))


@given(seed=st.integers(0, 2**16), n=st.integers(1, 30))
def test_split_colours_are_kept_inside_the_photos_range_and_sum_to_its_pixel(seed, n):
    rng = np.random.default_rng(seed)
    lo, hi = np.sort(rng.uniform(0.0, 2.0, (2, 3)), axis=0).astype(np.float32)
    a = rng.uniform(0.01, 0.99, n).astype(np.float32)
    photo = rng.uniform(lo, hi, (n, 3)).astype(np.float32)
    fg = (photo + rng.normal(0, 0.5, (n, 3)) * (rng.random((n, 1)) < 0.5)).astype(np.float32)  # some outside
    bg = ((photo - a[:, None] * fg) / (1 - a[:, None])).astype(np.float32)  # the identity holds
    f2, b2 = sc.within_range(a, fg, bg, photo, lo, hi)
    assert (f2 >= lo).all() and (f2 <= hi).all() and (b2 >= lo).all() and (b2 <= hi).all()
    np.testing.assert_allclose(a[:, None] * f2 + (1 - a[:, None]) * b2, photo, atol=1e-5 * (1 + float(hi.max())))
    inside = ((fg >= lo) & (fg <= hi) & (bg >= lo) & (bg <= hi)).all(axis=1)
    np.testing.assert_array_equal(f2[inside], fg[inside])
    np.testing.assert_array_equal(b2[inside], bg[inside])


def test_a_render_with_split_pixels_stays_inside_the_input_range():
    """Found by test_render_api's range test: a split whose F overshoots the photo's largest value by 1e-3."""
    image = np.ones((2, 7, 3), np.float32)
    image[0, 0, 0] = 0.0
    disparity = np.ones((2, 7), np.float32)
    disparity[0, ::2] = disparity[1, 1::2] = 0.0
    a = np.full(2, 0.55, np.float32)
    soft = sc.SoftEdges(np.array([1, 8], np.int64), a, np.array([[1.002, 1, 1]] * 2, np.float32),
                        np.array([[(1 - 0.55 * 1.002) / 0.45, 1, 1]] * 2, np.float32), np.full(2, 2.0, np.float32),
                        np.zeros(2, np.float32))
    for quality in ("preview", "raytrace"):
        out, _ = _render(quality, image, disparity, br.BlurParams(2.0, 0.0), soft)
        assert out.max() <= 1.0 + 1e-6 and out.min() >= 0.0


@given(seed=st.integers(0, 2**16), quality=st.sampled_from(["preview", "raytrace"]))
def test_a_split_pixel_with_no_coverage_renders_like_its_far_part(seed, quality):
    rng = np.random.default_rng(seed)
    h, w = int(rng.integers(8, 40)), int(rng.integers(8, 40))
    blur = br.BlurParams(20.0, 0.3)
    far_coc, near_coc = 0.0, float(rng.uniform(2.0, 8.0))
    s, soft = _two_regions(rng, h, w, far_coc, near_coc)
    disparity = (s / blur.k_px + blur.focus_disparity).astype(np.float32)
    soft = dataclasses.replace(soft, alpha=np.full(len(soft), 1e-7, np.float32))
    image = rng.random((h, w, 3)).astype(np.float32)
    image[0, 0], image[0, 1] = 0.0, 1.0  # the photo's range holds every F and B (none is moved into it)
    far_image = image.copy()
    far_image.reshape(-1, 3)[soft.index] = soft.background
    far_disp = disparity.copy()
    far_disp.reshape(-1)[soft.index] = blur.focus_disparity + soft.far_coc / blur.k_px
    opts = br.RaytraceOptions(max_spp=8) if quality == "raytrace" else None
    got, _ = _render(quality, image, disparity, blur, soft, options=opts)
    want, _ = _render(quality, far_image, far_disp, blur, None, options=opts)
    np.testing.assert_allclose(got, want, atol=1e-5)


# --------------------------------------------------------------------------- no split pixel, bad split pixels


@pytest.mark.parametrize("quality,tile", [("preview", None), ("preview", 48), ("raytrace", None), ("raytrace", 32)])
def test_no_split_pixel_renders_bit_for_bit_as_one_depth_a_pixel(quality, tile):
    demo = build_demo_scene(128, 96)
    blur = br.BlurParams(12.0, 0.2)
    memory = br.MemoryOptions(tile_size=tile)
    opts = br.RaytraceOptions(max_spp=8) if quality == "raytrace" else None
    a, _ = _render(quality, demo.image, demo.disparity, blur, None, memory=memory, options=opts)
    b, _ = _render(quality, demo.image, demo.disparity, blur, sc.SoftEdges.empty(), memory=memory, options=opts)
    assert a.tobytes() == b.tobytes()


def test_the_pipeline_renders_the_matting_split(monkeypatch):
    """``LayerOptions(soft_edges=True)`` renders the split ``bokehray.matting`` returns; False renders none."""
    matting = pytest.importorskip("bokehray.matting")
    t = R.two_plane_scene(64, 96)
    blur = br.BlurParams(K, D_FAR)
    disparity = np.where(t["alpha"] >= 0.5, D_NEAR, D_FAR).astype(np.float32)
    soft = sc.SoftEdges(**R.exact_split(t, R_NEAR, 0.0))
    seen = []
    monkeypatch.setattr(matting, "split_mixed_pixels", lambda image, s, *a, **kw: seen.append(s.shape) or soft)
    got = br.render(t["photo"], disparity, blur)
    want, _ = _render("preview", t["photo"], disparity, blur, soft)
    assert seen == [(64, 96)] and got.tobytes() == want.tobytes()
    off = br.render(t["photo"], disparity, blur, layers=NO_MATTING)
    assert seen == [(64, 96)] and off.tobytes() != got.tobytes()


def test_an_rgba_photo_splits_its_colour_and_renders_its_alpha_with_one_depth_a_pixel(monkeypatch):
    matting = pytest.importorskip("bokehray.matting")
    t = R.two_plane_scene(64, 96)
    blur = br.BlurParams(K, D_FAR)
    disparity = np.where(t["alpha"] >= 0.5, D_NEAR, D_FAR).astype(np.float32)
    soft = sc.SoftEdges(**R.exact_split(t, R_NEAR, 0.0))
    monkeypatch.setattr(matting, "split_mixed_pixels", lambda image, s, *a, **kw: soft)
    alpha = np.linspace(0.0, 1.0, 64 * 96, dtype=np.float32).reshape(64, 96, 1)
    # the split is given, so the map stays as given too (its dashed strands not bridged: bokehray.strands)
    out = br.render(np.concatenate([t["photo"], alpha], axis=2), disparity, blur,
                    layers=br.LayerOptions(strand_gaps=False))
    colour, _ = _render("preview", t["photo"], disparity, blur, soft)
    grey, _ = _render("preview", np.repeat(alpha, 3, axis=2), disparity, blur, None)
    assert out[..., :3].tobytes() == colour.tobytes() and out[..., 3].tobytes() == grey[..., 0].tobytes()


@pytest.mark.parametrize("field,value,match", [
    ("index", np.array([3, 1], np.int64), "sorted unique"),
    ("index", np.array([0, 99], np.int64), "sorted unique"),
    ("alpha", np.array([0.5, 1.0], np.float32), r"alpha in \(0, 1\)"),
    ("far_coc", np.array([0.0, np.nan], np.float32), "finite"),
    ("foreground", np.zeros((1, 3), np.float32), "n entries"),
])
def test_bad_split_pixels_are_refused_in_one_line(field, value, match):
    soft = sc.SoftEdges(np.array([0, 1], np.int64), np.array([0.5, 0.5], np.float32), np.zeros((2, 3), np.float32),
                        np.zeros((2, 3), np.float32), np.ones(2, np.float32), np.zeros(2, np.float32))
    with pytest.raises(InputError, match=match) as e:
        sc.check_soft_edges(dataclasses.replace(soft, **{field: value}), (4, 4))
    assert "\n" not in str(e.value)


def test_a_one_pixel_image_with_a_split_renders():
    soft = sc.SoftEdges(np.array([0], np.int64), np.array([0.5], np.float32), np.ones((1, 3), np.float32),
                        np.zeros((1, 3), np.float32), np.array([5.0], np.float32), np.array([0.0], np.float32))
    for quality in ("preview", "raytrace"):
        out, _ = _render(quality, np.full((1, 1, 3), 0.5, np.float32), np.full((1, 1), 0.2, np.float32),
                         br.BlurParams(10.0, 0.2), soft)
        assert out.shape == (1, 1, 3) and np.isfinite(out).all()
