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


SAG_PX = 0.02  # largest sag of a chord end inside a sub-row (docs/renderer.md)
MAX_SUB = 32  # most sub-rows per pixel row


def _mean_clamped(p0: float, p1: float, lo: float, hi: float) -> float:
    """Mean over u in [0, 1] of clamp(p0 + (p1 - p0) u, lo, hi), in closed form."""
    if abs(p1 - p0) < 1e-4:
        return min(max(0.5 * (p0 + p1), lo), hi)

    def g(p: float) -> float:  # an antiderivative of clamp(p, lo, hi)
        if p <= lo:
            return lo * p
        if p <= hi:
            return lo * lo + 0.5 * (p * p - lo * lo)
        return lo * lo + 0.5 * (hi * hi - lo * lo) + hi * (p - hi)

    return (g(p1) - g(p0)) / (p1 - p0)


def footprint(xc: float, yc: float, rho: float, blades: np.ndarray, h: int, w: int,
              extent: tuple[float, float] = (-1.0, 1.0)) -> np.ndarray:
    """Weights a source at (xc, yc) (continuous pixel coords) spreads over an h x w grid (level 0).

    ``extent``: the shape's vertical extent at unit radius (rows outside it are empty).
    A positive ``rho`` (in front of focus) draws the shape point-reflected.

    Discretisation (docs/renderer.md): each pixel row, clipped to the extent, is cut into
    ``n`` equal sub-rows, ``n = clamp(ceil(sqrt(sag / SAG_PX)), 1, MAX_SUB)`` where the sag is
    how far the chord ends at mid-row lie from the straight line between the ends at the row's
    top and bottom. Each sub-row is the trapezoid between the chords at its top and bottom; a
    pixel gets the trapezoid's area over it, computed here as the mean over the sub-row's height
    of the overlap of ``[a(y), b(y)]`` with ``[x, x + 1]`` (ends linear in y). The weights are
    divided by the summed trapezoid area of the whole shape, inside the image or not.
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

    def ch(y: float) -> tuple[float, float]:
        lo, hi = chord(y - yc, rho, blades)
        if hi < lo:
            lo = hi = 0.5 * (lo + hi)
        return xc + lo, xc + hi

    top, bot = yc + extent[0] * rho, yc + extent[1] * rho
    traps = []  # (row, height, (a0, b0), (a1, b1))
    for k in range(math.floor(top), math.floor(bot) + 1):
        t0, t1 = max(k, top), min(k + 1, bot)
        if t1 <= t0:
            continue
        (a0, b0), (am, bm), (a1, b1) = ch(t0), ch(0.5 * (t0 + t1)), ch(t1)
        sag = max(abs(am - 0.5 * (a0 + a1)), abs(bm - 0.5 * (b0 + b1)))
        n = min(MAX_SUB, max(1, math.ceil(math.sqrt(sag / SAG_PX))))
        for j in range(n):
            s0, s1 = t0 + j * (t1 - t0) / n, t0 + (j + 1) * (t1 - t0) / n
            traps.append((k, s1 - s0, ch(s0), ch(s1)))
    total = sum(hk * 0.5 * ((e0[1] - e0[0]) + (e1[1] - e1[0])) for _, hk, e0, e1 in traps)
    for k, hk, (a0, b0), (a1, b1) in traps:
        if not 0 <= k < h or (b0 - a0) + (b1 - a1) <= 0:
            continue
        for x in range(w):
            # overlap of [a, b] with [x, x + 1] is clamp(b) - clamp(a); its mean over the sub-row
            overlap = _mean_clamped(b0, b1, x, x + 1) - _mean_clamped(a0, a1, x, x + 1)
            if overlap != 0:
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


def area_coverage(xc: float, yc: float, rho: float, blades: np.ndarray, h: int, w: int,
                  n_super: int = 64) -> np.ndarray:
    """The analytic shape integrated over every pixel of an h x w grid, normalised to sum 1 over the plane.

    Shape of circumradius ``|rho|`` centred at ``(xc, yc)`` (continuous pixel coordinates); a
    positive ``rho`` (in front of focus) is the point reflection. Pixels of the shape's bounding
    box are classified on a 4 x 4 grid; those not all in or all out (and their neighbours) are
    supersampled ``n_super`` x ``n_super``. The normalisation is over the whole bounding box,
    inside the image or not, so a shape cut by the frame keeps only what falls inside.
    """
    sgn = -1.0 if rho > 0 else 1.0
    rho = abs(rho)

    def grid(ys: np.ndarray, xs: np.ndarray, n: int) -> np.ndarray:
        sub = (np.arange(n) + 0.5) / n
        py = (ys[:, None] + sub[None, :]).ravel()
        px = (xs[:, None] + sub[None, :]).ravel()
        c = inside(sgn * (px[None, :] - xc), sgn * (py[:, None] - yc), rho, blades)
        return c.reshape(len(ys), n, len(xs), n).mean(axis=(1, 3))

    y0, y1 = int(math.floor(yc - rho)) - 1, int(math.ceil(yc + rho)) + 2
    x0, x1 = int(math.floor(xc - rho)) - 1, int(math.ceil(xc + rho)) + 2
    ys, xs = np.arange(y0, y1, dtype=np.float64), np.arange(x0, x1, dtype=np.float64)
    fine = np.concatenate([grid(ys[i:i + 64], xs, 4) for i in range(0, len(ys), 64)])
    mixed = np.pad((fine > 0) & (fine < 1), 1)
    mixed = mixed[1:-1, 1:-1] | mixed[:-2, 1:-1] | mixed[2:, 1:-1] | mixed[1:-1, :-2] | mixed[1:-1, 2:]
    for iy in np.unique(np.nonzero(mixed)[0]):
        cols = np.flatnonzero(mixed[iy])
        fine[iy, cols] = grid(ys[iy:iy + 1], xs[cols], n_super)[0]
    fine /= fine.sum()
    out = np.zeros((h, w))
    oy0, oy1, ox0, ox1 = max(0, y0), min(h, y1), max(0, x0), min(w, x1)
    if oy1 > oy0 and ox1 > ox0:
        out[oy0:oy1, ox0:ox1] = fine[oy0 - y0:oy1 - y0, ox0 - x0:ox1 - x0]
    return out
