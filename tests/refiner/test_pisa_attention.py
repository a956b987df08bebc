"""PISA attention (torch): windowed == dense, energy conservation, empty columns, dtypes, no NaN."""

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from bokehray_refiner.attention import pisa_attention, pisa_attention_dense, pisa_weights  # noqa: E402
from bokehray_refiner.pisa import pisa_masks  # noqa: E402
from hypothesis import given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402
from reference import pisa_ref as ref  # noqa: E402

H, W = 7, 9


def _masks(k_lat=3.0, d_f=0.2):
    d = np.full((H, W), 0.2, np.float32)
    d[2:5, 3:7] = 0.8
    m = pisa_masks(d, d_f, k_lat)
    coc, vis = m.numpy()
    return coc, vis, m.window


def _qkv(b=2, heads=3, d=4, dv=5, dtype=torch.float64, seed=0, scale=1.0):
    g = torch.Generator().manual_seed(seed)
    mk = lambda n: (scale * torch.randn(b, heads, H, W, n, generator=g, dtype=torch.float64)).to(dtype)  # noqa: E731
    return mk(d).requires_grad_(), mk(d).requires_grad_(), mk(dv).requires_grad_()


def _dense(win, window, b):
    return torch.tensor(ref.window_to_dense(win, window))[None].expand(b, -1, -1)


def test_windowed_equals_dense_values_and_gradients():
    coc, vis, w = _masks()
    q, k, v = _qkv()
    ct, vt = torch.tensor(coc)[None].expand(2, -1, -1, -1), torch.tensor(vis)[None].expand(2, -1, -1, -1)
    out = pisa_attention(q, k, v, ct, vt, w)
    dense = pisa_attention_dense(q.flatten(2, 3), k.flatten(2, 3), v.flatten(2, 3),
                                 _dense(coc, w, 2).double(), _dense(vis, w, 2).double())
    torch.testing.assert_close(out.flatten(2, 3), dense, rtol=1e-10, atol=1e-12)
    g = torch.randn_like(out)
    ga = torch.autograd.grad((out * g).sum(), [q, k, v])
    gd = torch.autograd.grad((dense.reshape(out.shape) * g).sum(), [q, k, v])
    for a, b in zip(ga, gd):
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-11)


def test_gradcheck():
    g = torch.Generator().manual_seed(3)
    q, k, v = (torch.randn(1, 1, 3, 4, 2, generator=g, dtype=torch.float64, requires_grad=True) for _ in range(3))
    coc = torch.rand(3, 4, 9, generator=g, dtype=torch.float64)
    coc[1, 2] = 0.0  # an empty column too
    vis = torch.rand(3, 4, 9, generator=g, dtype=torch.float64)
    f = lambda q, k, v: pisa_attention(q, k, v, coc, vis, 1)  # noqa: E731
    assert torch.autograd.gradcheck(f, (q, k, v), eps=1e-6, atol=1e-6)


def test_energy_conservation_every_key_sums_to_one():
    coc, _, w = _masks()
    q, k, _ = _qkv()
    a = pisa_weights(q, k, torch.tensor(coc), w)
    torch.testing.assert_close(a.sum(-1), torch.ones(a.shape[:-1], dtype=a.dtype))
    # ... and so, without occlusion, the output's total equals the values' total (eq. 2).
    v = torch.randn(2, 3, H, W, 5, dtype=torch.float64)
    out = pisa_attention(q, k, v, torch.tensor(coc), None, w)
    torch.testing.assert_close(out.sum(dim=(2, 3)), v.sum(dim=(2, 3)))


def test_in_focus_is_the_identity():
    d = np.full((H, W), 0.5, np.float32)
    m = pisa_masks(d, 0.5, 8.0)
    coc, vis = m.numpy()
    q, k, v = _qkv(scale=0.1)
    out = pisa_attention(q, k, v, torch.tensor(coc), torch.tensor(vis), m.window)
    # At k_max a neighbour's mask is sigmoid(-13.8) = 1e-6; the logits can raise its share by exp(ds).
    torch.testing.assert_close(out, v.detach(), rtol=0, atol=2e-5)


def test_fully_masked_key_contributes_zero_not_nan():
    coc, vis, w = _masks()
    coc = coc.copy()
    coc[3, 4] = 0.0  # one key with an empty column
    q, k, v = _qkv()
    a = pisa_weights(q, k, torch.tensor(coc), w)
    assert torch.isfinite(a).all() and (a[:, :, 3, 4] == 0).all()
    out = pisa_attention(q, k, v, torch.tensor(coc), torch.tensor(vis), w)
    out.sum().backward()
    assert torch.isfinite(q.grad).all() and torch.isfinite(k.grad).all()
    zero = pisa_attention(q, k, v, torch.zeros_like(torch.tensor(coc)), None, w)
    assert (zero == 0).all()


@pytest.mark.parametrize("dtype", [torch.float32, torch.float16, torch.bfloat16])
def test_half_precision_matches_float64(dtype):
    coc, vis, w = _masks()
    q, k, v = _qkv(dtype=torch.float64, scale=4.0)  # logits up to ~+-100: exp overflows fp16 unshifted
    ref_out = pisa_attention(q, k, v, torch.tensor(coc).double(), torch.tensor(vis).double(), w)
    out = pisa_attention(q.to(dtype), k.to(dtype), v.to(dtype), torch.tensor(coc), torch.tensor(vis), w)
    assert out.dtype == dtype and torch.isfinite(out).all()
    # Error budget: rounding q, k to the dtype (relative 2^-8 for bf16) on logits of ~100.
    tol = {torch.float32: 1e-4, torch.float16: 0.1, torch.bfloat16: 0.6}[dtype]
    assert (out.double() - ref_out).abs().max() < tol * max(1.0, ref_out.abs().max().item())


def test_bad_shapes_are_refused():
    coc, vis, w = _masks()
    q, k, v = _qkv()
    with pytest.raises(ValueError, match="mask"):
        pisa_attention(q, k, v, torch.tensor(coc), None, w + 1)
    with pytest.raises(ValueError, match="q and k"):
        pisa_attention(q, k[:, :1], v, torch.tensor(coc), None, w)
    with pytest.raises(ValueError, match="visibility"):
        pisa_attention(q, k, v, torch.tensor(coc), torch.tensor(vis)[:-1], w)


@settings(max_examples=30, deadline=None)
@given(
    logit_scale=st.sampled_from([0.0, 1.0, 30.0, 1e3, 1e4]),
    coc_value=st.sampled_from([0.0, 1e-38, 1e-10, 0.5, 1.0]),
    dtype=st.sampled_from([torch.float32, torch.float16, torch.bfloat16]),
    seed=st.integers(0, 1000),
)
def test_random_inputs_never_give_nan_or_inf(logit_scale, coc_value, dtype, seed):
    coc, vis, w = _masks()
    rng = np.random.default_rng(seed)
    coc = np.where(rng.uniform(size=coc.shape) < 0.5, coc, coc_value).astype(np.float32)
    q, k, v = _qkv(dtype=torch.float32, seed=seed)
    q, k = (q.detach() * logit_scale).to(dtype), k.detach().to(dtype)
    out = pisa_attention(q, k, v.detach().to(dtype), torch.tensor(coc), torch.tensor(vis), w)
    assert torch.isfinite(out).all()
