"""Float64 NumPy oracle of ``bokehray_kernels.ramps`` (``bokehray.ramps.snap_ramps``): the same rule, one pixel
at a time, written for reading, not speed."""

from __future__ import annotations

import math

import numpy as np


def sobel_ref(s: np.ndarray, y: int, x: int) -> tuple[float, float]:
    h, w = s.shape

    def at(yy: int, xx: int) -> float:
        return float(s[min(max(yy, 0), h - 1), min(max(xx, 0), w - 1)])

    gy = (at(y + 1, x - 1) + 2 * at(y + 1, x) + at(y + 1, x + 1)) - (at(y - 1, x - 1) + 2 * at(y - 1, x) + at(y - 1, x + 1))
    gx = (at(y - 1, x + 1) + 2 * at(y, x + 1) + at(y + 1, x + 1)) - (at(y - 1, x - 1) + 2 * at(y, x - 1) + at(y + 1, x - 1))
    return gy / 8.0, gx / 8.0


def snap_ramps_ref(image: np.ndarray, s: np.ndarray, rule) -> tuple[np.ndarray, np.ndarray]:
    """(the snapped map, which pixels were snapped) for ``rule`` (a ``bokehray.ramps.RampRule``)."""
    h, w = s.shape
    s = s.astype(np.float64)
    img = image.astype(np.float64)
    grad = np.array([[math.hypot(*sobel_ref(s, y, x)) for x in range(w)] for y in range(h)])
    out = s.copy()
    moved = np.zeros((h, w), bool)
    for y in range(h):
        for x in range(w):
            if grad[y, x] > rule.grad_min:
                v = _snapped(img, s, grad, y, x, rule)
                if v is not None:
                    out[y, x], moved[y, x] = v, True
    return out, moved


def _at(v: float, n: int) -> int:
    return min(max(math.floor(v + 0.5), 0), n - 1)


def _walk(grad, y, x, ny, nx, rule) -> int:
    h, w = grad.shape
    for k in range(1, rule.max_walk + 1):
        if grad[_at(y + k * ny, h), _at(x + k * nx, w)] <= rule.grad_min:
            return k
    return 0


def _colour(img, y, x, ny, nx, k0, rule) -> np.ndarray:
    h, w = img.shape[:2]
    return np.mean([img[_at(y + (k0 + j) * ny, h), _at(x + (k0 + j) * nx, w)] for j in range(rule.samples)], 0)


def _snapped(img, s, grad, y, x, rule) -> float | None:
    """The plateau value pixel (y, x) takes, or None where it stays."""
    h, w = s.shape
    gy, gx = sobel_ref(s, y, x)
    g = math.hypot(gy, gx)
    ny, nx = gy / g, gx / g
    kn, kf = _walk(grad, y, x, ny, nx, rule), _walk(grad, y, x, -ny, -nx, rule)
    if kn == 0 or kf == 0 or kn + kf < rule.min_len:
        return None
    vn, vf = s[_at(y + kn * ny, h), _at(x + kn * nx, w)], s[_at(y - kf * ny, h), _at(x - kf * nx, w)]
    span = vn - vf
    own = s[y, x]
    up, down = s[_at(y + ny, h), _at(x + nx, w)] - own, own - s[_at(y - ny, h), _at(x - nx, w)]
    t = (own - vf) / span if span > 0 else 0.0
    if span <= rule.min_range or min(up, down) <= min(0.02 * span, rule.grad_min) or max(up, down) >= 0.5 * span \
            or not rule.place < t < 1 - rule.place:
        return None
    cn, cf = _colour(img, y, x, ny, nx, kn, rule), _colour(img, y, x, -ny, -nx, kf, rule)
    d = cn - cf
    den = d @ d
    score = rule.place_weight * (t - 0.5)
    if den > rule.min_contrast ** 2 * max(cn @ cn, cf @ cf) and den > 1e-20:
        score += min(max((img[y, x] - cf) @ d / den, -0.5), 1.5) - 0.5
    return vn if score > 0 else vf
