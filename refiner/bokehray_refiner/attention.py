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
``bokehray_refiner.pisa`` (memory ``O(N (2w+1)^2)`` per head, not ``O(N^2)``), one
window row at a time, in place when no gradient is needed. Logits and weights
are computed in float32 for half-precision inputs (float64 stays float64); a
key whose mask is empty contributes 0, never NaN.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from bokehray.errors import InputError

__all__ = ["pisa_attention", "pisa_attention_dense", "pisa_weights", "window_offsets"]


def _logits(q: torch.Tensor, k: torch.Tensor, window: int) -> torch.Tensor:
    """``s[b, h, y, x, o] = q[(y, x) + offset(o)] . k[(y, x)]`` (zero outside the image).

    One window row at a time: a strided view (no copy) holds the row's 2w+1 neighbours of
    every key, so temporaries stay at ``B heads N (2w+1) d`` values.
    """
    h = q.shape[2]
    qp = F.pad(q, (0, 0, window, window, window, window))
    rows = (qp[:, :, window + dy: window + dy + h].unfold(3, 2 * window + 1, 1) for dy in range(-window, window + 1))
    return torch.cat([torch.einsum("bzyxdo,bzyxd->bzyxo", row, k) for row in rows], dim=-1)


def window_offsets(window: int) -> list[tuple[int, int]]:
    """(dy, dx) of each window entry, row-major, as in ``bokehray_refiner.pisa.window_offsets``."""
    r = range(-window, window + 1)
    return [(dy, dx) for dy in r for dx in r]


def _check(q: torch.Tensor, k: torch.Tensor, coc: torch.Tensor, window: int) -> None:
    if q.ndim != 5 or k.shape != q.shape:
        raise InputError(f"q and k: expected equal shapes (B, heads, H, W, d), got {tuple(q.shape)}, {tuple(k.shape)}")
    n_off = (2 * window + 1) ** 2
    b, _, h, w, _ = q.shape
    if coc.shape[-3:] != (h, w, n_off) or coc.ndim not in (3, 4) or (coc.ndim == 4 and coc.shape[0] not in (1, b)):
        raise InputError(f"mask: expected (B, {h}, {w}, {n_off}) for window {window}, got {tuple(coc.shape)}")


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
    d = q.shape[-1]
    scale = 1.0 / math.sqrt(d) if scale is None else scale
    acc = _acc_dtype(q)
    with torch.no_grad():
        log_c = torch.log(_batched(coc).to(acc))  # 0 -> -inf: masked out
    logits = _logits(q.to(acc), k.to(acc), window)
    inplace = not (torch.is_grad_enabled() and (q.requires_grad or k.requires_grad))
    if inplace:  # inference: one window-sized buffer, updated in place
        masked = logits.mul_(scale).add_(log_c)
    else:
        masked = logits * scale + log_c
    peak = masked.amax(dim=-1, keepdim=True).detach()
    peak = torch.where(torch.isfinite(peak), peak, torch.zeros_like(peak))  # empty column: any finite shift
    e = masked.sub_(peak).exp_() if inplace else torch.exp(masked - peak)
    total = e.sum(dim=-1, keepdim=True)
    total = torch.where(total > 0, total, torch.ones_like(total))  # empty column: 0 / 1, and finite gradients
    return e.div_(total) if inplace else e / total


def _aggregate(weights: torch.Tensor, v: torch.Tensor, window: int) -> torch.Tensor:
    """``out[q] = sum_k W[k, q - k] V[k]``: each key scatters its weighted value over its window."""
    b, nh, h, w, _ = weights.shape
    vf = v.to(weights.dtype)
    n = 2 * window + 1
    dv = v.shape[-1]
    out = vf.new_zeros((b, nh, h + 2 * window, w, dv))
    for i, dy in enumerate(range(-window, window + 1)):  # one window row at a time, summed into place by col2im
        blocks = torch.einsum("bzyxo,bzyxd->bzdoyx", weights[..., i * n:(i + 1) * n], vf).reshape(b * nh, dv * n, h * w)
        row = F.fold(blocks, (h, w), (1, n), padding=(0, window)).view(b, nh, dv, h, w).permute(0, 1, 3, 4, 2)
        out[:, :, window + dy: window + dy + h] += row
    return out[:, :, window: window + h]


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
        coc, visibility: ``(B, H, W, (2w+1)^2)`` masks from ``bokehray_refiner.pisa.pisa_masks``
            (visibility None: no occlusion term).
        window: the window radius ``w`` of the masks.

    Returns:
        ``(B, heads, H, W, dv)`` in the dtype of ``v``.
    """
    if v.shape[:4] != q.shape[:4]:
        raise InputError(f"v: expected (B, heads, H, W, dv) matching q {tuple(q.shape[:4])}, got {tuple(v.shape)}")
    a = pisa_weights(q, k, coc, window, scale)
    if visibility is not None:
        if visibility.shape != coc.shape:
            raise InputError(f"visibility: expected the shape of coc {tuple(coc.shape)}, got {tuple(visibility.shape)}")
        vis = _batched(visibility).to(a.dtype)
        a = a.mul_(vis) if not a.requires_grad else a * vis
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
