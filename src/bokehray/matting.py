"""Soft edges: split the mixed pixels at depth edges into a near and a far part (local sampling matting).

A pixel on the edge of a near object holds both colours, ``I = alpha F + (1 - alpha) B``, but a disparity map
gives it one depth. :func:`split_mixed_pixels` finds those pixels and estimates ``alpha``, the decontaminated
foreground ``F`` and the background ``B`` behind it, so the layered scene (``bokehray.scene.SoftEdges``) can
blur the two parts with their own CoC. NumPy over the edge bands only:

1. **Depth edges.** Pairs of 4-neighbours whose signed CoC differs by more than ``jump_px``
   (``depthfix.depth_edges``). A map whose edges are noise (an edge on most pixels, consecutive steps of
   alternating sign: ``depthfix.step_flips``) is left alone.
2. **Trimap.** The unknown band is every pixel within ``band_px`` (Chebyshev) of a depth-edge pixel. A soft map
   (an estimator's, a blurred one) has ramps: runs of consecutive same-sign steps across the edge; the band and
   the search window widen by the measured ramp width (:func:`ramp_width`, capped by ``max_ramp_px``). Around
   each band pixel the window's CoC range is split at its middle: pixels above are the near side, below the
   far side. Pixels outside the band are known (pure near or pure far); band pixels are unknown.
3. **Alpha: a local linear model of colour.** Per band pixel, ``alpha = w . I + c`` is fitted by ridge
   regression on its window (Gaussian weights): known pixels are 1 (near) or 0 (far), unknown ones count their
   side at a lower weight (``unknown_weight``), so a strand narrower than the band, with no known pixel of its
   own, is still found by its colour. The model is the colour direction that separates the two sides locally
   (closed-form matting's local model, solved per pixel instead of as one global system).
4. **F and B: sampling.** ``candidates`` pixels of each side are taken from the window, known ones first
   (nearest first), then unknown ones. Every (F, B) pair is scored by the distance ratio of colour-line
   sampling matting ``(|I - (a F + (1 - a) B)|^2 + sigma^2) / |F - B|^2`` (``a``: the photo colour projected on
   the F-B line; ``sigma``: a noise floor, which makes a purer, more contrasted candidate win among collinear
   ones) plus a spatial term; the best pair gives F, B and the near / far CoC (the CoC of the chosen samples,
   not the pixel's own mixed value). F and B are then averaged over the band pixels of each 3 x 3
   neighbourhood, weighted by the pairs' confidence (``smooth``).
5. **Compositing identity.** Per channel, the least-squares change of (F, B) that makes
   ``alpha F + (1 - alpha) B`` the photo's colour, kept between 0 and the photo's colour over the part's
   share (no negative light). Where ``|F - B|`` is below ``min_contrast`` the colour says nothing about alpha
   and the pixel is left alone.

A band pixel is split when its alpha lies in ``[min_alpha, 1 - min_alpha]``, or when its own CoC puts it on
the side its colour says it is not (a misplaced depth edge): then alpha is clipped into that range. Every other
pixel is untouched. Results and the choice of method: docs/soft-scene.md.
"""

from __future__ import annotations

import numpy as np

from .depthfix import depth_edges, step_flips
from .errors import InputError
from .scene import SoftEdges

__all__ = ["ramp_width", "split_mixed_pixels", "window_offsets"]

_UNKNOWN_PENALTY = 1.0e3
"""Added to an unknown candidate's distance when ranking candidates: every known one of a side comes first."""

_CHUNK = 8192
"""Band pixels processed together: bounds the memory to a few times ``_CHUNK x window pixels``."""


def ramp_width(signed_coc: np.ndarray, jump_px: float, cap: int) -> int:
    """How many pixels a depth edge's CoC ramp spans (0 for a hard edge): the 90th percentile, over the map's
    depth-edge pairs, of the length of the run of consecutive same-sign steps above ``jump_px`` a pair belongs
    to (along its axis), minus one; at most ``cap``."""
    lengths = []
    for ax in (0, 1):
        dd = np.diff(signed_coc, axis=ax)
        if dd.size == 0:
            continue
        sgn = np.where(dd > jump_px, 1, np.where(dd < -jump_px, -1, 0)).astype(np.int8)
        sgn = np.moveaxis(sgn, ax, -1).reshape(-1, sgn.shape[ax])
        flat = np.concatenate([sgn, np.zeros((sgn.shape[0], 1), np.int8)], axis=1).ravel()
        # run boundaries: where the sign changes (zeros end every row)
        change = np.flatnonzero(np.diff(np.concatenate([[0], flat])) != 0)
        starts = change
        ends = np.concatenate([change[1:], [flat.size]])
        vals = flat[starts]
        run = ends - starts
        keep = vals != 0
        lengths.append(np.repeat(run[keep], run[keep]))
    if not lengths or sum(v.size for v in lengths) == 0:
        return 0
    allr = np.concatenate(lengths)
    return int(min(cap, max(0, int(np.percentile(allr, 90)) - 1)))


def window_offsets(radius: int) -> tuple[np.ndarray, np.ndarray]:
    """(dy, dx) offsets of the search window and their distances, nearest first: every pixel within 4 px, and a
    grid of pitch 2 from there to ``radius`` (the far rings of a wide window hold the same colours at a quarter
    of the cost)."""
    r = int(radius)
    g = np.arange(-r, r + 1)
    oy, ox = np.meshgrid(g, g, indexing="ij")
    dist = np.hypot(oy, ox)
    keep = (dist <= r + 0.5) & ((dist <= 4.0) | ((oy % 2 == 0) & (ox % 2 == 0)))
    order = np.argsort(dist[keep], kind="stable")
    offs = np.stack([oy[keep], ox[keep]], 1)[order]
    return offs.astype(np.int64), dist[keep][order].astype(np.float32)


def _check(image: np.ndarray, signed_coc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    img = np.asarray(image)
    s = np.asarray(signed_coc)
    if img.ndim == 2:
        img = img[..., None]
    if img.ndim != 3 or img.shape[2] not in (1, 3, 4):
        raise InputError(f"image: expected an H x W x 3 linear RGB array, got shape {np.shape(image)}")
    if s.ndim == 3 and s.shape[2] == 1:
        s = s[..., 0]
    if s.shape != img.shape[:2]:
        raise InputError(f"signed_coc: expected an H x W map of the image's size {img.shape[:2]}, got {s.shape}")
    if not (np.issubdtype(img.dtype, np.number) and np.issubdtype(s.dtype, np.number)):
        raise InputError(f"image, signed_coc: expected numeric arrays, got {img.dtype} and {s.dtype}")
    img = np.asarray(img[..., :3] if img.shape[2] >= 3 else np.repeat(img, 3, axis=2), np.float32)
    s = np.asarray(s, np.float32)
    for a, name in ((img, "image"), (s, "signed_coc")):
        bad = ~np.isfinite(a)
        if bad.any():
            raise InputError(f"{name}: expected finite values, got NaN/Inf at {np.unravel_index(int(np.argmax(bad)), bad.shape)}")
    return np.ascontiguousarray(img), np.ascontiguousarray(s)


def _dilate(mask: np.ndarray, k: int) -> np.ndarray:
    if k <= 0:
        return mask.copy()
    from scipy import ndimage

    return ndimage.binary_dilation(mask, np.ones((2 * k + 1, 2 * k + 1), bool))


def split_mixed_pixels(
    image: np.ndarray,
    signed_coc: np.ndarray,
    *,
    jump_px: float = 1.0,
    band_px: int = 1,
    max_ramp_px: int = 6,
    candidates: int = 6,
    spatial_weight: float = 0.05,
    noise: float = 0.02,
    min_contrast: float = 0.02,
    min_alpha: float = 0.02,
    smooth: bool = True,
    max_edge_share: float = 0.4,
    unknown_weight: float = 0.3,
    ridge: float = 0.03,
) -> SoftEdges:
    """Split the mixed pixels at the depth edges of ``signed_coc`` into a near and a far part.

    Args:
        image: ``H x W x 3`` float32, scene-linear (1 or 4 channels are taken as grey / RGB).
        signed_coc: ``H x W`` signed CoC ``K (d - d_f)`` in px (> 0 in front of the focus).
        jump_px: a depth edge is a pair of 4-neighbours whose CoC differs by more than this.
        band_px: half-width (Chebyshev px) of the unknown band around the depth-edge pixels of a hard edge.
        max_ramp_px: the widest CoC ramp (px) the band and the window widen for (a soft map's edges).
        candidates: samples of each side per pixel (``candidates^2`` pairs are scored).
        spatial_weight: weight of the samples' squared distance (over the window radius squared) in the score.
        noise: the colour noise floor relative to the pixel's brightness (``sigma`` of the score).
        min_contrast: pixels whose F and B differ by less than this share of the brighter of the two (Euclidean,
            linear RGB) are left alone: their colour says nothing about alpha.
        min_alpha: split pixels have ``min_alpha <= alpha <= 1 - min_alpha``.
        smooth: average F and B over each 3 x 3 neighbourhood of the band before alpha is taken.
        max_edge_share: a map with depth edges on more than this share of its pixels whose consecutive steps
            mostly flip sign is noise, not edges: nothing is split.

    Returns:
        The split pixels (:class:`~bokehray.scene.SoftEdges`); ``SoftEdges.empty()`` when the map has no edge.
        For every split pixel ``alpha F + (1 - alpha) B`` is the photo's colour (up to float32 rounding),
        ``near_coc > far_coc``, and F, B lie between 0 and the colour over the part's share.

    Raises:
        InputError: mismatched shapes, non-numeric or non-finite input.
    """
    img, s = _check(image, signed_coc)
    photo = img
    h, w = s.shape
    if h < 2 and w < 2:
        return SoftEdges.empty()
    edges = depth_edges(s, float(jump_px))
    n_edge = int(edges.sum())
    if n_edge == 0:
        return SoftEdges.empty()
    if n_edge > max_edge_share * s.size and step_flips(s, float(jump_px)) > 0.5:
        return SoftEdges.empty()  # noise in the map, not edges

    scale = float(np.abs(img).max())
    if scale > 0.0:  # every threshold below is relative: the result does not depend on the exposure
        img = img / np.float32(scale)
    ramp = ramp_width(s, float(jump_px), int(max_ramp_px))
    b = int(band_px) + (ramp + 1) // 2
    radius = ramp + 2 * b + 2
    # work on the box of the edges, padded by everything a band pixel's window reaches
    ey, ex = np.nonzero(edges)
    pad = b + radius
    y0, y1 = max(0, int(ey.min()) - pad), min(h, int(ey.max()) + pad + 1)
    x0, x1 = max(0, int(ex.min()) - pad), min(w, int(ex.max()) + pad + 1)
    band = _dilate(edges[y0:y1, x0:x1], b)
    ch, cw = band.shape
    r = radius
    wp_ = cw + 2 * r
    img_p = np.pad(img[y0:y1, x0:x1], ((r, r), (r, r), (0, 0))).reshape(-1, 3)
    s_p = np.pad(s[y0:y1, x0:x1], r).ravel()
    valid_p = np.pad(np.ones((ch, cw), bool), r).ravel()
    unknown_p = np.pad(band, r).ravel()
    offs, dist = window_offsets(r)
    off_f = offs[:, 0] * wp_ + offs[:, 1]
    k = max(1, min(int(candidates), offs.shape[0]))

    by, bx = np.nonzero(band)
    n = by.size
    p_f = (by + r) * wp_ + (bx + r)
    F = np.zeros((n, 3), np.float32)
    B = np.zeros((n, 3), np.float32)
    conf = np.zeros(n, np.float32)
    near = np.zeros(n, np.float32)
    far = np.zeros(n, np.float32)
    mid_all = np.zeros(n, np.float32)
    ok = np.zeros(n, bool)
    lin_alpha = np.zeros(n, np.float32)
    rank = dist[None, :].astype(np.float32)
    r2 = np.float32(max(radius, 1) ** 2)
    for c0 in range(0, n, _CHUNK):
        c1 = min(n, c0 + _CHUNK)
        q = p_f[c0:c1, None] + off_f[None, :]
        sq = s_p[q]
        vq = valid_p[q]
        hi = np.where(vq, sq, -np.inf).max(1)
        lo = np.where(vq, sq, np.inf).min(1)
        mid = 0.5 * (hi + lo)
        has_edge = (hi - lo) > jump_px
        key = rank + np.float32(_UNKNOWN_PENALTY) * unknown_p[q]
        nearside = vq & (sq > mid[:, None])
        farside = vq & (sq <= mid[:, None])
        sel_f = np.argsort(np.where(nearside, key, np.inf), axis=1, kind="stable")[:, :k]
        sel_b = np.argsort(np.where(farside, key, np.inf), axis=1, kind="stable")[:, :k]
        rows = np.arange(c1 - c0)[:, None]
        okf = nearside[rows, sel_f]
        okb = farside[rows, sel_b]
        qf, qb = q[rows, sel_f], q[rows, sel_b]
        Fc, Bc = img_p[qf], img_p[qb]  # (m, k, 3)
        I = img[y0:y1, x0:x1][by[c0:c1], bx[c0:c1]]
        d = Fc[:, :, None, :] - Bc[:, None, :, :]  # (m, kf, kb, 3)
        ib = I[:, None, None, :] - Bc[:, None, :, :]
        den = np.einsum("mijc,mijc->mij", d, d)
        a = np.clip(np.einsum("mijc,mijc->mij", ib, d) / np.maximum(den, np.float32(1e-12)), 0.0, 1.0)
        res = ib - a[..., None] * d
        res2 = np.einsum("mijc,mijc->mij", res, res)
        sig2 = np.float32(noise) ** 2 * (I * I).sum(1) + np.float32(1e-12)
        cost = (res2 + sig2[:, None, None]) / np.maximum(den, np.float32(1e-12))
        cost += np.float32(spatial_weight) * (dist[sel_f][:, :, None] ** 2 + dist[sel_b][:, None, :] ** 2) / r2
        far_enough = den > np.float32(min_contrast) ** 2 * np.maximum((Fc * Fc).sum(-1)[:, :, None], (Bc * Bc).sum(-1)[:, None, :])
        cost = np.where(okf[:, :, None] & okb[:, None, :] & far_enough & (den > 1e-12), cost, np.inf)
        best = np.argmin(cost.reshape(c1 - c0, -1), axis=1)
        bi, bj = np.divmod(best, k)
        m = np.arange(c1 - c0)
        cbest = cost[m, bi, bj]
        good = has_edge & np.isfinite(cbest)
        F[c0:c1] = Fc[m, bi]
        B[c0:c1] = Bc[m, bj]
        conf[c0:c1] = np.where(good, 1.0 / (cbest + np.float32(1e-3)), 0.0)
        near[c0:c1] = s_p[qf[m, bi]]
        far[c0:c1] = s_p[qb[m, bj]]
        mid_all[c0:c1] = mid
        ok[c0:c1] = good
        lin_alpha[c0:c1] = _linear_alpha(img_p[q], I, vq, unknown_p[q], nearside, dist, radius, unknown_weight,
                                         ridge)

    if smooth and n:
        F, B = _smooth(F, B, conf, by, bx, ch, cw)
    I = img[y0:y1, x0:x1][by, bx]
    d = F - B
    den = (d * d).sum(1)
    contrast = (den > np.float32(min_contrast) ** 2 * np.maximum((F * F).sum(1), (B * B).sum(1))) & (den > 1e-12)
    alpha = lin_alpha
    own_near = s[y0:y1, x0:x1][by, bx] > mid_all
    lo_a, hi_a = np.float32(min_alpha), np.float32(1.0 - min_alpha)
    mixed = (alpha >= lo_a) & (alpha <= hi_a)
    misplaced = ((alpha < lo_a) & own_near) | ((alpha > hi_a) & ~own_near)
    split = ok & contrast & (mixed | misplaced) & (near > far)
    if not split.any():
        return SoftEdges.empty()
    a = np.clip(alpha[split], lo_a, hi_a).astype(np.float32)
    Fs, Bs = _composite_exact(photo[y0:y1, x0:x1][by[split], bx[split]], a, F[split] * np.float32(scale),
                              B[split] * np.float32(scale))
    index = ((by[split] + y0).astype(np.int64) * w + (bx[split] + x0)).astype(np.int64)
    order = np.argsort(index, kind="stable")  # np.nonzero is row-major already; kept explicit
    return SoftEdges(index[order], a[order], Fs[order], Bs[order], near[split][order].astype(np.float32),
                     far[split][order].astype(np.float32))


def _linear_alpha(cq: np.ndarray, I: np.ndarray, vq: np.ndarray, unknown: np.ndarray, nearside: np.ndarray,
                  dist: np.ndarray, radius: int, unknown_weight: float, ridge: float) -> np.ndarray:
    """Alpha of each pixel from ``alpha = w . I + c`` fitted on its window by weighted ridge regression.

    ``cq``: the window's colours (m, M, 3); ``I``: the pixels' colours (m, 3); ``vq``: inside the image;
    ``unknown``: in the band; ``nearside``: the target (1 near, 0 far). Weights: a Gaussian of half the window's
    radius, times ``unknown_weight`` for unknown pixels. The ridge is ``ridge^2`` times the window's mean squared
    colour (scale-free).
    """
    wt = np.exp(-(dist * dist) / np.float32(2.0 * (0.5 * radius) ** 2))[None, :] * vq
    wt = wt * np.where(unknown, np.float32(unknown_weight), np.float32(1.0))
    y = nearside.astype(np.float32)
    sw = np.maximum(wt.sum(1), np.float32(1e-12))
    wn = (wt / sw[:, None]).astype(np.float32)  # normalised weights
    mu = np.matmul(wn[:, None, :], cq)[:, 0, :]  # (m, 3)
    my = (wn * y).sum(1)
    second = np.matmul((cq * wn[..., None]).transpose(0, 2, 1), cq)  # (m, 3, 3): E[I I^T]
    cov = second - mu[:, :, None] * mu[:, None, :]
    eps = np.float32(ridge) ** 2 * ((mu * mu).mean(1) + np.float32(1e-8))
    cov = cov + eps[:, None, None] * np.eye(3, dtype=np.float32)[None]
    cy = np.matmul((wn * y)[:, None, :], cq)[:, 0, :] - my[:, None] * mu  # E[y I] - E[y] E[I]
    wv = np.linalg.solve(cov, cy[..., None])[..., 0]
    return np.clip(my + ((I - mu) * wv).sum(1), 0.0, 1.0).astype(np.float32)


def _smooth(F: np.ndarray, B: np.ndarray, conf: np.ndarray, by: np.ndarray, bx: np.ndarray, ch: int,
            cw: int) -> tuple[np.ndarray, np.ndarray]:
    """F and B averaged over the band pixels of each 3 x 3 neighbourhood, weighted by confidence."""
    wp_ = cw + 2
    flat = (by + 1) * wp_ + (bx + 1)
    size = (ch + 2) * wp_
    cf = np.zeros(size, np.float32)
    cf[flat] = conf
    Fm = np.zeros((size, 3), np.float32)
    Bm = np.zeros((size, 3), np.float32)
    Fm[flat] = F * conf[:, None]
    Bm[flat] = B * conf[:, None]
    sf = np.zeros_like(F)
    sb = np.zeros_like(B)
    sw = np.zeros_like(conf)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            q = flat + dy * wp_ + dx
            sw += cf[q]
            sf += Fm[q]
            sb += Bm[q]
    has = sw > 0
    Fo = np.where(has[:, None], sf / np.where(has, sw, 1.0)[:, None], F)
    Bo = np.where(has[:, None], sb / np.where(has, sw, 1.0)[:, None], B)
    return Fo.astype(np.float32), Bo.astype(np.float32)


def _composite_exact(I: np.ndarray, a: np.ndarray, F: np.ndarray, B: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(F, B) moved the least (sum of squares, per channel) so that ``a F + (1 - a) B = I``, with F between 0 and
    ``I / a`` and B between 0 and ``I / (1 - a)`` (no negative light, no part brighter than the pixel allows)."""
    I64, F64, B64 = I.astype(np.float64), F.astype(np.float64), B.astype(np.float64)
    a64 = a.astype(np.float64)[:, None]
    r = I64 - a64 * F64 - (1.0 - a64) * B64
    norm = a64 * a64 + (1.0 - a64) * (1.0 - a64)
    Fn = F64 + r * a64 / norm
    lo = np.minimum(0.0, I64 / a64)
    hi = np.maximum(0.0, I64 / a64)
    Fn = np.clip(Fn, lo, hi)
    Bn = (I64 - a64 * Fn) / (1.0 - a64)
    Bn = np.clip(Bn, np.minimum(0.0, I64 / (1.0 - a64)), np.maximum(0.0, I64 / (1.0 - a64)))  # rounding only
    return Fn.astype(np.float32), Bn.astype(np.float32)
