"""Prototype: give a soft map's lost thin structures their depth back from the photo (docs/soft-scene.md,
"Soft maps"; research/soft_thin/README.md).

A soft map is the true map blurred, D = G_s * D_true, and D_true is locally an affine function of the photo's
colour (two depths split by the colour's boundary: the matting's local linear model). So D = a . (G_s * I) + b
over a window: a ridge regression of the map on the photo blurred by s gives (a, b), and a . I + b is the map
before the blur. Box filters of products give every pixel's window regression at once (as the guided filter does).
"""

from __future__ import annotations

import cv2
import numpy as np


def _box(x: np.ndarray, r: int) -> np.ndarray:
    return cv2.boxFilter(x, -1, (2 * r + 1, 2 * r + 1), normalize=True, borderType=cv2.BORDER_REFLECT)


def fit_colour(guide: np.ndarray, d: np.ndarray, sigma: float, r: int, eps: float):
    """Per-pixel ridge regression of ``d`` on ``guide`` blurred by ``sigma`` over a (2r+1)^2 window.
    Returns (a [H,W,3], b [H,W], residual variance [H,W], variance of d [H,W])."""
    gb = guide if sigma <= 0 else cv2.GaussianBlur(guide, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
    md = _box(d, r)
    mg = [_box(gb[..., i], r) for i in range(3)]
    vd = _box(d * d, r) - md * md
    c = np.stack([_box(gb[..., i] * d, r) - mg[i] * md for i in range(3)], -1)
    cov = np.empty(d.shape + (3, 3), np.float64)
    for i in range(3):
        for j in range(i, 3):
            cov[..., i, j] = cov[..., j, i] = _box(gb[..., i] * gb[..., j], r) - mg[i] * mg[j]
    reg = cov + eps * np.eye(3)
    a = np.linalg.solve(reg, c[..., None])[..., 0]
    b = md - (a * np.stack(mg, -1)).sum(-1)
    res = vd - 2 * (a * c).sum(-1) + np.einsum("...i,...ij,...j->...", a, cov, a)
    return a, b, np.maximum(res, 0), np.maximum(vd, 0)


def fit_plane(d: np.ndarray, r: int) -> np.ndarray:
    """Residual variance of the best plane over each (2r+1)^2 window (interior formula)."""
    h, w = d.shape
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    md = _box(d, r)
    vd = _box(d * d, r) - md * md
    v = r * (r + 1) / 3.0
    cx = _box(xx * d, r) - xx * md
    cy = _box(yy * d, r) - yy * md
    return np.maximum(vd - (cx * cx + cy * cy) / v, 0)


def restore(image: np.ndarray, d: np.ndarray, sigmas=(1.0, 2.0, 4.0, 8.0), eps: float = 1e-4,
            ratio: float = 0.25, win: float = 2.0, jump: float = 0.5, average: bool = False,
            hard: str = "", info: dict | None = None) -> np.ndarray:
    d64 = d.astype(np.float64)
    guide = image.astype(np.float64)
    guide = guide / (1 + guide)
    best = np.full(d.shape, np.inf)
    out = d64.copy()
    pick = np.zeros(d.shape, np.int8)
    for k, s in enumerate(sigmas, 1):
        r = max(2, int(np.ceil(win * s)) + 1)
        a, b, res, vd = fit_colour(guide, d64, s, r, eps)
        if average:
            a = np.stack([_box(a[..., i], r) for i in range(3)], -1)
            b = _box(b, r)
        rel = res / np.maximum(vd, 1e-12)
        plane = fit_plane(d64, r)
        # the colour must explain the window much better than a plane does, and the window must ramp
        ok = (res < ratio * plane) & (vd > 1e-6)
        # no hard step in the window: a hard map's step is not a blur
        jmp = np.maximum(np.abs(np.diff(d64, axis=0, append=d64[-1:])), np.abs(np.diff(d64, axis=1, append=d64[:, -1:])))
        jmax = cv2.dilate(jmp, np.ones((2 * r + 1, 2 * r + 1), np.uint8))
        rng = cv2.dilate(d64, np.ones((2 * r + 1, 2 * r + 1), np.uint8)) - cv2.erode(d64, np.ones((2 * r + 1, 2 * r + 1), np.uint8))
        ok &= jmax < jump * rng
        better = ok & (rel < best)
        best = np.where(better, rel, best)
        est = (a * guide).sum(-1) + b
        if hard:
            est = harden(est, d64, ok, hard, r)
        out = np.where(better, est, out)
        pick[better] = k
    if info is not None:
        info["pick"] = pick
    return out.astype(np.float32)


def harden(rest: np.ndarray, d: np.ndarray, pick: np.ndarray, how: str, r: int) -> np.ndarray:
    """Snap the restored map's pixels to a window's two depths."""
    k = np.ones((2 * r + 1, 2 * r + 1), np.uint8)
    lo, hi_d = cv2.erode(d, k), cv2.dilate(d, k)
    out = rest.copy()
    m = pick
    if "clip" in how:  # nothing farther than the window's farthest blurred value
        out = np.where(m, np.maximum(out, lo), out)
    if "snap" in how:  # the near depth: the restored map's own high values
        hi = np.maximum(cv2.dilate(np.where(m, out, -np.inf), k), hi_d)
        near = out > 0.5 * (lo + hi)
        top = hi if "hi" in how else out
        out = np.where(m, np.where(near, top, lo), out)
    return out
