"""``bokehray_kernels.split.split_kernel`` (through ``bokehray.matting``'s split of an edge estimate) against its
float64 oracle (``reference.split_ref``): random estimates over every flag, contrast, side and rule."""

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from reference import split_ref

from bokehray.edge_estimate import EdgeBand, EdgeEstimate, MattingRule
from bokehray.matting import _split_estimate


def _estimate(seed: int, n: int, ramp: int, scale: float):
    rng = np.random.default_rng(seed)
    h, w, y0, x0 = 9, 11, 3, 2
    photo = rng.uniform(0, 2 * scale, (h + y0 + 2, w + x0 + 1, 3)).astype(np.float32)
    image = (photo[y0:y0 + h, x0:x0 + w] / np.float32(scale)).astype(np.float32)
    flat = rng.choice(h * w, size=min(n, h * w), replace=False)
    by, bx = (v.astype(np.int32) for v in np.divmod(np.sort(flat), w))
    m = by.size
    fg, bg = rng.uniform(0, 1, (m, 3)).astype(np.float32), rng.uniform(0, 1, (m, 3)).astype(np.float32)
    same = rng.random(m) < 0.15  # no contrast: left alone
    bg[same] = fg[same] * np.float32(1.01)
    var_f = (rng.uniform(0, 0.05, (m, 3)) * (rng.random((m, 1)) < 0.8)).astype(np.float32)
    var_b = rng.uniform(0, 0.05, (m, 3)).astype(np.float32)
    near = rng.normal(0, 10, m).astype(np.float32)
    far = np.where(rng.random(m) < 0.85, near - rng.uniform(0.5, 20, m), near + 1).astype(np.float32)
    band = EdgeBand((photo.shape[0], photo.shape[1]), (y0, y0 + h, x0, x0 + w), by, bx, ramp, scale, image,
                    np.zeros((h, w), np.float32), np.zeros((h, w), bool), 2)
    est = EdgeEstimate(band, by, bx, rng.uniform(-0.05, 1.05, m).clip(0, 1).astype(np.float32), fg, bg, var_f, var_b,
                       near, far, rng.integers(0, 4, m).astype(np.int32))
    return photo, est


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**16), n=st.integers(0, 99), ramp=st.sampled_from([0, 3]),
       scale=st.sampled_from([1.0, 7.5]), model_sd=st.sampled_from([None, 0.1]))
def test_split_kernel_matches_the_oracle(seed, n, ramp, scale, model_sd):
    photo, est = _estimate(seed, n, ramp, scale)
    rule = MattingRule(model_sd=model_sd)
    got = _split_estimate(photo, est, rule)
    y0, x0 = est.band.box[0], est.band.box[2]
    w = est.band.shape[1]
    want_index, want, kept = [], [], []
    for k in range(est.by.size):
        y, x = int(est.by[k]), int(est.bx[k])
        split, a, f, b = split_ref.split_pixel(
            est.alpha[k], est.band.image[y, x], est.fg[k], est.bg[k], est.fg_var[k], est.bg_var[k], est.near[k],
            est.far[k], int(est.flags[k]), photo[y0 + y, x0 + x], scale=scale, min_alpha=rule.min_alpha,
            max_alpha=rule.max_alpha, min_contrast=rule.min_contrast, model_sd=model_sd, sharp=ramp == 0)
        if split:
            want_index.append((y0 + y) * w + x0 + x)
            want.append((a, f, b))
            kept.append(k)
    np.testing.assert_array_equal(got.index, np.array(want_index, np.int64))
    if want:
        np.testing.assert_allclose(got.alpha, [v[0] for v in want], atol=2e-6)
        np.testing.assert_allclose(got.foreground, [v[1] for v in want], rtol=1e-5, atol=1e-5 * scale)
        np.testing.assert_allclose(got.background, [v[2] for v in want], rtol=1e-5, atol=1e-5 * scale)
        np.testing.assert_array_equal(got.near_coc, est.near[kept])
        np.testing.assert_array_equal(got.far_coc, est.far[kept])


@pytest.mark.parametrize("threads", [1, 3])
def test_split_kernel_keeps_the_photo(threads, monkeypatch):
    """Every split pixel composites back to the photo's colour: alpha F + (1 - alpha) B = I."""
    import bokehray.edge_estimate as edge_estimate

    monkeypatch.setattr(edge_estimate, "PIXELS_PER_THREAD", 8)  # several parts
    photo, est = _estimate(7, 99, 0, 1.0)
    got = _split_estimate(photo, est, MattingRule(), threads=threads)
    assert len(got) >= 5
    y, x = np.divmod(got.index, est.band.shape[1])
    a = got.alpha[:, None]
    np.testing.assert_allclose(a * got.foreground + (1 - a) * got.background, photo[y, x], atol=2e-6)
    assert ((got.alpha >= 0.02) & (got.alpha <= 0.9)).all()


def test_uniform_sides_take_the_projection_and_a_sure_model_its_alpha():
    """Where F's and B's samples do not vary (a wire over a flat sky) the colour's place on the F-B line is the
    alpha; where the model is very sure (model_sd near 0) its alpha is."""
    photo, est = _estimate(11, 99, 3, 1.0)
    flat = dataclasses.replace(est, fg_var=np.zeros_like(est.fg_var), bg_var=np.zeros_like(est.bg_var))
    got = _split_estimate(photo, flat, MattingRule())
    k = np.searchsorted((est.by + est.band.box[0]) * est.band.shape[1] + est.bx + est.band.box[2], got.index)
    c, f, b = est.band.image[est.by[k], est.bx[k]], est.fg[k], est.bg[k]
    proj = ((c - b) * (f - b)).sum(1) / ((f - b) ** 2).sum(1)
    np.testing.assert_allclose(got.alpha, np.clip(proj, 0.02, 0.9), atol=1e-5)
    sure = _split_estimate(photo, est, MattingRule(model_sd=1e-6))
    k = np.searchsorted((est.by + est.band.box[0]) * est.band.shape[1] + est.bx + est.band.box[2], sure.index)
    np.testing.assert_allclose(sure.alpha, np.clip(est.alpha[k], 0.02, 0.9), atol=1e-4)
