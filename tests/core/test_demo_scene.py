"""Tests of the built-in demo scene and the contact sheet."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import ndimage

from bokehray.app.demo import SHEET_GAP, SHEET_LABEL_H, DemoScene, build_demo_scene, contact_sheet, stroke
from bokehray.errors import InputError


@pytest.fixture(scope="module")
def scene() -> DemoScene:
    return build_demo_scene()


def test_shapes_dtypes_ranges(scene: DemoScene) -> None:
    assert scene.image.shape == (512, 768, 3) and scene.image.dtype == np.float32
    assert scene.disparity.shape == (512, 768) and scene.disparity.dtype == np.float32
    assert np.isfinite(scene.image).all() and scene.image.min() >= 0.0
    assert np.isfinite(scene.disparity).all()
    assert scene.disparity.min() >= 0.0 and scene.disparity.max() <= 1.0
    lum = scene.image.max(axis=2)
    assert (lum > 1.0).sum() > 20  # HDR highlights that become bokeh balls
    assert 4.0 <= lum.max() <= 20.0
    assert np.median(lum) < 1.0  # mostly plausible radiance
    assert 0.8 <= scene.focus_near <= 1.0 and 0.0 <= scene.focus_far <= 0.25
    assert isinstance(scene.description, str) and scene.description


def test_k_gives_about_24px_max_coc(scene: DemoScene) -> None:
    coc = max(float(np.abs(scene.disparity - f).max()) for f in (scene.focus_near, scene.focus_far))
    assert scene.k_px * coc == pytest.approx(24.0, rel=0.1)
    assert build_demo_scene(384, 256).k_px == pytest.approx(scene.k_px / 2, rel=0.1)


def test_focus_near_is_subject_centre(scene: DemoScene) -> None:
    d = scene.disparity
    assert np.abs(d - scene.focus_near).min() < 0.01
    near = d > 0.85
    # the subject is a large connected region whose disparity peaks at focus_near
    assert near.mean() > 0.1


def test_deterministic() -> None:
    a, b = build_demo_scene(seed=3), build_demo_scene(seed=3)
    np.testing.assert_array_equal(a.image, b.image)
    np.testing.assert_array_equal(a.disparity, b.disparity)
    assert a.k_px == b.k_px
    c = build_demo_scene(seed=4)
    assert not np.array_equal(a.image, c.image)


def test_near_mid_far_content(scene: DemoScene) -> None:
    d = scene.disparity
    assert (d > 0.8).mean() > 0.05
    assert ((d > 0.4) & (d < 0.6)).mean() > 0.05
    assert (d < 0.25).mean() > 0.3


def test_tilted_surfaces(scene: DemoScene) -> None:
    d = scene.disparity
    bg = d[d < 0.25]
    assert bg.max() - bg.min() > 0.1  # receding background plane
    mid = d[(d > 0.4) & (d < 0.6)]
    assert mid.max() - mid.min() > 0.05  # tilted panel
    # the background varies linearly: rows of the sky strip are monotone in y
    col = d[:40, 5]
    assert np.all(np.diff(col[col < 0.25]) >= 0)


def test_thin_structures(scene: DemoScene) -> None:
    d = scene.disparity
    near = d >= 0.65
    far = d < 0.6
    far_count = ndimage.convolve(far.astype(np.int32), np.ones((3, 3), np.int32), mode="nearest")
    thin = near & (far_count >= 5)
    assert thin.sum() > 300
    # an opening with a 3x3 square removes thin strands but keeps the subject
    opened = ndimage.binary_opening(near, structure=np.ones((3, 3), bool))
    assert (near & ~opened).sum() > 500 and opened.sum() > 0.05 * near.size


@pytest.mark.parametrize("width", [0.4, 1.0, 2.5])
def test_strokes_are_antialiased_and_area_preserving(width: float) -> None:
    pts = np.array([[-5.0, 10.3], [45.0, 14.7]])
    sl, alpha = stroke(pts, np.full(2, width), 40, 30)
    cols = np.zeros((30, 40), np.float32)
    cols[sl] = alpha
    # each column's coverage integrates to about the stroke width (times the slope factor)
    slope = math.hypot(50.0, 4.4) / 50.0
    np.testing.assert_allclose(cols.sum(axis=0), width * slope, rtol=0.12)
    assert ((alpha > 0.02) & (alpha < 0.98)).any()  # partial coverage on edges
    assert alpha.max() <= min(width, 1.0) + 1e-6


@pytest.mark.parametrize("size", [(64, 64), (300, 200), (200, 301), (1000, 90)])
def test_other_sizes(size: tuple[int, int]) -> None:
    w, h = size
    sc = build_demo_scene(w, h)
    assert sc.image.shape == (h, w, 3) and sc.disparity.shape == (h, w)
    assert np.isfinite(sc.image).all() and sc.image.min() >= 0
    assert sc.disparity.min() >= 0 and sc.disparity.max() <= 1
    assert (sc.disparity > 0.8).any() and (sc.disparity < 0.25).any()
    assert sc.k_px > 0


def test_too_small_rejected() -> None:
    with pytest.raises(InputError):
        build_demo_scene(63, 64)


@pytest.mark.parametrize("n", [3, 5])
def test_contact_sheet_grid(scene: DemoScene, n: int) -> None:
    images = [scene.image * (i + 1) / n for i in range(n)]
    cols, tw = 4, 128
    sheet = contact_sheet(images, [f"img {i}" for i in range(n)], columns=cols, tile_width=tw)
    c = min(cols, n)
    rows = math.ceil(n / c)
    th = round(tw * 512 / 768)
    assert sheet.dtype == np.uint8
    assert sheet.shape == (rows * (th + SHEET_LABEL_H) + (rows + 1) * SHEET_GAP, c * tw + (c + 1) * SHEET_GAP, 3)
    # first tile is the sRGB-encoded image, labels carry light text
    tile = sheet[SHEET_GAP:SHEET_GAP + th, SHEET_GAP:SHEET_GAP + tw]
    assert tile.std() > 10
    label = sheet[SHEET_GAP + th:SHEET_GAP + th + SHEET_LABEL_H, SHEET_GAP:SHEET_GAP + tw]
    assert label.max() > 150


def test_contact_sheet_mixed_sizes_and_errors(scene: DemoScene) -> None:
    imgs = [scene.image, np.full((50, 100, 3), 0.5, np.float32), np.full((100, 50, 3), np.nan, np.float32)]
    sheet = contact_sheet(imgs, ["a", "b", "c"], columns=2, tile_width=64)
    assert sheet.shape == (2 * (128 + SHEET_LABEL_H) + 3 * SHEET_GAP, 2 * 64 + 3 * SHEET_GAP, 3)
    with pytest.raises(InputError):
        contact_sheet([scene.image], ["a", "b"])
    with pytest.raises(InputError):
        contact_sheet([], [])
    with pytest.raises(InputError):
        contact_sheet([scene.disparity], ["d"])
