"""``bokehray_kernels.thin`` (through ``bokehray.thin_depth``'s launchers) against their float64 oracles
(``reference.thin_ref``): random maps, photos, windows and blocks, odd and even sides."""

from types import SimpleNamespace

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from reference import thin_ref

from bokehray.thin_depth import _BlockArgs, _half_level, _ramps, _window_fit


def _map(seed: int, h: int, w: int):
    rng = np.random.default_rng(seed)
    s = np.cumsum(rng.normal(0, 0.4, (h, w)), 1).astype(np.float32)  # steps around grad_min, both signs
    s[rng.random((h, w)) < 0.1] += np.float32(5)
    photo = rng.uniform(0, 3, (h, w, 3)).astype(np.float32)
    return rng, photo, s


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**16), h=st.integers(3, 21), w=st.integers(3, 21))
def test_the_level_kernel_matches_the_oracle(seed, h, w):
    _, photo, s = _map(seed, h, w)
    for g, x in zip(_half_level(photo, s), thin_ref.level_ref(photo, s), strict=True):
        np.testing.assert_allclose(g, x, rtol=1e-6, atol=1e-5)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**16), h=st.integers(3, 21), w=st.integers(3, 21), grad_min=st.sampled_from([0.2, 0.6]),
       flip=st.booleans())
def test_the_ramp_kernel_matches_the_oracle(seed, h, w, grad_min, flip):
    _, _, s = _map(seed, h, w)
    s = np.ascontiguousarray(s.T if flip else s)  # ramps down the columns too
    assert _ramps(s, grad_min) == thin_ref.ramps_ref(s, grad_min)


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**16), h=st.integers(3, 16), w=st.integers(3, 16), k=st.integers(1, 4))
def test_the_window_fit_kernel_matches_the_oracle(seed, h, w, k):
    rng = np.random.default_rng(seed)
    gb = rng.uniform(-0.3, 0.3, (h, w, 3))
    d = gb @ rng.normal(0, 1, 3) + rng.normal(0, 0.05, (h, w)) + 0.01 * np.arange(w)
    ys, xs = np.nonzero(rng.random((h, w)) < 0.5)
    a, b, res, var, plane = _window_fit(gb, d, (ys, xs), k, 1e-6)
    for i, (wa, wb, wres, wvar, wplane) in enumerate(thin_ref.window_fit_ref(gb, d, ys, xs, k, 1e-6)):
        np.testing.assert_allclose(a[i], wa, rtol=1e-6, atol=1e-8)
        np.testing.assert_allclose([b[i], res[i], var[i], plane[i]], [wb, wres, wvar, wplane], rtol=1e-6, atol=1e-10)


def _blocks(seed: int, h: int, w: int, f: int):
    rng, photo, s = _map(seed, h, w)
    gh, gw = -(-h // f), -(-w // f)
    ok = rng.random((gh, gw)) < 0.6
    fit = SimpleNamespace(f=f, a=rng.normal(0, 1, (gh, gw, 3)).astype(np.float32),
                          b=rng.normal(0, 1, (gh, gw)).astype(np.float32))
    grids = SimpleNamespace(photo=photo, s=s, centre=float(s.mean()), scale=float(s.max() - s.min()))
    iy, ix = np.nonzero(ok)
    return rng, grids, fit, iy, ix, _BlockArgs(grids, fit, iy, ix)


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**16), h=st.integers(3, 30), w=st.integers(3, 30), f=st.sampled_from([1, 2, 4, 8]))
def test_the_extremes_kernel_matches_the_oracle(seed, h, w, f):
    _, grids, fit, iy, ix, blocks = _blocks(seed, h, w, f)
    got = blocks.extremes()
    want = thin_ref.extremes_ref(grids.photo, iy, ix, f, fit.a[iy, ix], fit.b[iy, ix])
    for g, x in zip(got, want):
        np.testing.assert_allclose(g, x, rtol=1e-5, atol=1e-5)


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**16), h=st.integers(3, 30), w=st.integers(3, 30), f=st.sampled_from([1, 2, 4, 8]),
       clamp=st.booleans())
def test_the_harden_kernel_matches_the_oracle(seed, h, w, f, clamp):
    rng, grids, fit, iy, ix, blocks = _blocks(seed, h, w, f)
    shape = fit.b.shape
    far = rng.uniform(-0.5, 0, shape).astype(np.float32)
    near = (far + rng.uniform(0, 1, shape)).astype(np.float32)
    top = (far + rng.uniform(0, 1, shape)).astype(np.float32)
    pick = rng.random(iy.size) < 0.7
    lo, hi = (float(np.percentile(grids.s, 20)), float(np.percentile(grids.s, 80))) if clamp else (-np.inf, np.inf)
    keep = 0.1
    done = blocks.harden(pick, far, near, top, SimpleNamespace(keep=keep), (lo, hi))
    p = np.flatnonzero(pick)
    want = thin_ref.harden_ref(grids.photo, grids.s, iy[p], ix[p], f, fit.a[iy[p], ix[p]], fit.b[iy[p], ix[p]],
                               far[iy[p], ix[p]], near[iy[p], ix[p]], top[iy[p], ix[p]], grids.centre, grids.scale,
                               keep, lo, hi)
    got = grids.s if done is None else done[0]
    tol = 1e-5 * grids.scale + 1e-5
    # a pixel whose far or near value is its own moves by a rounding only (left as it is by the kernel)
    assert (np.abs(got - want) <= tol).mean() >= 0.99
    assert done is None or done[1] == np.count_nonzero(done[0] != grids.s)
