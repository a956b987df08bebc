"""Float64 NumPy oracle of ``bokehray.thin_depth.restore_thin``: the same rule, one pixel and one window at a time
(a least-squares fit per window), written for reading, not speed. It answers for the pixels whose whole reach lies
inside the image (``interior``); the implementation's box filters reflect at the borders."""

from __future__ import annotations

import numpy as np
from scipy import ndimage


def interior(rule, shape) -> tuple[slice, slice]:
    """The pixels the oracle answers for: the blur's kernel, the fit's window and the hardening's two windows."""
    s = max(rule.sigmas)
    m = int(4 * s + 0.5) + 3 * rule.radius(s) + 1
    return slice(m, shape[0] - m), slice(m, shape[1] - m)


def _window(a: np.ndarray, y: int, x: int, r: int) -> np.ndarray:
    return a[y - r : y + r + 1, x - r : x + r + 1]


def _steps(d: np.ndarray) -> np.ndarray:
    step = np.zeros_like(d)
    step[:-1] = np.abs(np.diff(d, axis=0))
    step[:, :-1] = np.maximum(step[:, :-1], np.abs(np.diff(d, axis=1)))
    return step


def _fit_pixel(gb, d, step, guide, y, x, r, rule, floor):
    """(restored value before hardening, relative residual, usable) of the window around (y, x)."""
    g = _window(gb, y, x, r).reshape(-1, 3)
    v = _window(d, y, x, r).ravel()
    n = v.size
    gc, vc = g - g.mean(0), v - v.mean()
    a = np.linalg.solve(gc.T @ gc / n + rule.ridge * np.eye(3), gc.T @ vc / n)
    b = v.mean() - a @ g.mean(0)
    res = float(np.mean((vc - gc @ a) ** 2))
    yy, xx = np.mgrid[-r : r + 1, -r : r + 1]
    design = np.stack([np.ones(n), yy.ravel(), xx.ravel()], 1)
    plane = float(np.mean((v - design @ np.linalg.lstsq(design, v, rcond=None)[0]) ** 2))
    var = float(np.var(v))
    hard_step = _window(step, y, x, r).max() >= rule.jump * (v.max() - v.min())
    ok = res < rule.ratio * plane and var > floor and not hard_step
    return float(a @ guide[y, x] + b), res / max(var, 1e-12), ok


def _harden_pixel(d, est, ok, top, high, y, x, r, rule):
    """(hardened value, whether it is used) at (y, x), from the fits around it."""
    dw = _window(d, y, x, r)
    far, near_d = dw.min(), dw.max()
    hw = _window(high, y, x, r)
    near = _window(est, y, x, r)[hw].mean() if hw.any() else top[y, x]
    dw2 = _window(d, y, x, 2 * r)
    tol = rule.plateau_tol * (dw2.max() - dw2.min())
    thin = near > dw2.max() + rule.thin * (near - far)
    use = far - dw2.min() <= tol and (thin or dw2.max() - near_d <= tol)
    low = _window(est, y, x, r)[_window(ok, y, x, r)].min()
    use = use and far - low <= rule.undershoot * (top[y, x] - far) and hw.sum() >= r + 1
    place = (d[y, x] - far) / max(near_d - far, 1e-12)
    to_near = (max(est[y, x], far) > 0.5 * (far + top[y, x]) and place > rule.keep) or place > 1 - rule.keep
    return (top[y, x] if to_near else far), use


def restore_thin_ref(image: np.ndarray, s: np.ndarray, rule) -> tuple[np.ndarray, np.ndarray]:
    """(the restored map, which pixels changed) over ``interior(rule, s.shape)`` (elsewhere: the input)."""
    d = s.astype(np.float64)
    guide = image[..., :3].astype(np.float64)
    guide = guide / (1 + np.maximum(guide, 0))
    h, w = d.shape
    ys, xs = interior(rule, d.shape)
    step = _steps(d)
    out, best, use = d.copy(), np.full(d.shape, np.inf), np.zeros(d.shape, bool)
    floor = rule.min_sd**2
    for sigma in rule.sigmas:
        r = rule.radius(sigma)
        gb = np.stack([ndimage.gaussian_filter(guide[..., c], sigma, mode="reflect", truncate=4.0) for c in range(3)], -1)
        est, rel, ok = np.zeros((h, w)), np.full((h, w), np.inf), np.zeros((h, w), bool)
        top, high = np.full((h, w), -np.inf), np.zeros((h, w), bool)
        for y in range(ys.start - 2 * r, ys.stop + 2 * r):
            for x in range(xs.start - 2 * r, xs.stop + 2 * r):
                est[y, x], rel[y, x], ok[y, x] = _fit_pixel(gb, d, step, guide, y, x, r, rule, floor)
        for y in range(ys.start - r, ys.stop + r):
            for x in range(xs.start - r, xs.stop + r):
                ew, kw = _window(est, y, x, r), _window(ok, y, x, r)
                top[y, x] = ew[kw].max() if kw.any() else -np.inf
                high[y, x] = ok[y, x] and est[y, x] > 0.5 * (_window(d, y, x, r).min() + top[y, x])
        for y in range(ys.start, ys.stop):
            for x in range(xs.start, xs.stop):
                if not ok[y, x] or rel[y, x] >= best[y, x]:
                    continue
                best[y, x] = rel[y, x]
                out[y, x], use[y, x] = _harden_pixel(d, est, ok, top, high, y, x, r, rule)
    out = np.where(use, out, d)
    return out, out != d
