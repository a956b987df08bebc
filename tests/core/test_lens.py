"""Thin-lens mapping, depth normalisation and their round trips."""

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

import bokehray as br


def test_textbook_example():
    # 50 mm f/1.4 at 2 m, 36 mm sensor, 1000 px wide, d = 1 m / z
    blur = br.ThinLens(50, 1.4, 2.0).blur_params(br.DepthNormalization(1.0), 1000)
    assert blur.k_px == pytest.approx(25.4375, rel=1e-4)
    assert blur.focus_disparity == pytest.approx(0.5)
    # CoC at infinity: K * |0 - 0.5|
    assert br.ThinLens(50, 1.4, 2.0).coc_radius_px(np.inf, 1000) == pytest.approx(12.72, rel=1e-3)


def test_matches_direct_thin_lens_coc():
    lens = br.ThinLens(85, 1.8, 3.0, 23.5)
    norm = br.DepthNormalization(1.5, 40.0)
    blur = lens.blur_params(norm, 6000)
    z = np.array([1.5, 2.0, 3.0, 7.0, 40.0])
    d = norm.disparity(z)
    np.testing.assert_allclose(blur.coc_radius(d), lens.coc_radius_px(z, 6000), rtol=1e-4)


@given(
    f=st.floats(10, 300), n=st.floats(0.95, 22), zf=st.floats(0.5, 50), zn=st.floats(0.35, 0.5),
    far=st.one_of(st.just(math.inf), st.floats(60, 1000)), width=st.integers(64, 8000),
)
def test_lens_and_blur_round_trip(f, n, zf, zn, far, width):
    if zf * 1e3 <= f * 1.01:
        return
    lens = br.ThinLens(f, n, zf)
    norm = br.DepthNormalization(zn, far)
    blur = lens.blur_params(norm, width)
    back = br.ThinLens.from_blur_params(blur, norm, width, focal_length_mm=f)
    assert back.f_number == pytest.approx(n, rel=1e-6)
    assert back.focus_distance_m == pytest.approx(zf, rel=1e-6)


@given(zn=st.floats(0.1, 10), ratio=st.floats(1.01, 100))
def test_depth_normalisation_round_trip(zn, ratio):
    norm = br.DepthNormalization(zn, zn * ratio)
    z = np.geomspace(zn, zn * ratio, 17)
    d = norm.disparity(z)
    assert d[0] == pytest.approx(1.0) and d[-1] == pytest.approx(0.0, abs=1e-6)
    np.testing.assert_allclose(norm.depth(d), z, rtol=1e-5)


def test_disparity_from_depth_min_max_and_errors():
    z = np.array([[1.0, 2.0], [4.0, 8.0]])
    d, norm = br.disparity_from_depth(z)
    assert norm.z_near_m == 1.0 and norm.z_far_m == 8.0
    assert d.max() == 1.0 and d.min() == 0.0
    d, norm = br.disparity_from_depth(np.array([[0.0, 1.0]]))  # no measurement (0): infinitely far
    assert d.tolist() == [[0.0, 1.0]] and math.isinf(norm.z_far_m)
    with pytest.raises(br.InputError, match="no pixel has a depth"):
        br.disparity_from_depth(np.array([[0.0, -1.0]]))
    with pytest.raises(br.InputError, match="NaN"):
        br.disparity_from_depth(np.array([[np.nan, 1.0]]))
    with pytest.raises(br.InputError, match="focal length"):
        br.ThinLens(50, 2, 0.04)


def test_dev_set_convention():
    """The path-traced dev set: K = K_abs * (1/z_near - 1/z_far), K_abs = R * f_px."""
    norm = br.DepthNormalization(1.149999880045665, 9.95578922773085)
    assert norm.disparity(2.8) == pytest.approx(0.3337559460926761, rel=1e-5)
    k_abs = 10.401481085313574
    assert k_abs * norm.inv_span == pytest.approx(8.0, rel=1e-6)
