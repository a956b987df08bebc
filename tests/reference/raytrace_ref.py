"""Slow, obvious float64 NumPy layered thin-lens ray tracer (loops over pixels, cells and layers).

Same estimator as the Warp kernel: one ray per aperture cell (the cell table
of ``bokehray.levels.quadrature``), each layer's texture averaged over the cell's
footprint box by summing the overlap of the box with every texel it touches
(texture constant over each texel, clamp-to-edge outside), composited nearest
first. Convergence to the exact image is tested separately.
"""

from __future__ import annotations

import math

import numpy as np


def bilinear(tex: np.ndarray, px: float, py: float) -> np.ndarray:
    """Bilinear lookup between texel centres, clamped to the edge (the PISA oracle's sampler)."""
    h, w = tex.shape[:2]
    fx = min(max(px - 0.5, 0.0), w - 1.0)
    fy = min(max(py - 0.5, 0.0), h - 1.0)
    x0, y0 = int(math.floor(fx)), int(math.floor(fy))
    x1, y1 = min(x0 + 1, w - 1), min(y0 + 1, h - 1)
    tx, ty = fx - x0, fy - y0
    top = tex[y0, x0] * (1 - tx) + tex[y0, x1] * tx
    bot = tex[y1, x0] * (1 - tx) + tex[y1, x1] * tx
    return top * (1 - ty) + bot * ty


def box_mean(tex: np.ndarray, cx: float, cy: float, hx: float, hy: float) -> np.ndarray:
    """Mean of ``tex`` (H x W x C, constant per texel, border continued) over ``[cx +- hx] x [cy +- hy]``."""
    h, w = tex.shape[:2]
    x0, x1, y0, y1 = cx - hx, cx + hx, cy - hy, cy + hy
    acc = np.zeros(tex.shape[2])
    for j in range(math.floor(y0), math.ceil(y1)):
        oy = min(y1, j + 1) - max(y0, j)
        if oy <= 0:
            continue
        for i in range(math.floor(x0), math.ceil(x1)):
            ox = min(x1, i + 1) - max(x0, i)
            if ox > 0:
                acc += tex[min(max(j, 0), h - 1), min(max(i, 0), w - 1)] * (ox * oy)
    return acc / ((x1 - x0) * (y1 - y0))


def trace(layers: list[tuple[np.ndarray, tuple[float, float, float]]], k: float, d_f: float,  # noqa: C901
          spp, aperture=None) -> np.ndarray:
    """Plane layers only, nearest first: ``(rgba straight-alpha H x W x 4, (a, b, c))``; images of
    at most 16 x 16 px (one tile of the kernel's content grid: every layer with content reaches
    every pixel).

    ``spp``: an int (that many rays everywhere, as ``RaytraceOptions(samples_per_px2=1e6,
    max_spp=spp, min_spp=spp)``), a ``RaytraceOptions``, or an ``(n, 5)`` array of cells
    ``(ux, uy, hx, hy, weight)`` used at every pixel. Otherwise a pixel's cells are those the
    launcher picks for the largest CoC among layers with content (``bokehray.levels.raytrace_launch``,
    tested on its own); a cell with ``hx = 0`` is the centre ray, whose lookup is a 1 px box
    (bilinear). For a ray from pixel centre ``x`` through ``u`` the hit on the plane
    ``d = g.p + c`` solves ``p = x + k (g.p + c - d_f) u``.
    """
    import bokehray as br
    from bokehray.levels.raytrace_launch import choose_levels, strip_range

    h, w = layers[0][0].shape[:2]
    assert h <= 16 and w <= 16
    aperture = aperture or br.Aperture()
    yy, xx = np.mgrid[0:h, 0:w] + 0.5
    if isinstance(spp, np.ndarray):
        pixel_cells = lambda y, x: spp  # noqa: E731
    else:
        opts = br.RaytraceOptions(samples_per_px2=1e6, max_spp=spp, min_spp=spp) if isinstance(spp, int) else spp
        r = np.zeros((h, w))
        for tex, (a, b, c) in layers:
            if (tex[..., 3] > 0).any():
                r = np.maximum(r, np.abs(k * (a * xx + b * yy + c - d_f)))
        levels, table, _ = choose_levels(r.astype(np.float32), aperture, opts.samples_per_px2, strip_range(opts),
                                         opts.max_spp)
        rows = np.concatenate([table.boxes, table.weights[:, None]], axis=1).astype(np.float64)

        def pixel_cells(y, x):
            lv = levels[y, x]
            return rows[table.offsets[lv] : table.offsets[lv + 1]]

    # premultiplied colour: a straight-alpha texel of alpha 0 has no colour to lend
    layers = [(np.concatenate([t[..., :3] * t[..., 3:], t[..., 3:]], axis=2).astype(np.float64), p)
              for t, p in layers]
    out = np.zeros((h, w, 4))
    for y in range(h):
        for x in range(w):
            acc = np.zeros(4)
            for ux, uy, hx, hy, weight in pixel_cells(y, x):
                u = np.array([ux, uy])
                colour, trans = np.zeros(3), 1.0
                for tex, (a, b, c) in layers:
                    g = np.array([a, b])
                    m = np.eye(2) - k * np.outer(u, g)  # (I - k u g^T) p = x + k (c - d_f) u
                    if abs(np.linalg.det(m)) < 1e-6:
                        continue  # the ray grazes the plane: no hit
                    p = np.linalg.solve(m, np.array([x + 0.5, y + 0.5]) + k * (c - d_f) * u)
                    rad = abs(k * (g @ p + c - d_f))
                    if hx > 0:
                        bx, by = max(rad * hx, 1e-3), max(rad * hy, 1e-3)
                    else:
                        bx = by = 0.5
                    s = box_mean(tex, p[0], p[1], bx, by)
                    colour += trans * s[:3]
                    trans *= 1.0 - min(max(s[3], 0.0), 1.0)
                acc += weight * np.concatenate([colour, [1.0 - trans]])
            out[y, x] = acc
    return out


def disc_convolution(tex: np.ndarray, r: float, inside, sub: int = 16) -> np.ndarray:
    """Exact thin-lens image of one fronto-parallel layer behind focus: ``tex`` (constant per texel,
    border continued) convolved with the aperture of radius ``r``, at pixel centres.

    ``inside(ux, uy)`` is the aperture's indicator at unit circumradius; the kernel weight of a
    texel offset is the share of the texel inside the aperture (``sub`` x ``sub`` points per texel).
    """
    big_r = int(math.ceil(r)) + 1
    o = (np.arange(sub) + 0.5) / sub - 0.5
    offs = np.arange(-big_r, big_r + 1)
    pos = (offs[:, None] + o[None, :]).ravel() / r
    ker = inside(pos[None, :], pos[:, None]).reshape(2 * big_r + 1, sub, 2 * big_r + 1, sub).mean(axis=(1, 3))
    ker = ker / ker.sum()
    h, w = tex.shape[:2]
    pad = np.pad(tex.astype(np.float64), ((big_r, big_r), (big_r, big_r), (0, 0)), mode="edge")
    out = np.zeros((h, w, tex.shape[2]))
    # a pixel at x sees texel x + s u with s = -r (behind focus): texel offset (pixel - texel)/r in the aperture
    for dy in range(-big_r, big_r + 1):
        for dx in range(-big_r, big_r + 1):
            wgt = ker[dy + big_r, dx + big_r]
            if wgt:
                out += wgt * pad[big_r - dy : big_r - dy + h, big_r - dx : big_r - dx + w]
    return out


def inside(aperture):
    """Indicator of the unit-circumradius aperture, from its blade constraints (independent of the chords)."""
    rows = aperture.blade_discs().astype(np.float64)

    def f(x, y):
        ok = x * x + y * y < 1.0
        for nx, ny, h, big_r in rows:
            if big_r == 0.0:
                ok = ok & (nx * x + ny * y < h)
            else:
                ok = ok & ((x - h * nx) ** 2 + (y - h * ny) ** 2 < big_r * big_r)
        return ok

    return f
