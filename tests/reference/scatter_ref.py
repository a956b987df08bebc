"""Slow, obvious float64 NumPy references for the preview renderer's kernels.

Written from the description in docs/renderer.md, not from the Warp code:
loops over sources and rows, coverage of every pixel computed directly as the
overlap of the row interval with the pixel, no difference buffers, no pyramid.
"""

from __future__ import annotations

import itertools
import math

import numpy as np

from .interior_ref import opaque_pixels


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


SAG_PX = 0.25  # a chord end's sag inside a row above which the row is split (docs/renderer.md)
MAX_SUB = 4  # most sub-rows per pixel row


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


def analytic_area(blades: int, curvature: float) -> float:
    """Area of the aperture of unit circumradius: a disc, or the inscribed regular polygon plus,
    for curved blades, one circular segment of radius 1 / curvature on each side."""
    if blades == 0 or curvature >= 1.0:
        return math.pi
    poly = 0.5 * blades * math.sin(2.0 * math.pi / blades)
    if curvature < 1e-4:
        return poly
    big_r = 1.0 / curvature
    theta = 2.0 * math.asin(math.sin(math.pi / blades) / big_r)
    return poly + blades * 0.5 * big_r * big_r * (theta - math.sin(theta))


def rows_area(blades: np.ndarray) -> float:
    """:func:`analytic_area` of the shape given by its blade rows (``Aperture.blade_discs``)."""
    blades = np.asarray(blades, np.float64)
    if len(blades) == 0:
        return math.pi
    return analytic_area(len(blades), 1.0 / blades[0, 3] if blades[0, 3] > 0 else 0.0)


def unit_area(blades: np.ndarray, n: int = 2000) -> float:
    """Area of the aperture of unit circumradius, numerically: point-in-shape counts on an n x n
    grid, refined (64 x 64 per cell) in the cells the shape's outline crosses."""
    c = (np.arange(n) + 0.5) * (2.0 / n) - 1.0
    ins = inside(c[None, :], c[:, None], 1.0, blades)
    edge = np.zeros_like(ins)
    edge[:-1] |= ins[:-1] != ins[1:]
    edge[1:] |= ins[:-1] != ins[1:]
    edge[:, :-1] |= ins[:, :-1] != ins[:, 1:]
    edge[:, 1:] |= ins[:, :-1] != ins[:, 1:]
    cell = (2.0 / n) ** 2
    total = float((ins & ~edge).sum()) * cell
    sub = ((np.arange(64) + 0.5) / 64 - 0.5) * (2.0 / n)
    iy, ix = np.nonzero(edge)
    for i in range(0, len(iy), 2000):
        py = c[iy[i:i + 2000], None, None] + sub[None, :, None]
        px = c[ix[i:i + 2000], None, None] + sub[None, None, :]
        total += float(inside(px, py, 1.0, blades).mean(axis=(1, 2)).sum()) * cell
    return total


def _sub_edges(t0: float, t1: float, n: int, at_top: bool, at_bot: bool) -> list[float]:
    """Edges of the n sub-rows of [t0, t1]: uniform, graded towards a shape end the row holds."""
    u = np.arange(n + 1) / n
    if at_top and at_bot:
        u = 0.5 - 0.5 * np.cos(np.pi * u)
    elif at_top:
        u = 1.0 - np.cos(0.5 * np.pi * u)
    elif at_bot:
        u = np.sin(0.5 * np.pi * u)
    u[-1] = 1.0
    return [t0 + (t1 - t0) * x for x in u]


def footprint(xc: float, yc: float, rho: float, blades: np.ndarray, h: int, w: int,  # noqa: C901
              extent: tuple[float, float] = (-1.0, 1.0), area: float | None = None) -> np.ndarray:
    """Weights a source at (xc, yc) (continuous pixel coords) spreads over an h x w grid (level 0).

    ``extent``: the shape's vertical extent at unit radius (rows outside it are empty);
    ``area``: its area at unit radius (default: :func:`rows_area`).
    A positive ``rho`` (in front of focus) draws the shape point-reflected.

    Discretisation (docs/renderer.md): each pixel row, clipped to the extent, is cut into
    ``n`` sub-rows, ``n = clamp(ceil(sqrt(sag / SAG_PX)), 1, MAX_SUB)`` where the sag is how far
    the chord ends at mid-row lie from the straight line between the ends at the row's top and
    bottom; uniform, or graded towards the shape's end in its first and last row. Each sub-row
    is a span whose ends move linearly from their positions at its top edge to those at its
    bottom edge, shifted by 2/3 of the sag measured at its middle (Simpson's rule: the end's
    mean position is (a0 + 4 a_mid + a1) / 6); a pixel gets the span's area over it (the mean
    over the sub-row's height of the overlap of ``[a(y), b(y)]`` with ``[x, x + 1]``) divided by
    the shape's exact area. What the sub-rows' summed area misses of (or adds to) the exact area
    is added as a uniform span on the centre row's chord, so the source deposits exactly 1.
    """
    if rho > 0 and len(blades):
        # point reflection: a shape S at -S; blades (n, h, R) -> (-n, h, R), extent (a, b) -> (-b, -a)
        flipped = np.asarray(blades, np.float64).copy()
        flipped[:, :2] *= -1
        return footprint(xc, yc, -rho, flipped, h, w, (-extent[1], -extent[0]), area)
    rho = abs(rho)
    out = np.zeros((h, w))
    if rho < 0.5:
        out[int(math.floor(yc)), int(math.floor(xc))] = 1.0
        return out
    if area is None:
        area = rows_area(blades)

    top, bot = yc + extent[0] * rho, yc + extent[1] * rho

    def ch(y: float) -> tuple[float, float]:
        # the extent is padded by 1e-5: at the shape's ends the chord is taken 2e-5 inside
        y = min(max(y, top + 2e-5 * rho), bot - 2e-5 * rho)
        lo, hi = chord(y - yc, rho, blades)
        if hi < lo:
            lo = hi = 0.5 * (lo + hi)
        return xc + lo, xc + hi

    def add_span(k: int, weight: float, a0: float, b0: float, a1: float, b1: float) -> None:
        for x in range(w):
            # overlap of [a, b] with [x, x + 1] is clamp(b) - clamp(a); its mean over the sub-row
            overlap = _mean_clamped(b0, b1, x, x + 1) - _mean_clamped(a0, a1, x, x + 1)
            out[k, x] += weight * overlap

    total = area * rho * rho
    top, bot = yc + extent[0] * rho, yc + extent[1] * rho
    k_top, k_bot = math.floor(top), math.floor(bot)
    inscribed = 0.0
    for k in range(k_top, k_bot + 1):
        t0, t1 = max(k, top), min(k + 1, bot)
        if t1 <= t0:
            continue
        (a0, b0), (am, bm), (a1, b1) = ch(t0), ch(0.5 * (t0 + t1)), ch(t1)
        sag = max(abs(am - 0.5 * (a0 + a1)), abs(bm - 0.5 * (b0 + b1)))
        n = 1 if sag <= SAG_PX else min(MAX_SUB, math.ceil(math.sqrt(sag / SAG_PX)))
        edges = _sub_edges(t0, t1, n, k == k_top, k == k_bot)
        for s0, s1 in itertools.pairwise(edges):
            (a0, b0), (am, bm), (a1, b1) = ch(s0), ch(0.5 * (s0 + s1)), ch(s1)
            # Simpson: each end is the straight ramp between its positions at the sub-row's
            # edges, shifted so its mean position is (a0 + 4 a_mid + a1) / 6
            da, db = (2.0 / 3.0) * (am - 0.5 * (a0 + a1)), (2.0 / 3.0) * (bm - 0.5 * (b0 + b1))
            wsum = (b0 - a0) + (b1 - a1) + 2.0 * (db - da)
            inscribed += (s1 - s0) * 0.5 * wsum
            if 0 <= k < h and wsum > 0:
                add_span(k, (s1 - s0) / total, a0 + da, b0 + db, a1 + da, b1 + db)
    rest = 1.0 - inscribed / total
    a, b = ch(yc)
    if b - a < 1.0:
        a, b = math.floor(xc), math.floor(xc) + 1.0
    add_span(min(max(math.floor(yc), 0), h - 1), rest / (b - a), a, b, a, b)
    return out


def scatter(src: np.ndarray, radius: np.ndarray, blades: np.ndarray,
            extent: tuple[float, float] = (-1.0, 1.0)) -> np.ndarray:
    """Scatter every source ``src[y, x]`` (any channels) with ``radius[y, x]``."""
    h, w = radius.shape
    out = np.zeros(src.shape, np.float64)
    area = rows_area(blades)
    for y in range(h):
        for x in range(w):
            if not np.any(src[y, x]):
                continue
            fp = footprint(x + 0.5, y + 0.5, float(radius[y, x]), blades, h, w, extent, area)  # signed
            out += fp[..., None] * src[y, x][None, None, :]
    return out


def layered(image: np.ndarray, signed_coc: np.ndarray, edges: np.ndarray, blades: np.ndarray,
            extent: tuple[float, float] = (-1.0, 1.0), border: bool = True) -> np.ndarray:
    """Layered preview without fill, pyramid or tile skipping (docs/renderer.md, "compositing rule").

    Border rule (``border=True``): the frame is extended by its edge pixels (colour and signed CoC
    replicated outwards) on each side as far as the largest CoC on that side reaches, rendered, and cropped;
    not when that CoC exceeds half the frame's longer side (then only the final division applies).
    Layer ``i`` holds the pixels with ``edges[i] <= s < edges[i + 1]``; each layer scatters (RGB, 1) of its own
    pixels; layers are composited back to front with opacity ``min(coverage, 1)`` (1 at the layer's own pixels whose
    cone meets no farther surface, ``interior_ref.opaque_pixels``) and colour ``sum / coverage``; the result is
    divided by the total opacity.
    """
    if border:
        rims = (signed_coc[0], signed_coc[-1], signed_coc[:, 0], signed_coc[:, -1])
        radii = [float(np.abs(rim).max()) for rim in rims]
        if max(radii) <= 0.5 * max(signed_coc.shape):
            t, b, l, r = (math.ceil(x) + 1 if x >= 0.5 else 0 for x in radii)
            if t + b + l + r:
                big = layered(np.pad(image, ((t, b), (l, r), (0, 0)), mode="edge"),
                              np.pad(signed_coc, ((t, b), (l, r)), mode="edge"), edges, blades, extent, border=False)
                return big[t:t + image.shape[0], l:l + image.shape[1]]
    ids = np.searchsorted(edges, signed_coc, side="right") - 1
    h, w, _ = image.shape
    whole = opaque_pixels(ids, np.zeros((h, w), bool), signed_coc)
    acc = np.zeros((h, w, 3))
    opacity = np.zeros((h, w))
    for lid in sorted(set(ids.ravel().tolist())):
        member = ids == lid
        src = np.concatenate([image * member[..., None], member[..., None].astype(np.float64)], axis=2)
        lay = scatter(src, signed_coc * member, blades, extent)
        cov = lay[..., 3]
        alpha = np.where(whole & member & (cov > 1e-6), 1.0, np.minimum(cov, 1.0))
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


def level_of(r: float, r0: float, n_levels: int) -> int:
    """Pyramid level of a source of radius r: the first l with r / 2^l <= r0 (at most n_levels - 1)."""
    lev = 0
    while r / 2 ** lev > r0 and lev < n_levels - 1:
        lev += 1
    return lev


def radiance_pyramid(src: np.ndarray, coc: np.ndarray, inside: np.ndarray, r0: float, n_levels: int
                     ) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """(means, pixels, levels present) of radiance pyramid levels 1 .. n_levels - 1, by plain loops.

    A level-k cell's mean of the sources (premultiplied RGB, coverage) over the pixels it holds (cut by the array's
    edge), sources outside ``inside`` (the layer's support) counting as zero; its pixels; and as bits, the pyramid
    levels l >= 1 (bit l) from that of the smallest to that of the largest radius ``|coc| >= 0.5`` of a level-1 cell's
    sources with coverage (every level one of them scatters on, and those between), a coarser cell's those of its
    2 x 2 cells."""
    h, w = coc.shape
    out = []
    for k in range(1, n_levels):
        s = 2 ** k
        hk, wk = -(-h // s), -(-w // s)
        means, pixels, bits = np.zeros((hk, wk, 4)), np.zeros((hk, wk)), np.zeros((hk, wk), int)
        lo, hi = np.full((hk, wk), n_levels, int), np.full((hk, wk), -1, int)  # levels of its radii
        for cy in range(hk):
            for cx in range(wk):
                for y in range(cy * s, min(h, cy * s + s)):
                    for x in range(cx * s, min(w, cx * s + s)):
                        pixels[cy, cx] += 1
                        if not inside[y, x]:
                            continue
                        means[cy, cx] += src[y, x]
                        r = abs(float(coc[y, x]))
                        if src[y, x, 3] != 0 and r >= 0.5:
                            lv = level_of(r, r0, n_levels)
                            lo[cy, cx], hi[cy, cx] = min(lo[cy, cx], lv), max(hi[cy, cx], lv)
                means[cy, cx] /= pixels[cy, cx]
                if k == 1:
                    for lv in range(max(1, lo[cy, cx]), hi[cy, cx] + 1):
                        bits[cy, cx] |= 1 << lv
                else:  # the levels of its 2 x 2 cells'
                    finer = out[-1][2]
                    bits[cy, cx] = np.bitwise_or.reduce(finer[2 * cy:2 * cy + 2, 2 * cx:2 * cx + 2], axis=None)
        out.append((means, pixels, bits))
    return out


def salient(src: np.ndarray, coc: np.ndarray, r0: float, n_levels: int, visible: float, floor: float
            ) -> tuple[np.ndarray, np.ndarray]:
    """(score, routed mask) of the salient-source routing (docs/renderer.md), by plain loops.

    For a source of level l >= 1: the mean premultiplied radiance m and coverage a_m over the
    pixels of the 3 x 3 level-l cells around its own (cut to the array), the excess
    e = q - a m / a_m, score = e - visible max(m, floor) pi r^2 where positive. Then in each
    level-l cell, the max(1, 2^(l-1)) best-scored salient sources of level l (ties: row order).
    """
    h, w = coc.shape
    q = src[..., :3].mean(-1)
    a = src[..., 3]
    score = np.zeros((h, w))
    lev = np.zeros((h, w), int)
    for y in range(h):
        for x in range(w):
            r = abs(float(coc[y, x]))
            if a[y, x] == 0 or r < 0.5:
                continue
            lv = lev[y, x] = level_of(r, r0, n_levels)
            if lv == 0:
                continue
            s = 2 ** lv
            cy, cx = y // s, x // s
            ys = slice(max(0, (cy - 1) * s), min(h, (cy + 2) * s))
            xs = slice(max(0, (cx - 1) * s), min(w, (cx + 2) * s))
            m, a_m = q[ys, xs].mean(), a[ys, xs].mean()
            e = q[y, x] - a[y, x] * m / a_m
            score[y, x] = max(0.0, e - visible * max(m, floor) * math.pi * r * r)
    routed = np.zeros((h, w), bool)
    for lv in range(1, n_levels):
        s = 2 ** lv
        for cy in range(0, h, s):
            for cx in range(0, w, s):
                cand = [(-score[y, x], y, x) for y in range(cy, min(h, cy + s)) for x in range(cx, min(w, cx + s))
                        if score[y, x] > 0 and lev[y, x] == lv]
                for _, y, x in sorted(cand)[: max(1, s // 2)]:
                    routed[y, x] = True
    return score, routed


def clusters(src: np.ndarray, coc: np.ndarray, routed: np.ndarray, r0: float, n_levels: int, visible: float,  # noqa: C901
             floor: float) -> tuple[np.ndarray, list[tuple[float, float, float, np.ndarray]]]:
    """(member mask, cluster sources) of the extended-light gathering (docs/renderer.md), by plain loops.

    In each level-l cell (l >= 1), the sources of level l not ``routed`` alone whose excess over the 3 x 3
    cells' mean, e = q - a m / a_m, is positive are the cluster. When their summed excess E beats
    visible max(m, floor) pi s^2 (s: the e-weighted mean CoC radius), each member's light beyond its coverage
    of the other sources' local colour goes into the source of its block of 2^b px, b = max(1, l - 2): at the
    members' e-weighted centroid (pixel centres) rounded to 1/256 px, with their e-weighted mean CoC radius,
    signed as their e-weighted mean signed CoC (near and far members in one layer keep their radius).
    Returns the members and the sources as (x, y, signed CoC, RGB).
    """
    h, w = coc.shape
    q = src[..., :3].mean(-1)
    members = np.zeros((h, w), bool)
    sources = []
    for lv in range(1, n_levels):
        s = 2 ** lv
        for cy in range(0, h, s):
            for cx in range(0, w, s):
                ys = slice(max(0, cy - s), min(h, cy + 2 * s))
                xs = slice(max(0, cx - s), min(w, cx + 2 * s))
                total = src[ys, xs].sum(axis=(0, 1))
                n = src[ys, xs].shape[0] * src[ys, xs].shape[1]
                m, a_m = total[:3].mean() / n, total[3] / n
                cell = []
                for y in range(cy, min(h, cy + s)):
                    for x in range(cx, min(w, cx + s)):
                        r = abs(float(coc[y, x]))
                        if routed[y, x] or src[y, x, 3] == 0 or r < 0.5 or level_of(r, r0, n_levels) != lv:
                            continue
                        e = q[y, x] - src[y, x, 3] * m / a_m
                        if e > 0:
                            rest = total - src[y, x]
                            base = np.zeros(3) if rest[3] <= 1e-6 * n else np.maximum(rest[:3], 0) * src[y, x, 3] / rest[3]
                            cell.append((y, x, e, src[y, x, :3] - base))
                if not cell:
                    continue
                e_sum = sum(c[2] for c in cell)
                s_mean = sum(c[2] * abs(coc[c[0], c[1]]) for c in cell) / e_sum
                if e_sum - visible * max(m, floor) * math.pi * s_mean ** 2 <= 0:
                    continue
                b = 2 ** max(1, lv - 2)
                blocks = {}
                for y, x, e, light in cell:
                    members[y, x] = True
                    blocks.setdefault((y // b, x // b), []).append((y, x, e, light))
                for (by, bx), part in blocks.items():
                    pe = sum(c[2] for c in part)
                    fx = sum(c[2] * (c[1] - bx * b + 0.5) for c in part) / pe  # within the block,
                    fy = sum(c[2] * (c[0] - by * b + 0.5) for c in part) / pe  # rounded to 1/256 px
                    radius = sum(c[2] * abs(coc[c[0], c[1]]) for c in part) / pe
                    sign = -1.0 if sum(c[2] * coc[c[0], c[1]] for c in part) < 0 else 1.0
                    sources.append((bx * b + math.floor(fx * 256 + 0.5) / 256, by * b + math.floor(fy * 256 + 0.5) / 256,
                                    sign * radius, sum(c[3] for c in part)))
    return members, sources


def sharp_footprint(xc: float, yc: float, rho: float, blades: np.ndarray, h: int, w: int,
                    extent: tuple[float, float] = (-1.0, 1.0), area: float | None = None) -> np.ndarray:
    """Weights a source at (xc, yc) spreads over an h x w grid with the pyramid levels' cheap rule (docs/renderer.md,
    "Large radii"): each pixel row the shape covers (clipped to its extent) holds one span, the chord at the row
    part's mid-height, of that part's height; a pixel gets the span's overlap with it, over the shape's exact area;
    what the rows miss of that area goes on the centre row's chord (at least one pixel wide). Spans are clipped to
    the grid's columns. A positive ``rho`` draws the shape point-reflected."""
    if rho > 0 and len(blades):
        flipped = np.asarray(blades, np.float64).copy()
        flipped[:, :2] *= -1
        return sharp_footprint(xc, yc, -rho, flipped, h, w, (-extent[1], -extent[0]), area)
    rho = abs(rho)
    area = rows_area(blades) if area is None else area
    out = np.zeros((h, w))
    top, bot = yc + extent[0] * rho, yc + extent[1] * rho

    def add(k: int, weight: float, a: float, b: float) -> None:
        a, b = min(max(a, 0.0), w), min(max(b, 0.0), w)  # clipped to the grid
        for x in range(w):
            out[k, x] += weight * max(0.0, min(b, x + 1) - max(a, x))

    covered = 0.0
    for k in range(math.floor(top), math.floor(bot) + 1):
        t0, t1 = max(k, top), min(k + 1, bot)
        if t1 <= t0:
            continue
        lo, hi = chord(0.5 * (t0 + t1) - yc, rho, blades)
        if hi <= lo:
            continue
        covered += (t1 - t0) * (hi - lo)
        if 0 <= k < h:
            add(k, (t1 - t0) / (area * rho * rho), xc + lo, xc + hi)
    lo, hi = chord(0.0, rho, blades)
    a, b = xc + lo, xc + hi
    if b - a < 1.0:
        a, b = math.floor(xc), math.floor(xc) + 1.0
    add(min(max(math.floor(yc), 0), h - 1), (1.0 - covered / (area * rho * rho)) / (b - a), a, b)
    return out


def _merged(part: list, src: np.ndarray, coc: np.ndarray, cy: int, cx: int, s: int, split: float) -> list:
    """One bin's sources of a cell as one or two merged sources (:func:`merged_sources`)."""
    total = sum(src[p].astype(np.float64) for p in part)
    c = sum(float(src[p][3]) * float(coc[p]) for p in part) / total[3]

    def centroid(k: int) -> tuple[float, float]:  # channel k's, within the cell, on the 1/256 px grid
        cw = [float(src[p][k]) for p in part]
        return tuple(math.floor(sum(wi * (p[i] - o + 0.5) for wi, p in zip(cw, part)) / sum(cw) * 256 + 0.5) / 256
                     for i, o in ((1, cx), (0, cy)))

    a = centroid(3)
    cents = [centroid(k) if total[k] > 0 else a for k in range(3)]
    apart = [max(abs(q[0] - a[0]), abs(q[1] - a[1])) for q in cents]
    if max(apart) <= split * s:
        return [(cx + a[0], cy + a[1], c, total)]
    far = cents[int(np.argmax(apart))]
    moved = np.array([max(abs(q[0] - far[0]), abs(q[1] - far[1])) < d for q, d in zip(cents, apart)] + [False])
    return [(cx + far[0], cy + far[1], c, np.where(moved, total, 0.0)),
            (cx + a[0], cy + a[1], c, np.where(moved, 0.0, total))]


def merged_sources(src: np.ndarray, coc: np.ndarray, r0: float, n_levels: int, lev: int, tol: float,
                   groups: int = 4, split: float = 0.0625) -> list[tuple[float, float, float, np.ndarray]]:
    """The sources of pyramid level ``lev`` >= 1 merged per cell of 2^lev px (docs/renderer.md), by plain loops:
    the cell's sources of that level (coverage > 0, radius >= 0.5) are binned by signed CoC in bins of ``tol`` from
    the smallest (the last bin taking the largest); at most ``groups`` bins, each a source of the summed value at
    the coverage-weighted centroid (pixel centres, within the cell, rounded to 1/256 px) and mean signed CoC, or,
    where a colour channel's centroid lies farther than ``split`` of the cell from it (in x or y), two sources: the
    channels whose centroids lie nearer the farthest one's at that one, the others and the coverage at the
    coverage's; more bins: every source alone. Returns (x, y, signed CoC, value) in pixels of level 0."""
    h, w = coc.shape
    s = 2 ** lev
    out = []
    for cy in range(0, h, s):
        for cx in range(0, w, s):
            cell = [(y, x) for y in range(cy, min(h, cy + s)) for x in range(cx, min(w, cx + s))
                    if src[y, x, 3] != 0 and abs(coc[y, x]) >= 0.5 and level_of(abs(coc[y, x]), r0, n_levels) == lev]
            if not cell:
                continue
            lo, hi = min(coc[p] for p in cell), max(coc[p] for p in cell)
            n_bins = int((hi - lo) / tol) + 1
            if n_bins > groups:
                out += [(x + 0.5, y + 0.5, float(coc[y, x]), src[y, x].astype(np.float64)) for y, x in cell]
                continue
            for b in range(n_bins):
                part = [p for p in cell if min(int((coc[p] - lo) / tol), n_bins - 1) == b]
                if part:
                    out += _merged(part, src, coc, cy, cx, s, split)
    return out


def over(layer: np.ndarray, acc: np.ndarray, whole: np.ndarray | None = None) -> np.ndarray:
    """One scattered layer (sum of premultiplied RGB, sum of coverage) over the accumulator (RGB, opacity)
    (docs/renderer.md, "compositing rule"): opacity min(coverage, 1), 1 where ``whole`` (the layer covers the pixel
    whole: ``interior_ref.opaque_pixels`` at the layer's own pixels), colour normalised by the coverage; where the
    coverage is at most 1e-6 the accumulator stays."""
    cov = layer[..., 3:4].astype(np.float64)
    alpha = np.minimum(cov, 1.0)
    if whole is not None:
        alpha = np.where(whole[..., None], 1.0, alpha)
    colour = layer[..., :3] / np.maximum(cov, 1e-30)
    out = np.concatenate([colour * alpha + (1 - alpha) * acc[..., :3], alpha + (1 - alpha) * acc[..., 3:4]], -1)
    return np.where(cov > 1e-6, out, acc)
