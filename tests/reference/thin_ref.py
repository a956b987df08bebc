"""Float64 NumPy oracle of ``bokehray.thin_depth.restore_thin``: the same rule, one sample, one window and one pixel
at a time (a least-squares fit per window), written for reading, not speed. It answers for images whose sides are
multiples of the largest grid spacing (the implementation pads the others)."""

from __future__ import annotations

import math

import numpy as np
from scipy import ndimage


def _blocks(a: np.ndarray, f: int) -> np.ndarray:
    """``a`` (H x W x ...) as blocks: (H / f) x (W / f) x f x f x ..."""
    h, w = a.shape[:2]
    return a.reshape(h // f, f, w // f, f, *a.shape[2:]).swapaxes(1, 2)


def _window(a: np.ndarray, i: int, j: int, k: int) -> np.ndarray:
    """The samples within ``k`` of (i, j), cut at the grid's borders."""
    return a[max(0, i - k) : i + k + 1, max(0, j - k) : j + k + 1]


def _steps(d: np.ndarray) -> np.ndarray:
    step = np.zeros_like(d)
    step[:-1] = np.abs(np.diff(d, axis=0))
    step[:, :-1] = np.maximum(step[:, :-1], np.abs(np.diff(d, axis=1)))
    return step


def _fit_sample(gb, dm, low, high, step, i, j, k, sigma, rule):
    """(a, b, usable, relative residual) of the window around sample (i, j); None where it may not be fitted."""
    far, near = _window(low, i, j, k).min(), _window(high, i, j, k).max()
    span, steepest = near - far, _window(step, i, j, k).max()
    if not (steepest < rule.jump * span and span >= rule.min_step):
        return None
    if not (sigma / rule.profile * steepest <= span <= rule.profile * sigma * steepest):
        return None
    g = _window(gb, i, j, k).reshape(-1, 3)
    v = _window(dm, i, j, k).ravel()
    n = v.size
    gc, vc = g - g.mean(0), v - v.mean()
    a = np.linalg.solve(gc.T @ gc / n + rule.ridge * np.eye(3), gc.T @ vc / n)
    b = v.mean() - a @ g.mean(0)
    res = float(np.mean((vc - gc @ a) ** 2))
    yy, xx = np.meshgrid(np.arange(max(0, i - k), min(dm.shape[0], i + k + 1)),
                         np.arange(max(0, j - k), min(dm.shape[1], j + k + 1)), indexing="ij")
    design = np.stack([np.ones(n), yy.ravel(), xx.ravel()], 1)
    plane = float(np.mean((v - design @ np.linalg.lstsq(design, v, rcond=None)[0]) ** 2))
    var = float(np.var(v))
    ok = res < rule.ratio * plane and var > rule.min_sd**2
    return a, b, ok, res / max(var, 1e-12)


def _fit(tone_blocks_mean, d, sigma, rule, choosing):
    """One blur's fits on its grid: dict of per-sample arrays (a, b, ok, rel) and the grid's block min / max."""
    f = rule.factor(sigma, choosing)
    gm = tone_blocks_mean(f)
    dm = _blocks(d, f).mean((2, 3))
    low, high = _blocks(d, f).min((2, 3)), _blocks(d, f).max((2, 3))
    step = _blocks(_steps(d), f).max((2, 3))
    rest = math.sqrt(max(sigma * sigma - (f * f - 1) / 12, 0.0)) / f
    gb = np.stack([ndimage.gaussian_filter(gm[..., c], rest, mode="reflect", truncate=4.0) for c in range(3)], -1)
    hl, wl = dm.shape
    a, b = np.zeros((hl, wl, 3)), np.zeros((hl, wl))
    ok, rel = np.zeros((hl, wl), bool), np.full((hl, wl), np.inf)
    for i in range(hl):
        for j in range(wl):
            got = _fit_sample(gb, dm, low, high, step, i, j, rule.samples(sigma, f), sigma, rule)
            if got is not None:
                a[i, j], b[i, j], ok[i, j], rel[i, j] = got
    return {"f": f, "k": rule.samples(sigma, f), "sigma": sigma, "a": a, "b": b, "ok": ok, "rel": rel, "low": low, "high": high}


def _flat(low, i, j, k, e):
    """The largest value the map holds over a whole square of ``e`` samples around a sample within ``k`` of (i, j)
    (each sample's own value there: its block's smallest)."""
    hl, wl = low.shape
    best = -np.inf
    for y in range(max(0, i - k), min(hl, i + k + 1)):
        for x in range(max(0, j - k), min(wl, j + k + 1)):
            # the square is cut at the grid's borders (its border samples repeat: the same minimum)
            best = max(best, _window(low, y, x, e).min())
    return best


def _near_value(fit, top, far, i, j, rule):
    """A thin structure's near value is the largest restored value of its window; a wide object's (the map holds its
    largest value within twice the window as a plateau, over a square of ``flat_reach`` blurs) that plateau where
    it is lower. (near value, wide)."""
    k, f = fit["k"], fit["f"]
    e = max(1, int(rule.flat_reach * fit["sigma"] / f))
    near_wide = _window(fit["high"], i, j, 2 * k).max()
    wide = near_wide - _flat(fit["low"], i, j, 2 * k, e) <= rule.flat_tol * (near_wide - far)
    return (min(top, near_wide) if wide else top), wide


def _harden(fit, guide, d, rule):
    """The restored map (and which pixels it moved) from the image's chosen fit."""
    f, k, ok = fit["f"], fit["k"], fit["ok"]
    hl, wl = ok.shape
    est = np.einsum("ijc,ijxyc->ijxy", fit["a"], _blocks(guide, f)) + fit["b"][..., None, None]
    top, low_est = np.full((hl, wl), -np.inf), np.full((hl, wl), np.inf)
    far, near_d = np.zeros((hl, wl)), np.zeros((hl, wl))
    near_v, wide = np.full((hl, wl), -np.inf), np.zeros((hl, wl), bool)
    for i in range(hl):
        for j in range(wl):
            okw = _window(ok, i, j, k)
            far[i, j] = _window(fit["low"], i, j, k).min()
            near_d[i, j] = _window(fit["high"], i, j, k).max()
            if okw.any():
                top[i, j] = _window(est, i, j, k)[okw].max()
                low_est[i, j] = _window(est, i, j, k)[okw].min()
                near_v[i, j], wide[i, j] = _near_value(fit, top[i, j], far[i, j], i, j, rule)
    high = ok[..., None, None] & (est > (0.5 * (far + near_v))[..., None, None])
    out = d.copy()
    r = (2 * k + 1) * f // 2
    for i in range(hl):
        for j in range(wl):
            if not ok[i, j]:
                continue
            hw = _window(high, i, j, k)
            n_high = hw.sum() / (hw.shape[0] * hw.shape[1])
            far_wide, near_wide = _window(fit["low"], i, j, 2 * k).min(), _window(fit["high"], i, j, 2 * k).max()
            tol = rule.plateau_tol * (near_wide - far_wide)
            use = far[i, j] - far_wide <= tol and (not wide[i, j] or near_wide - near_d[i, j] <= tol)
            use = use and far[i, j] - low_est[i, j] <= rule.undershoot * (top[i, j] - far[i, j])
            use = use and near_v[i, j] - far[i, j] >= rule.min_step and n_high * (2 * k + 1) ** 2 >= r + 1
            if not use:
                continue
            for y in range(f):
                for x in range(f):
                    py, px = i * f + y, j * f + x
                    place = (d[py, px] - far[i, j]) / max(near_d[i, j] - far[i, j], 1e-12)
                    up = max(est[i, j, y, x], far[i, j]) > 0.5 * (far[i, j] + near_v[i, j])
                    to_near = (up and place > rule.keep) or place > 1 - rule.keep
                    out[py, px] = near_v[i, j] if to_near else far[i, j]
    return out


def restore_thin_ref(image: np.ndarray, s: np.ndarray, rule) -> tuple[np.ndarray, np.ndarray]:
    """(the restored map, which pixels changed): each blur fitted on its grid, the blur whose usable windows' median
    relative residual is lowest applied to the whole image (a fine blur from its per-pixel fit)."""
    d = s.astype(np.float64)
    photo = image[..., :3].astype(np.float64)

    def tone_blocks_mean(f):  # the regression's colour: the block's mean colour, tone-mapped
        m = _blocks(photo, f).mean((2, 3))
        return m / (1 + np.maximum(m, 0))

    fits = [_fit(tone_blocks_mean, d, sigma, rule, True) for sigma in rule.sigmas]
    fits = [x for x in fits if x["ok"].any()]
    if not fits:
        return d, np.zeros(d.shape, bool)
    best = min(fits, key=lambda x: float(np.median(x["rel"][x["ok"]])))
    if rule.factor(best["sigma"]) != best["f"]:  # a fine blur: applied from its per-pixel fit
        best = _fit(tone_blocks_mean, d, best["sigma"], rule, False)
        if not best["ok"].any():
            return d, np.zeros(d.shape, bool)
    out = _harden(best, photo / (1 + np.maximum(photo, 0)), d, rule)
    return out, out != d


# --- the kernels of ``bokehray_kernels.thin``, one at a time ---------------------------------------------------


def ramps_ref(s: np.ndarray, grad_min: float) -> bool:
    """``thin_ramp_kernel``: whether two steps in a row (along a row or a column) are both above ``grad_min`` or
    both below ``-grad_min``, the steps as the map's float32 differences (the kernel's)."""
    g = np.float32(grad_min)
    for d in (np.diff(s, axis=1), np.diff(s, axis=0).T):
        for i in range(d.shape[0]):
            for j in range(d.shape[1] - 1):
                if (d[i, j] > g and d[i, j + 1] > g) or (d[i, j] < -g and d[i, j + 1] < -g):
                    return True
    return False


def level_ref(photo: np.ndarray, s: np.ndarray):
    """``thin_level_kernel``: the 2 x 2 blocks (the last row / column repeated at an odd side) of the photo and the
    map: mean colour, mean, smallest and largest value, largest step to a right or lower neighbour."""
    h, w = s.shape
    ph, pw = h + h % 2, w + w % 2
    rows, cols = np.minimum(np.arange(ph), h - 1), np.minimum(np.arange(pw), w - 1)
    sp, pp = s[rows][:, cols].astype(np.float64), photo[rows][:, cols].astype(np.float64)
    step = _steps(s.astype(np.float64))[rows][:, cols]
    return (_blocks(pp, 2).mean((2, 3)), _blocks(sp, 2).mean((2, 3)), _blocks(sp, 2).min((2, 3)),
            _blocks(sp, 2).max((2, 3)), _blocks(step, 2).max((2, 3)))


def window_fit_ref(gb: np.ndarray, d: np.ndarray, ys: np.ndarray, xs: np.ndarray, k: int, ridge: float):
    """``thin_fit_kernel``: per sample, over its window of radius ``k`` (cut at the grid's borders), the ridge
    regression of ``d`` on ``gb`` (a, b, residual variance), the variance of ``d`` and the residual variance of the
    least-squares plane."""
    out = []
    for y, x in zip(ys, xs):
        g = _window(gb, y, x, k).reshape(-1, 3).astype(np.float64)
        v = _window(d, y, x, k).ravel().astype(np.float64)
        n = v.size
        gc, vc = g - g.mean(0), v - v.mean()
        a = np.linalg.solve(gc.T @ gc / n + ridge * np.eye(3), gc.T @ vc / n)
        res = max(float(np.mean((vc - gc @ a) ** 2)), 0.0)
        yy, xx = np.meshgrid(np.arange(max(0, y - k), min(d.shape[0], y + k + 1)),
                             np.arange(max(0, x - k), min(d.shape[1], x + k + 1)), indexing="ij")
        design = np.stack([np.ones(n), yy.ravel(), xx.ravel()], 1)
        plane = float(np.mean((v - design @ np.linalg.lstsq(design, v, rcond=None)[0]) ** 2))
        out.append((a, v.mean() - a @ g.mean(0), res, float(np.var(v)), plane))
    return out


def _tone(c: np.ndarray) -> np.ndarray:
    return c / (1 + np.maximum(c, 0))


def block_pixels(iy: int, ix: int, f: int, shape: tuple[int, int], own: bool = False):
    """The pixels of block (iy, ix): the last row / column repeated at the image's edge, or (``own``) left out."""
    for p in range(f):
        for q in range(f):
            y, x = iy * f + p, ix * f + q
            if own and (y >= shape[0] or x >= shape[1]):
                continue
            yield min(y, shape[0] - 1), min(x, shape[1] - 1)


def extremes_ref(photo, iy, ix, f, a, b):
    """``thin_extremes_kernel``: per block the model ``a . tone(photo) + b`` at its pixels (f x f, the edge's
    repeats included), its largest and smallest value."""
    est = np.zeros((len(iy), f, f))
    for t in range(len(iy)):
        for n, (y, x) in enumerate(block_pixels(iy[t], ix[t], f, photo.shape[:2])):
            est[t, n // f, n % f] = float(np.dot(a[t], _tone(photo[y, x].astype(np.float64)))) + float(b[t])
    return est, est.max((1, 2)), est.min((1, 2))


def harden_ref(photo, coc, iy, ix, f, a, b, far, near, top, centre, scale, keep, lo, hi):
    """``thin_harden_kernel``: the map with each pixel a block holds at its far or near value (normalised
    ``(coc - centre) / scale``), back in CoC px and clamped to [lo, hi]."""
    out = coc.astype(np.float64).copy()
    for t in range(len(iy)):
        for y, x in block_pixels(iy[t], ix[t], f, coc.shape, own=True):
            d = (float(coc[y, x]) - centre) / scale
            place = (d - far[t]) / max(top[t] - far[t], 1e-12)
            e = float(np.dot(a[t], _tone(photo[y, x].astype(np.float64)))) + float(b[t])
            to_near = (max(e, far[t]) > 0.5 * (far[t] + near[t]) and place > keep) or place > 1 - keep
            out[y, x] = min(max((near[t] if to_near else far[t]) * scale + centre, lo), hi)
    return out
