"""PISA attention (BokehDiff eq. 2, 4, 8) over a window, and its dense reference.

PISA replaces the key-axis softmax of self-attention by a *query-axis* one
(eq. 2): every key ``k`` hands out a total weight of 1 over the queries, like a
light source spreading its energy over its circle of confusion. The CoC mask
``C`` restricts that spread (eq. 4) and the visibility ``E[M_vis]`` removes what
occluders block (eq. 8)::

    A[q, k] = C[q, k] exp(s_qk) / sum_q' C[q', k] exp(s_q'k),   s = Q K^T / sqrt(d)
    out[q]  = sum_k A[q, k] * Vis[q, k] * V[k]

``C`` is 0 outside the largest CoC, so only queries within the window radius
``w`` of a key matter: :func:`pisa_attention` works on the key-centric window of
``bokehray.pisa`` (memory ``O(N (2w+1)^2)`` per head, not ``O(N^2)``).
Logits and weights are computed in float32 for half-precision inputs (float64 stays float64); a key whose
mask is empty contributes 0, never NaN.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

__all__ = ["pisa_attention", "pisa_attention_dense", "pisa_weights", "window_offsets"]


def window_offsets(window: int) -> list[tuple[int, int]]:
    """(dy, dx) of each window entry, row-major, as in ``bokehray.pisa.window_offsets``."""
    r = range(-window, window + 1)
    return [(dy, dx) for dy in r for dx in r]


def _check(q: torch.Tensor, k: torch.Tensor, coc: torch.Tensor, window: int) -> None:
    if q.ndim != 5 or k.shape != q.shape:
        raise ValueError(f"q and k: expected equal shapes (B, heads, H, W, d), got {tuple(q.shape)}, {tuple(k.shape)}")
    n_off = (2 * window + 1) ** 2
    b, _, h, w, _ = q.shape
    if coc.shape[-3:] != (h, w, n_off) or coc.ndim not in (3, 4) or (coc.ndim == 4 and coc.shape[0] not in (1, b)):
        raise ValueError(f"mask: expected (B, {h}, {w}, {n_off}) for window {window}, got {tuple(coc.shape)}")


def _acc_dtype(x: torch.Tensor) -> torch.dtype:
    """float32 for half types, float64 stays float64."""
    return torch.promote_types(x.dtype, torch.float32)


def _batched(mask: torch.Tensor) -> torch.Tensor:
    """(B or 1, H, W, n) -> (B or 1, 1, H, W, n): broadcast over heads."""
    return (mask if mask.ndim == 4 else mask[None])[:, None]


def pisa_weights(
    q: torch.Tensor, k: torch.Tensor, coc: torch.Tensor, window: int, scale: float | None = None
) -> torch.Tensor:
    """The energy-conserving, CoC-masked weights ``A^(QC)`` in the key-centric window.

    Args:
        q, k: ``(B, heads, H, W, d)``.
        coc: ``(B, H, W, (2w+1)^2)`` (or without B): ``C`` for key ``(y, x)`` and query ``(y, x) + offset``.
        window: the window radius ``w``.
        scale: logit scale, default ``1 / sqrt(d)``.

    Returns:
        ``(B, heads, H, W, (2w+1)^2)`` float32; each key's weights sum to 1 over its
        queries, or are all 0 when its mask is empty.
    """
    _check(q, k, coc, window)
    b, nh, h, w, d = q.shape
    scale = 1.0 / math.sqrt(d) if scale is None else scale
    acc = _acc_dtype(q)
    qp = F.pad(q.to(acc), (0, 0, window, window, window, window))
    kf = k.to(acc)
    logits = torch.stack(
        [(qp[:, :, window + dy: window + dy + h, window + dx: window + dx + w] * kf).sum(-1)
         for dy, dx in window_offsets(window)],
        dim=-1,
    ) * scale
    with torch.no_grad():
        log_c = torch.log(_batched(coc).to(acc))  # 0 -> -inf: masked out
    masked = logits + log_c
    peak = masked.amax(dim=-1, keepdim=True).detach()
    peak = torch.where(torch.isfinite(peak), peak, torch.zeros_like(peak))  # empty column: any finite shift
    e = torch.exp(masked - peak)
    total = e.sum(dim=-1, keepdim=True)
    return e / torch.where(total > 0, total, torch.ones_like(total))  # empty column: 0 / 1, and finite gradients


def _aggregate(weights: torch.Tensor, v: torch.Tensor, window: int) -> torch.Tensor:
    """``out[q] = sum_k W[k, q - k] V[k]``: each key scatters its weighted value over its window."""
    b, nh, h, w, _ = weights.shape
    vf = v.to(weights.dtype)
    out = vf.new_zeros((b, nh, h + 2 * window, w + 2 * window, v.shape[-1]))
    for o, (dy, dx) in enumerate(window_offsets(window)):
        out[:, :, window + dy: window + dy + h, window + dx: window + dx + w] += weights[..., o, None] * vf
    return out[:, :, window: window + h, window: window + w]


def pisa_attention(
    q: torch.Tensor,
    k: torch.Tensor,
    v: torch.Tensor,
    coc: torch.Tensor,
    visibility: torch.Tensor | None,
    window: int,
    scale: float | None = None,
) -> torch.Tensor:
    """PISA self-attention over the key-centric window (eq. 8).

    Args:
        q, k: ``(B, heads, H, W, d)``; v: ``(B, heads, H, W, dv)``.
        coc, visibility: ``(B, H, W, (2w+1)^2)`` masks from ``bokehray.pisa.pisa_masks``
            (visibility None: no occlusion term).
        window: the window radius ``w`` of the masks.

    Returns:
        ``(B, heads, H, W, dv)`` in the dtype of ``v``.
    """
    if v.shape[:4] != q.shape[:4]:
        raise ValueError(f"v: expected (B, heads, H, W, dv) matching q {tuple(q.shape[:4])}, got {tuple(v.shape)}")
    a = pisa_weights(q, k, coc, window, scale)
    if visibility is not None:
        if visibility.shape != coc.shape:
            raise ValueError(f"visibility: expected the shape of coc {tuple(coc.shape)}, got {tuple(visibility.shape)}")
        a = a * _batched(visibility).to(a.dtype)
    return _aggregate(a, v, window).to(v.dtype)


def pisa_attention_dense(
    q: torch.Tensor,
    k: torch.Tensor,
    v: torch.Tensor,
    coc: torch.Tensor,
    visibility: torch.Tensor | None = None,
    scale: float | None = None,
) -> torch.Tensor:
    """Dense reference: ``q, k, v`` are ``(B, heads, N, d)``, masks ``(B, N, N)`` indexed ``[query, key]``.

    Memory ``O(N^2)``; for tests and small sizes only.
    """
    d = q.shape[-1]
    scale = 1.0 / math.sqrt(d) if scale is None else scale
    acc = _acc_dtype(q)
    logits = (q.to(acc) @ k.to(acc).transpose(-1, -2)) * scale  # [q, k]
    masked = logits + torch.log(coc.to(acc))[:, None]
    peak = masked.amax(dim=-2, keepdim=True).detach()
    peak = torch.where(torch.isfinite(peak), peak, torch.zeros_like(peak))
    e = torch.exp(masked - peak)
    total = e.sum(dim=-2, keepdim=True)  # over the query axis
    a = e / torch.where(total > 0, total, torch.ones_like(total))
    if visibility is not None:
        a = a * visibility.to(acc)[:, None]
    return (a @ v.to(acc)).to(v.dtype)
