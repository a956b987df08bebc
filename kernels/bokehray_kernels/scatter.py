"""Row-span scatter of aperture-shaped CoCs on a radius pyramid, and layer compositing.

Each source pixel spreads a ``vec4`` (premultiplied RGB, coverage) over its
aperture shape. The shape is cut into pixel rows; each row is one interval
``[a, b]`` deposited into a per-row *difference* buffer with four adds
(antialiased, fractional ends), and a prefix sum along each row turns the
differences into per-pixel coverage. A source therefore costs O(rows), not
O(r^2). Sources whose radius exceeds ``r0`` are scattered on a coarser level
``l`` (pixel size ``2^l``) where their radius is at most ``r0``, so the cost per
source is bounded by O(r0) whatever its radius; ``resolve_levels_kernel``
brings the levels back to full resolution (bilinear, energy preserving).

Each row ``k`` is split into ``n = clamp(ceil(4 / rho), 1, 4)`` equal sub-rows;
each sub-row gets the weight ``h * (b - a) / sum over all sub-rows of h * (b - a)``
where ``h`` is the part of the sub-row inside the shape's vertical extent and the
chord ``[a, b]`` is taken at the middle of that part (midpoint rule). The normalisation
is over the whole shape, inside the image or not, so every source deposits
exactly its value (minus what falls outside the image), at every radius,
including radii below one pixel.
"""

import warp as wp

from .aperture import chord
from .sampling import bilinear_taps

wp.set_module_options({"enable_backward": False})

MAX_LEVELS = 6
"""Pyramid levels 0..5: radii up to ``r0 * 32`` cost O(r0) per source."""

SAG_PX = wp.constant(0.02)
"""Largest sag [px] of a chord end inside a sub-row (before the ``MAX_SUB`` cap)."""

MAX_SUB = wp.constant(32)
"""Most sub-rows per pixel row (reached only next to the poles of a shape)."""


@wp.func
def _hat_cdf(u: float) -> float:
    # integral from -inf to u of the hat max(0, 1 - |t|)
    if u <= -1.0:
        return 0.0
    if u <= 0.0:
        return 0.5 * (1.0 + u) * (1.0 + u)
    if u <= 1.0:
        return 1.0 - 0.5 * (1.0 - u) * (1.0 - u)
    return 1.0


@wp.func
def _deposit_end(buf: wp.array2d(dtype=wp.vec4), row: int, p0: float, p1: float, v: wp.vec4):
    """One end of a span whose position moves linearly from ``p0`` to ``p1`` over the sub-row.

    A step at ``p`` (pixel-box integrated) is the difference pair ``(1 - f, f)`` at
    ``(floor(p), floor(p) + 1)``, i.e. the hat weights ``max(0, 1 - |p - j|)`` at every
    column ``j``. A position uniform on ``[p0, p1]`` deposits the mean hat weights, in
    closed form; positions left of 0 (right of W) deposit at column 0 (W): the span is
    clipped to the image. ``buf`` is (H, W + 2): columns W and W + 1 are never read back.
    """
    w = float(buf.shape[1] - 2)
    lo = wp.min(p0, p1)
    hi = wp.max(p0, p1)
    span = hi - lo
    if span < 1.0e-4:
        p = wp.clamp(0.5 * (lo + hi), 0.0, w)
        k = int(wp.floor(p))
        f = p - float(k)
        wp.atomic_add(buf, row, k, v * (1.0 - f))
        wp.atomic_add(buf, row, k + 1, v * f)
        return
    inv = 1.0 / span
    if lo < 0.0:
        wp.atomic_add(buf, row, 0, v * ((wp.min(hi, 0.0) - lo) * inv))
    if hi > w:
        wp.atomic_add(buf, row, int(w), v * ((hi - wp.max(lo, w)) * inv))
    mlo = wp.max(lo, 0.0)
    mhi = wp.min(hi, w)
    if mhi > mlo:
        j0 = int(wp.floor(mlo))
        j1 = int(wp.floor(mhi)) + 1
        for j in range(j0, j1 + 1):
            fj = float(j)
            wgt = (_hat_cdf(mhi - fj) - _hat_cdf(mlo - fj)) * inv
            if wgt != 0.0:
                wp.atomic_add(buf, row, j, v * wgt)


@wp.func
def _signed_chord(y: float, rho: float, blades: wp.array(dtype=wp.vec4), n_blades: int, sgn: float) -> wp.vec2:
    # the chord at height y (relative to the centre); empty chords collapse to their middle
    c = wp.vec2()
    if sgn < 0.0:
        cc = chord(-y, rho, blades, n_blades)
        c = wp.vec2(-cc[1], -cc[0])
    else:
        c = chord(y, rho, blades, n_blades)
    if c[1] < c[0]:
        m = 0.5 * (c[0] + c[1])
        c = wp.vec2(m, m)
    return c


@wp.func
def _n_sub(t0: float, t1: float, yc: float, rho: float, blades: wp.array(dtype=wp.vec4), n_blades: int,
           sgn: float) -> int:
    """Sub-rows of the row part ``[t0, t1]``: enough that each chord end is straight to ``SAG_PX``.

    The deviation of the chord ends at mid-height from the straight line between the
    ends at ``t0`` and ``t1`` is the sag; splitting in ``n`` divides a smooth sag by ``n^2``.
    """
    c0 = _signed_chord(t0 - yc, rho, blades, n_blades, sgn)
    cm = _signed_chord(0.5 * (t0 + t1) - yc, rho, blades, n_blades, sgn)
    c1 = _signed_chord(t1 - yc, rho, blades, n_blades, sgn)
    sag = wp.max(wp.abs(cm[0] - 0.5 * (c0[0] + c1[0])), wp.abs(cm[1] - 0.5 * (c0[1] + c1[1])))
    return wp.clamp(int(wp.ceil(wp.sqrt(sag / SAG_PX))), 1, MAX_SUB)


@wp.func
def _scatter_one(
    buf: wp.array2d(dtype=wp.vec4),
    xc: float,
    yc: float,
    rho: float,
    v: wp.vec4,
    blades: wp.array(dtype=wp.vec4),
    n_blades: int,
    extent: wp.vec2,
    sgn: float,
):
    # sgn = -1 draws the shape point-reflected (sources in front of the focal plane)
    top = yc + extent[0] * rho
    bot = yc + extent[1] * rho
    if sgn < 0.0:
        top = yc - extent[1] * rho
        bot = yc - extent[0] * rho
    ky0 = int(wp.floor(top))
    ky1 = int(wp.floor(bot))
    # pass 1: the area of the piecewise-linear shape (trapezoids), inside the image or not
    norm = float(0.0)
    for k in range(ky0, ky1 + 1):
        t0 = wp.max(float(k), top)
        t1 = wp.min(float(k + 1), bot)
        if t1 > t0:
            n = _n_sub(t0, t1, yc, rho, blades, n_blades, sgn)
            step = (t1 - t0) / float(n)
            c0 = _signed_chord(t0 - yc, rho, blades, n_blades, sgn)
            for j in range(n):
                c1 = _signed_chord(t0 + float(j + 1) * step - yc, rho, blades, n_blades, sgn)
                norm += step * 0.5 * ((c0[1] - c0[0]) + (c1[1] - c1[0]))
                c0 = c1
    if norm <= 0.0:
        # degenerate shape at this radius: keep the energy at the centre
        r = wp.clamp(int(wp.floor(yc)), 0, buf.shape[0] - 1)
        _deposit_end(buf, r, wp.floor(xc), wp.floor(xc), v)
        _deposit_end(buf, r, wp.floor(xc) + 1.0, wp.floor(xc) + 1.0, -v)
        return
    inv = 1.0 / norm
    # pass 2: each sub-row is a trapezoid; its two ends are deposited exactly (pixel-area integrated)
    k0 = wp.max(ky0, 0)
    k1 = wp.min(ky1, buf.shape[0] - 1)
    for k in range(k0, k1 + 1):
        t0 = wp.max(float(k), top)
        t1 = wp.min(float(k + 1), bot)
        if t1 > t0:
            n = _n_sub(t0, t1, yc, rho, blades, n_blades, sgn)
            step = (t1 - t0) / float(n)
            vv = v * (step * inv)
            c0 = _signed_chord(t0 - yc, rho, blades, n_blades, sgn)
            for j in range(n):
                c1 = _signed_chord(t0 + float(j + 1) * step - yc, rho, blades, n_blades, sgn)
                if (c0[1] - c0[0]) + (c1[1] - c1[0]) > 0.0:
                    _deposit_end(buf, k, xc + c0[0], xc + c1[0], vv)
                    _deposit_end(buf, k, xc + c0[1], xc + c1[1], -vv)
                c0 = c1


@wp.kernel
def scatter_kernel(
    src: wp.array2d(dtype=wp.vec4),
    coc: wp.array2d(dtype=float),
    blades: wp.array(dtype=wp.vec4),
    n_blades: int,
    extent: wp.vec2,
    r0: float,
    n_levels: int,
    buf0: wp.array2d(dtype=wp.vec4),
    buf1: wp.array2d(dtype=wp.vec4),
    buf2: wp.array2d(dtype=wp.vec4),
    buf3: wp.array2d(dtype=wp.vec4),
    buf4: wp.array2d(dtype=wp.vec4),
    buf5: wp.array2d(dtype=wp.vec4),
):
    """Scatter every source of ``src`` (local coordinates) with radius ``|coc|`` [px].

    ``extent`` is the shape's vertical extent ``(y_top, y_bottom)`` at unit radius. A
    positive (in-front-of-focus) ``coc`` draws the shape point-reflected, as a
    thin lens does: the aperture's orientation is that of background bokeh.

    ``buf<l>`` is the difference buffer of level ``l``, ``(ceil(H/2^l), ceil(W/2^l) + 2)``.
    """
    y, x = wp.tid()
    v = src[y, x]
    if v[3] == 0.0:
        return
    r = wp.abs(coc[y, x])
    # a thin lens images the aperture point-reflected in front of the focal plane (s > 0)
    sgn = float(1.0)
    if coc[y, x] > 0.0:
        sgn = -1.0
    if r < 0.5:
        # the disc lies inside the source pixel: a plain copy
        wp.atomic_add(buf0, y, x, v)
        wp.atomic_add(buf0, y, x + 1, -v)
        return
    lev = int(0)
    scale = float(1.0)
    while r * scale > r0 and lev < n_levels - 1:
        lev += 1
        scale *= 0.5
    xc = (float(x) + 0.5) * scale
    yc = (float(y) + 0.5) * scale
    rho = r * scale
    if lev == 0:
        _scatter_one(buf0, xc, yc, rho, v, blades, n_blades, extent, sgn)
    elif lev == 1:
        _scatter_one(buf1, xc, yc, rho, v, blades, n_blades, extent, sgn)
    elif lev == 2:
        _scatter_one(buf2, xc, yc, rho, v, blades, n_blades, extent, sgn)
    elif lev == 3:
        _scatter_one(buf3, xc, yc, rho, v, blades, n_blades, extent, sgn)
    elif lev == 4:
        _scatter_one(buf4, xc, yc, rho, v, blades, n_blades, extent, sgn)
    else:
        _scatter_one(buf5, xc, yc, rho, v, blades, n_blades, extent, sgn)


@wp.kernel
def prefix_rows_kernel(buf: wp.array2d(dtype=wp.vec4)):
    """In-place running sum along each row: differences -> per-pixel values."""
    y = wp.tid()
    acc = wp.vec4()
    for x in range(buf.shape[1]):
        acc = acc + buf[y, x]
        buf[y, x] = acc


@wp.func
def _bilinear(buf: wp.array2d(dtype=wp.vec4), fx: float, fy: float, h: int, w: int) -> wp.vec4:
    t = bilinear_taps(fx, fy, h, w)
    top = buf[t.y0, t.x0] * (1.0 - t.tx) + buf[t.y0, t.x1] * t.tx
    bottom = buf[t.y1, t.x0] * (1.0 - t.tx) + buf[t.y1, t.x1] * t.tx
    return top * (1.0 - t.ty) + bottom * t.ty


@wp.func
def _level_sample(buf: wp.array2d(dtype=wp.vec4), x: int, y: int, lev: int, full_h: int, full_w: int) -> wp.vec4:
    scale = 1.0 / float(1 << lev)
    h = (full_h + (1 << lev) - 1) >> lev
    w = (full_w + (1 << lev) - 1) >> lev
    fx = (float(x) + 0.5) * scale - 0.5
    fy = (float(y) + 0.5) * scale - 0.5
    return _bilinear(buf, fx, fy, h, w) * (scale * scale)


@wp.kernel
def resolve_levels_kernel(
    n_levels: int,
    buf0: wp.array2d(dtype=wp.vec4),
    buf1: wp.array2d(dtype=wp.vec4),
    buf2: wp.array2d(dtype=wp.vec4),
    buf3: wp.array2d(dtype=wp.vec4),
    buf4: wp.array2d(dtype=wp.vec4),
    buf5: wp.array2d(dtype=wp.vec4),
    out: wp.array2d(dtype=wp.vec4),
):
    """Sum level 0 and the bilinearly upsampled coarser levels (density-preserving) into ``out``."""
    y, x = wp.tid()
    h = out.shape[0]
    w = out.shape[1]
    acc = buf0[y, x]
    if n_levels > 1:
        acc = acc + _level_sample(buf1, x, y, 1, h, w)
    if n_levels > 2:
        acc = acc + _level_sample(buf2, x, y, 2, h, w)
    if n_levels > 3:
        acc = acc + _level_sample(buf3, x, y, 3, h, w)
    if n_levels > 4:
        acc = acc + _level_sample(buf4, x, y, 4, h, w)
    if n_levels > 5:
        acc = acc + _level_sample(buf5, x, y, 5, h, w)
    out[y, x] = acc


@wp.kernel
def composite_kernel(layer: wp.array2d(dtype=wp.vec4), x0: int, y0: int, acc: wp.array2d(dtype=wp.vec4)):
    """Composite one scattered layer OVER the accumulator (back-to-front "over").

    ``layer`` holds (sum of premultiplied RGB, sum of coverage) in local
    coordinates offset by ``(x0, y0)``. Its opacity is ``min(coverage, 1)`` and
    its colour is normalised by its coverage (so overlapping sources of one
    layer average instead of adding up). ``acc`` holds (RGB, opacity).
    """
    y, x = wp.tid()
    l = layer[y, x]
    cov = l[3]
    if cov <= 1.0e-6:
        return
    alpha = wp.min(cov, 1.0)
    k = alpha / cov
    gy = y + y0
    gx = x + x0
    a = acc[gy, gx]
    t = 1.0 - alpha
    acc[gy, gx] = wp.vec4(l[0] * k + t * a[0], l[1] * k + t * a[1], l[2] * k + t * a[2], alpha + t * a[3])


@wp.kernel
def finalize_kernel(
    acc: wp.array2d(dtype=wp.vec4),
    image: wp.array2d(dtype=wp.vec3),
    slice_id: wp.array2d(dtype=wp.int32),
    out: wp.array2d(dtype=wp.vec3),
):
    """Divide by the accumulated opacity (renormalises holes and borders).

    Copied pixels (``slice_id < 0``) and pixels no source reached keep the input.
    """
    y, x = wp.tid()
    a = acc[y, x]
    if slice_id[y, x] >= 0 and a[3] > 1.0e-4:
        out[y, x] = wp.vec3(a[0], a[1], a[2]) / a[3]
    else:
        out[y, x] = image[y, x]
