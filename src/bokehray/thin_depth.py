"""Soft depth maps: thin structures a blurred map lost, given back their depth from the photo (docs/soft-scene.md,
"Soft maps").

A soft map is close to the true map blurred, ``D = G_s * D_true``, and the true map is locally two depths whose
boundary is the photo's colour boundary: ``D_true = a . I + b`` over a small window (the matting's local linear
colour model). Blurring both sides, ``D = a . (G_s * I) + b``: a ridge regression of the map on the photo blurred by
``s`` over each window gives ``(a, b)``, and ``a . I + b`` is the map before the blur, with the 1-3 px wires and
twigs a blur of 2-8 px flattened into a faint bump. Every window's regression comes from box filters of products
(as in the guided filter), so the step is a fixed number of image passes per blur tried.

:func:`restore_thin` tries the blurs ``ThinRule.sigmas`` and keeps, per pixel, the one whose colour model explains
its window best, among the fits that explain it clearly better than a plane does (tilted planes and smooth slopes
stay exactly as they are) and whose window holds no hard step (a hard map's step is no blur: hard maps stay exactly
as they are). The restored value is made hard, each pixel at the window's far plateau (its smallest map value) or
at its near value (the largest restored value around), and used only where that is a structure: the far value is
a plateau of the map, and so is the near value unless the structure is thin (a wide object's ramp is the ramp
snap's, ``bokehray.ramps``, which runs next); the restoration does not undershoot the far plateau as a texture's
amplified noise would; and enough of the window lies on the near side. The matting then splits the mixed pixels of
the step this leaves, as on a hard map.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["ThinRule", "restore_thin"]


@dataclass(frozen=True, slots=True)
class ThinRule:
    """The constants of :func:`restore_thin` (chosen on the dev set's soft maps: docs/design/thin-depth.md)."""

    sigmas: tuple[float, ...] = (2.0, 4.0, 8.0)
    """The map blurs tried (Gaussian sigma, px); each pixel keeps the one whose model fits its window best (1 px
    was almost never usable: such a map keeps steps of half its range, which the hard-step test refuses)."""
    window: float = 1.5
    """A blur ``s`` is fitted over windows of radius ``ceil(window * s) + 1`` px (at least 2)."""
    ridge: float = 1e-6
    """Ridge on the colour slopes, in squared tone-mapped colour units (the window's colour covariance is about
    1e-3 to 1e-2: the ridge only keeps flat windows solvable; 1e-4 halved what the fit gives back on the wires)."""
    ratio: float = 0.5
    """The colour model must leave less than this share of a plane's residual over the window."""
    jump: float = 0.5
    """A window with a 4-neighbour step of this share of its range or more holds a hard edge: left alone."""
    thin: float = 0.25
    """A thin structure: its restored near depth lies beyond the map's nearest value within twice the window by
    at least this share of its step (a wide object keeps its near plateau in the map: ``bokehray.ramps`` snaps
    its ramp to it)."""
    undershoot: float = 0.5
    """The restored values may fall below the window's far value by at most this share of the restored step."""
    keep: float = 0.1
    """A pixel in the top (bottom) share of its window's map range is not moved to the far (near) value, whatever
    its colour says (a blob of texture in a plateau is no structure)."""
    plateau_tol: float = 0.3
    """The window's far value must be a plateau: twice as wide, the map's smallest value is lower by at most this
    share of its range; and so must its near value, unless the structure is thin."""
    min_sd: float = 0.05
    """A window whose map varies by less than this (CoC px, rms) is flat: left alone."""
    grad_min: float = 0.2
    """Only tiles with a ramp somewhere are looked at: two steps in a row of the same sign, each above this (CoC px
    per px; ``ramps.RampRule.grad_min``)."""
    tile: int = 512
    """The work goes tile by tile (px), with a margin the fit reaches through; tiles with no ramp are skipped."""

    def radius(self, sigma: float) -> int:
        return max(2, math.ceil(self.window * sigma) + 1)

    def margin(self) -> int:
        """How far a pixel's result reaches: the blur's kernel (4 sigma), the fit's window, the hardening's."""
        s = max(self.sigmas)
        return math.ceil(4 * s) + 3 * self.radius(s) + 2


def restore_thin(image: np.ndarray, signed_coc: np.ndarray, rule: ThinRule | None = None, *,
                 bounds: tuple[float, float] | None = None, check=None) -> tuple[np.ndarray, int]:
    """The signed CoC map with the depth of structures its blur flattened given back from the photo, and how many
    pixels changed. ``image``: ``H x W x 3`` float32 linear RGB; ``signed_coc``: ``H x W`` float32, both finite.
    ``bounds``: the CoC of the farthest and the nearest disparity (0 and 1): restored values stay within them.
    The map is returned as given (not copied) when nothing changes. ``check()``: called between tiles."""
    rule = rule or ThinRule()
    s = np.ascontiguousarray(signed_coc, np.float32)
    h, w = s.shape
    if h < 3 or w < 3:
        return signed_coc, 0
    ramp = _ramps(s, rule.grad_min)
    if not ramp.any():
        return signed_coc, 0
    out, m, t = s.copy(), rule.margin(), rule.tile
    for y0 in range(0, h, t):
        for x0 in range(0, w, t):
            if not ramp[y0 : y0 + t, x0 : x0 + t].any():
                continue
            if check is not None:
                check()
            ya, xa = max(0, y0 - m), max(0, x0 - m)
            yb, xb = min(h, y0 + t + m), min(w, x0 + t + m)
            part = _restore(image[ya:yb, xa:xb], s[ya:yb, xa:xb], rule)
            out[y0 : y0 + t, x0 : x0 + t] = part[y0 - ya : y0 - ya + t, x0 - xa : x0 - xa + t]
    if bounds is not None:
        lo, hi = min(bounds), max(bounds)
        np.clip(out, min(lo, float(s.min())), max(hi, float(s.max())), out=out)
    n = int(np.count_nonzero(out != s))
    return (out, n) if n else (signed_coc, 0)


def _ramps(s: np.ndarray, grad_min: float) -> np.ndarray:
    """Pixels between two steps of the same sign above ``grad_min`` along a row or a column: a ramp (a hard map's
    steps stand alone, so its tiles are not fitted)."""
    out = np.zeros(s.shape, bool)
    dy, dx = np.diff(s, axis=0), np.diff(s, axis=1)
    out[1:-1] |= (np.abs(dy[:-1]) > grad_min) & (np.abs(dy[1:]) > grad_min) & (dy[:-1] * dy[1:] > 0)
    out[:, 1:-1] |= (np.abs(dx[:, :-1]) > grad_min) & (np.abs(dx[:, 1:]) > grad_min) & (dx[:, :-1] * dx[:, 1:] > 0)
    return out


def _gradient(s: np.ndarray) -> np.ndarray:
    gy = np.abs(np.diff(s, axis=0, append=s[-1:]))
    gx = np.abs(np.diff(s, axis=1, append=s[:, -1:]))
    return np.maximum(gy, gx)


def _box(x: np.ndarray, r: int) -> np.ndarray:
    """The mean over each (2r+1)^2 window, cut at the image's borders (a mirrored slope is no plane)."""
    h, w = x.shape[:2]
    total = cv2.boxFilter(x, -1, (2 * r + 1, 2 * r + 1), normalize=False, borderType=cv2.BORDER_CONSTANT)
    count = np.outer(_extent(h, r)[2], _extent(w, r)[2]).astype(np.float64)
    return total / (count if x.ndim == 2 else count[..., None])


def _extent(n: int, r: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per index along an axis of ``n``: the first and last index of its window of radius ``r``, and the count."""
    i = np.arange(n)
    lo, hi = np.maximum(i - r, 0), np.minimum(i + r, n - 1)
    return lo, hi, hi - lo + 1


def _restore(image: np.ndarray, s: np.ndarray, rule: ThinRule) -> np.ndarray:
    """One tile: the map normalised (mean 0, range 1), each blur fitted, the best explained window kept."""
    scale = float(s.max() - s.min())
    if scale <= 0:
        return s
    mean = float(s.mean())
    d = (s.astype(np.float64) - mean) / scale  # float64: the 3 x 3 solve is ill-conditioned where colours align
    guide = np.ascontiguousarray(image[..., :3], np.float64)
    guide = guide / (1 + np.maximum(guide, 0))  # tone-mapped: a lamp's value does not swamp the regression
    guide -= guide.reshape(-1, 3).mean(0)
    step = _gradient(d)
    best = np.full(d.shape, np.inf)
    out, use = d.copy(), np.zeros(d.shape, bool)
    floor = (rule.min_sd / scale) ** 2
    for sigma in rule.sigmas:  # the blur that explains the window best decides
        est, rel, ok, usable = _fit_blur(guide, d, step, sigma, rule, floor)
        better = ok & (rel < best)
        best[better] = rel[better]
        out[better] = est[better]
        use[better] = usable[better]
    return np.where(use & (out != d), out * scale + mean, s).astype(np.float32)


def _fit_blur(guide: np.ndarray, d: np.ndarray, step: np.ndarray, sigma: float, rule: ThinRule, floor: float):
    """The map restored under a blur ``sigma`` (hardened), its colour model's relative residual, where the model
    may be used (the colour explains the window better than a plane, and the window holds no hard step), and where
    its restoration is (``_harden``)."""
    r = rule.radius(sigma)
    gb = cv2.GaussianBlur(guide, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
    a, b, res, var = _colour_fit(gb, d, r, rule.ridge)
    kernel = np.ones((2 * r + 1, 2 * r + 1), np.uint8)
    far, near_d = cv2.erode(d, kernel), cv2.dilate(d, kernel)
    plane = _plane_residual(d, r)
    ok = (res < rule.ratio * plane) & (var > floor)
    ok &= cv2.dilate(step, kernel) < rule.jump * (near_d - far)
    est = np.einsum("...i,...i->...", a, guide) + b
    hard, use = _harden(est, d, ok, far, near_d, r, rule)
    return hard, res / np.maximum(var, 1e-12), ok, use


def _harden(est: np.ndarray, d: np.ndarray, ok: np.ndarray, far: np.ndarray, near_d: np.ndarray, r: int,
            rule: ThinRule) -> tuple[np.ndarray, np.ndarray]:
    """Each pixel at its window's far value (the map's smallest) or near value (the largest restored value), and
    where that is to be used: the far value is a plateau of the map, and so is the near value unless the structure
    is thin (its restored near depth beyond the map's nearest value within twice the window)."""
    top, near, count = _near_value(est, far, ok, r)
    wide = np.ones((4 * r + 1, 4 * r + 1), np.uint8)
    far_wide, near_wide = cv2.erode(d, wide), cv2.dilate(d, wide)
    tol = rule.plateau_tol * (near_wide - far_wide)
    thin = near > near_wide + rule.thin * (near - far)
    use = (far - far_wide <= tol) & (thin | (near_wide - near_d <= tol))
    # a restoration that falls as far below the far plateau as it rises above the map is the photo's noise
    # amplified (a smooth slope fitted by a texture blurred smooth), not a structure
    low = cv2.erode(np.where(ok, est, np.inf), np.ones((2 * r + 1, 2 * r + 1), np.uint8))
    use &= far - low <= rule.undershoot * (top - far)
    use &= count * (2 * r + 1) ** 2 >= r + 1  # a structure, not a speck: half a line across the window at least
    place = (d - far) / np.maximum(near_d - far, 1e-12)  # the pixel's place in the map's own window range
    to_near = (np.maximum(est, far) > 0.5 * (far + top)) & (place > rule.keep) | (place > 1 - rule.keep)
    return np.where(to_near, top, far), use


def _colour_fit(gb: np.ndarray, d: np.ndarray, r: int, ridge: float):
    """Per window: ``d ~ a . gb + b`` by ridge regression; (a, b, residual variance, variance of d)."""
    md = _box(d, r)
    mg = _box(gb, r)
    var = np.maximum(_box(d * d, r) - md * md, 0)
    c = _box(gb * d[..., None], r) - mg * md[..., None]
    cov = {}
    for i in range(3):
        for j in range(i, 3):
            cov[i, j] = cov[j, i] = _box(gb[..., i] * gb[..., j], r) - mg[..., i] * mg[..., j]
    a = _solve3(cov, c, ridge)
    b = md - np.einsum("...i,...i->...", a, mg)
    fit = sum(a[..., i] * cov[i, j] * a[..., j] for i in range(3) for j in range(3))
    res = np.maximum(var - 2 * np.einsum("...i,...i->...", a, c) + fit, 0)
    return a, b, res, var


def _solve3(cov: dict, c: np.ndarray, ridge: float) -> np.ndarray:
    """``(cov + ridge I)^-1 c`` per pixel for the symmetric 3 x 3 ``cov`` (by cofactors, elementwise)."""
    a00, a11, a22 = cov[0, 0] + ridge, cov[1, 1] + ridge, cov[2, 2] + ridge
    a01, a02, a12 = cov[0, 1], cov[0, 2], cov[1, 2]
    i00 = a11 * a22 - a12 * a12
    i01 = a02 * a12 - a01 * a22
    i02 = a01 * a12 - a02 * a11
    i11 = a00 * a22 - a02 * a02
    i12 = a01 * a02 - a00 * a12
    i22 = a00 * a11 - a01 * a01
    det = a00 * i00 + a01 * i01 + a02 * i02
    inv = 1.0 / np.maximum(det, ridge**3)  # cov is positive semi-definite: the ridge bounds the determinant
    c0, c1, c2 = c[..., 0], c[..., 1], c[..., 2]
    return np.stack([(i00 * c0 + i01 * c1 + i02 * c2) * inv, (i01 * c0 + i11 * c1 + i12 * c2) * inv,
                     (i02 * c0 + i12 * c1 + i22 * c2) * inv], -1)


def _plane_residual(d: np.ndarray, r: int) -> np.ndarray:
    """The residual variance of the best plane over each window (cut at the borders: a rectangle of pixels, whose
    x and y are uncorrelated, with the mean and variance of a run of integers along each axis)."""
    h, w = d.shape
    md = _box(d, r)
    var = _box(d * d, r) - md * md
    terms = []
    for n, axis in ((w, 1), (h, 0)):
        lo, hi, count = _extent(n, r)
        pos = (np.arange(n) - n / 2).astype(np.float64)
        mean = ((lo + hi) / 2 - n / 2).astype(np.float64)
        v = ((count.astype(np.float64) ** 2 - 1) / 12).astype(np.float64)
        shape = (1, n) if axis == 1 else (n, 1)
        cov = _box(d * pos.reshape(shape), r) - md * mean.reshape(shape)
        terms.append(cov * cov / v.reshape(shape))
    return np.maximum(var - terms[0] - terms[1], 0)


def _near_value(est: np.ndarray, far: np.ndarray, ok: np.ndarray, r: int) -> tuple[np.ndarray, np.ndarray]:
    """The window's near depth two ways: the largest restored value of its usable pixels (what the near side is
    set to: the fit's slope is biased low by the texture, its top is not), and the mean of those above the middle
    between it and the far value (what the thin test reads: robust to a single overshoot); and the share of the
    window's pixels above that middle."""
    top = cv2.dilate(np.where(ok, est, -np.inf), np.ones((2 * r + 1, 2 * r + 1), np.uint8))
    high = (ok & (est > 0.5 * (far + top))).astype(np.float64)
    count = _box(high, r)
    mean = _box(est * high, r) / np.maximum(count, 1e-6)
    return top, np.where(count > 0, mean, top), count

