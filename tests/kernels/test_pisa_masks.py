"""PISA masks (Warp) against the float64 dense NumPy oracle, their limits, and their invariants."""

import math

import numpy as np
import pytest
from bokehray_refiner.pisa import K_MAX, PisaMaskOptions, edge_slope, pisa_masks, window_offsets, window_radius
from conftest import DEVICES
from hypothesis import given, settings
from hypothesis import strategies as st
from reference import pisa_ref as ref

from bokehray.errors import InputError


def _scene(h=9, w=10, seed=0):
    rng = np.random.default_rng(seed)
    d = np.full((h, w), 0.2, np.float32)
    d[3:7, 2:6] = 0.9
    return d + rng.uniform(0, 0.05, d.shape).astype(np.float32)


def _in_window(h, w, window):
    return ref.window_to_dense(np.ones((h, w, (2 * window + 1) ** 2), np.float32), window) > 0


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("model", ["thin_lens", "paper"])
def test_masks_match_dense_reference(device, model):
    d = _scene()
    opts = PisaMaskOptions(collinear=model)
    m = pisa_masks(d, 0.2, 4.0, opts, device=device)
    coc, vis = m.numpy()
    inside = _in_window(*d.shape, m.window)
    c_dense = ref.window_to_dense(coc, m.window)
    np.testing.assert_allclose(c_dense[inside], ref.coc_dense(d, 0.2, 4.0, opts.slope)[inside], atol=2e-6)
    v_ref = ref.visibility_dense(d, 0.2, 4.0, model=model)
    v_dense = ref.window_to_dense(vis, m.window)
    # Occlusion tests are thresholds: float32 and float64 may round a collinear point lying exactly on a
    # texel boundary to different texels, flipping one source sample (1/5) of a pair; rare, never more.
    err = np.abs(v_dense[inside] - v_ref[inside])
    assert err.max() <= 0.2 + 1e-6 and (err > 1e-6).mean() < 0.01
    assert 0.2 < v_dense[inside].mean() < 0.95  # the scene does occlude, and not everything


def test_window_holds_the_whole_coc_mask():
    d = _scene()
    opts = PisaMaskOptions(hardness=20.0)  # a soft edge: the window must grow with it
    m = pisa_masks(d, 0.2, 3.0, opts)
    dense = ref.coc_dense(d, 0.2, 3.0, opts.slope)
    outside = ~_in_window(*d.shape, m.window)
    assert dense[outside].max(initial=0.0) < 5e-5
    assert m.window == window_radius(3.0 * float(np.abs(d - 0.2).max()), opts)


def test_soft_edge_limits():
    assert edge_slope(K_MAX) == pytest.approx(math.log1p(1e6))
    assert edge_slope(1e12) == edge_slope(K_MAX)  # capped at k_max
    d = np.zeros((1, 41), np.float32)
    d[0, 20] = 1.0
    coc, _ = pisa_masks(d, 0.0, 5.0, window=20).numpy()  # key at x=20 has CoC radius 5
    row = coc[0, 20].reshape(41, 41)[20]  # queries along the row, distance |dx|
    assert row[20 + 3] > 0.999999 and row[20 + 4] > 0.99999  # inside: ~1
    assert row[20 + 5] == pytest.approx(0.5, abs=1e-6)  # on the circle: 1/2
    assert row[20 + 6] < 1e-5 and row[20 + 7] < 1e-11  # outside: ~0, sharpening with k
    soft, _ = pisa_masks(d, 0.0, 5.0, PisaMaskOptions(hardness=1.0), window=20).numpy()
    assert 0.3 < soft[0, 20].reshape(41, 41)[20, 26] < 0.5  # k = 1: a soft edge


def test_in_focus_key_keeps_to_itself():
    d = np.full((8, 8), 0.5, np.float32)
    coc, vis = pisa_masks(d, 0.5, 10.0).numpy()
    w = (int(math.isqrt(coc.shape[2])) - 1) // 2
    centre = (2 * w + 1) * w + w
    assert np.all(coc[..., centre] == 0.5)  # r = 0, distance 0: on the edge
    others = np.delete(coc, centre, axis=2)
    assert others.max() < 1e-5
    assert np.all(vis[..., centre] == 1.0)  # a flat scene occludes nothing


def test_foreground_blocks_background_behind_it():
    # Background key just beside a near block: queries looking through the block's
    # position see the key blocked; queries on the far side see it.
    d = np.full((1, 31), 0.1, np.float32)
    d[0, 14:17] = 1.0
    _, vis = pisa_masks(d, 1.0, 12.0, PisaMaskOptions(n_sources=1), window=12).numpy()
    v = vis[0, 12].reshape(25, 25)[12]  # background key at x=12, queries along the row
    assert v[12 - 6] == 1.0  # query to the left, away from the block: visible
    assert v[12 + 6] == 0.0  # query to the right, behind the block: blocked


@pytest.mark.parametrize("model", ["thin_lens", "paper"])
def test_singular_limits_stay_finite(model):
    # d_s -> 1 and d~ -> 0 make eq. 7's factor singular; d_s = d_f makes the thin-lens one singular.
    for d_val, d_f in [(1.0, 0.0), (0.0, 1.0), (1.0, 1.0), (0.0, 0.0), (0.999999, 0.5)]:
        d = np.full((6, 7), d_val, np.float32)
        d[2:4, 2:5] = 1.0 - d_val
        coc, vis = pisa_masks(d, d_f, 3.0, PisaMaskOptions(collinear=model)).numpy()
        assert np.isfinite(coc).all() and np.isfinite(vis).all()
        assert vis.min() >= 0.0 and vis.max() <= 1.0 and coc.min() >= 0.0 and coc.max() <= 1.0


def test_paper_factor_limits_match_clamped_reference():
    q, ps = np.array([0.0, 0.0]), np.array([2.0, 1.0])
    eps = 1e-3
    p = ref.collinear(q, ps, 1.0, 0.0, 0.5, 4.0, "paper", eps)  # d_s = 1, d~ = 0
    assert np.allclose(p, q + (1 - eps) * (1 - eps) / (eps * eps) * (ps - q))
    assert np.allclose(ref.collinear(q, ps, 0.4, 0.4, 0.5, 4.0, "paper", eps), ps)  # d~ = d_s: the source
    assert np.allclose(ref.collinear(q, ps, 0.4, 1.0, 0.5, 4.0, "paper", eps), q)  # d~ = 1: the query pixel
    # Thin lens: d~ = d_s gives the source, d~ = d_f the query pixel.
    assert np.allclose(ref.collinear(q, ps, 0.2, 0.2, 0.6, 10.0, "thin_lens", eps), ps)
    assert np.allclose(ref.collinear(q, ps, 0.2, 0.6, 0.6, 10.0, "thin_lens", eps), q)
    # A query outside the source's CoC: the ray is clamped to the aperture's rim.
    p = ref.collinear(q, ps, 0.2, 0.2, 0.6, 4.0, "thin_lens", eps)
    assert np.linalg.norm(p - q) == pytest.approx(4.0 * 0.4)


def test_window_offsets_order():
    offs = window_offsets(1)
    assert offs.tolist() == [[-1, -1], [-1, 0], [-1, 1], [0, -1], [0, 0], [0, 1], [1, -1], [1, 0], [1, 1]]


@pytest.mark.parametrize("bad", [
    dict(disparity=np.full((4, 4), np.nan, np.float32)),
    dict(disparity=np.full((4, 4), 1.5, np.float32)),
    dict(disparity=np.zeros((4,), np.float32)),
    dict(focus_disparity=2.0),
    dict(k_lat=-1.0),
    dict(window=100),
])
def test_bad_input_is_refused(bad):
    args = dict(disparity=np.zeros((4, 4), np.float32), focus_disparity=0.5, k_lat=2.0) | bad
    with pytest.raises(InputError):
        pisa_masks(**args)


@pytest.mark.parametrize("bad", [dict(hardness=0.0), dict(n_sources=0), dict(collinear="pinhole"),
                                 dict(eps=0.7), dict(source_sigma=-1.0), dict(max_window=65)])
def test_bad_options_are_refused(bad):
    with pytest.raises(InputError):
        PisaMaskOptions(**bad)


@settings(max_examples=25, deadline=None)
@given(
    h=st.integers(1, 6), w=st.integers(1, 6),
    values=st.lists(st.sampled_from([0.0, 1.0, 0.5, 1e-7, 1 - 1e-7]), min_size=36, max_size=36),
    d_f=st.sampled_from([0.0, 1.0, 0.3]), k=st.sampled_from([0.0, 1e-6, 2.5, 1e5]),
    model=st.sampled_from(["thin_lens", "paper"]),
)
def test_masks_are_finite_and_bounded(h, w, values, d_f, k, model):
    d = np.array(values[: h * w], np.float32).reshape(h, w)
    m = pisa_masks(d, d_f, k, PisaMaskOptions(collinear=model, max_window=4))
    coc, vis = m.numpy()
    assert np.isfinite(coc).all() and np.isfinite(vis).all()
    assert 0.0 <= coc.min() and coc.max() <= 1.0 and 0.0 <= vis.min() and vis.max() <= 1.0


@pytest.mark.parametrize("n", [1, 2, 3, 4, 5, 8])
def test_jittered_sources_are_centred_on_the_key(n):
    offs = ref.source_offsets(n, 0.5)
    assert len(offs) == n
    np.testing.assert_allclose(offs.mean(axis=0), 0.0, atol=1e-12)
    assert (n % 2 == 0) or np.any(np.all(offs == 0.0, axis=1))  # odd n: one source on the key
    # The kernel uses the same sources: a scene symmetric under a half turn about the key gives a
    # visibility symmetric under the same half turn (a biased source set breaks this).
    d = np.zeros((9, 9), np.float32)
    d[4, 6] = d[4, 2] = 1.0
    d[2, 5] = d[6, 3] = 0.7
    _, vis = pisa_masks(d, 0.0, 6.0, PisaMaskOptions(n_sources=n), window=4).numpy()
    v = vis[4, 4].reshape(9, 9)
    np.testing.assert_allclose(v, v[::-1, ::-1], atol=1e-6)
