"""Slow, obvious float64 NumPy references for the preview renderer's kernels.

Written from the description in docs/renderer.md, not from the Warp code:
loops over sources and rows, coverage of every pixel computed directly as the
overlap of the row interval with the pixel, no difference buffers, no pyramid.
"""

from __future__ import annotations

import math

import numpy as np


def chord(y: float, rho: float, blades: np.ndarray) -> tuple[float, float]:
    """Interval of the aperture of circumradius ``rho`` on the horizontal line at height ``y``."""
    if rho * rho - y * y <= 0:
        return 0.0, 0.0
    lo, hi = -math.sqrt(rho * rho - y * y), math.sqrt(rho * rho - y * y)
    for nx, ny, h, big_r in np.asarray(blades, np.float64):
        if big_r == 0:
            # half-plane nx*x + ny*y <= h*rho
            rhs = h * rho - ny * y
            if abs(nx) < 1e-7:
                if rhs < 0:
                    return 0.0, 0.0
            elif nx > 0:
                hi = min(hi, rhs / nx)
            else:
                lo = max(lo, rhs / nx)
        else:
            cx, cy, rr = h * rho * nx, h * rho * ny, big_r * rho
            q = rr * rr - (y - cy) ** 2
            if q <= 0:
                return 0.0, 0.0
            lo, hi = max(lo, cx - math.sqrt(q)), min(hi, cx + math.sqrt(q))
    return lo, hi


def inside(px: np.ndarray, py: np.ndarray, rho: float, blades: np.ndarray) -> np.ndarray:
    """Point-in-aperture test (for exact-coverage checks by supersampling)."""
    ok = px * px + py * py <= rho * rho
    for nx, ny, h, big_r in np.asarray(blades, np.float64):
        if big_r == 0:
            ok &= nx * px + ny * py <= h * rho
        else:
            ok &= (px - h * rho * nx) ** 2 + (py - h * rho * ny) ** 2 <= (big_r * rho) ** 2
    return ok


def footprint(xc: float, yc: float, rho: float, blades: np.ndarray, h: int, w: int,
              extent: tuple[float, float] = (-1.0, 1.0)) -> np.ndarray:
    """Weights a source at (xc, yc) (continuous pixel coords) spreads over an h x w grid (level 0).

    ``extent``: the shape's vertical extent at unit radius (rows outside it are empty).
    A positive ``rho`` (in front of focus) draws the shape point-reflected.
    """
    if rho > 0 and len(blades):
        # point reflection: a shape S at -S; blades (n, h, R) -> (-n, h, R), extent (a, b) -> (-b, -a)
        flipped = np.asarray(blades, np.float64).copy()
        flipped[:, :2] *= -1
        return footprint(xc, yc, -rho, flipped, h, w, (-extent[1], -extent[0]))
    rho = abs(rho)
    out = np.zeros((h, w))
    if rho < 0.5:
        out[int(math.floor(yc)), int(math.floor(xc))] = 1.0
        return out
    rows = []
    n_sub = min(4, max(1, math.ceil(4.0 / rho)))
    top, bot = yc + extent[0] * rho, yc + extent[1] * rho
    for k in range(math.floor(top), math.floor(bot) + 1):
        for j in range(n_sub):
            t0, t1 = max(k + j / n_sub, top), min(k + (j + 1) / n_sub, bot)
            if t1 <= t0:
                continue
            lo, hi = chord(0.5 * (t0 + t1) - yc, rho, blades)
            if hi > lo:
                rows.append((k, t1 - t0, xc + lo, xc + hi))
    total = sum(hk * (b - a) for _, hk, a, b in rows)
    for k, hk, a, b in rows:
        if not 0 <= k < h:
            continue
        for x in range(w):
            overlap = min(b, x + 1, w) - max(a, x, 0)
            if overlap > 0:
                out[k, x] += hk * overlap / total
    return out


def scatter(src: np.ndarray, radius: np.ndarray, blades: np.ndarray,
            extent: tuple[float, float] = (-1.0, 1.0)) -> np.ndarray:
    """Scatter every source ``src[y, x]`` (any channels) with ``radius[y, x]``."""
    h, w = radius.shape
    out = np.zeros(src.shape, np.float64)
    for y in range(h):
        for x in range(w):
            if not np.any(src[y, x]):
                continue
            fp = footprint(x + 0.5, y + 0.5, float(radius[y, x]), blades, h, w, extent)  # signed
            out += fp[..., None] * src[y, x][None, None, :]
    return out


def layered(image: np.ndarray, signed_coc: np.ndarray, edges: np.ndarray, blades: np.ndarray,
            extent: tuple[float, float] = (-1.0, 1.0)) -> np.ndarray:
    """Layered preview without fill, pyramid or tile skipping (docs/renderer.md, "compositing rule").

    Layer ``i`` holds the pixels with ``edges[i] <= s < edges[i + 1]``; each layer scatters (RGB, 1) of its own
    pixels; layers are composited back to front with opacity ``min(coverage, 1)``
    and colour ``sum / coverage``; the result is divided by the total opacity.
    """
    ids = np.searchsorted(edges, signed_coc, side="right") - 1
    h, w, _ = image.shape
    acc = np.zeros((h, w, 3))
    opacity = np.zeros((h, w))
    for lid in sorted(set(ids.ravel().tolist())):
        member = ids == lid
        src = np.concatenate([image * member[..., None], member[..., None].astype(np.float64)], axis=2)
        lay = scatter(src, signed_coc * member, blades, extent)
        cov = lay[..., 3]
        alpha = np.minimum(cov, 1.0)
        colour = np.where(cov[..., None] > 1e-6, lay[..., :3] / np.maximum(cov, 1e-12)[..., None], 0.0)
        acc = colour * alpha[..., None] + (1 - alpha[..., None]) * acc
        opacity = alpha + (1 - alpha) * opacity
    return np.where(opacity[..., None] > 1e-4, acc / np.maximum(opacity, 1e-12)[..., None], image)
