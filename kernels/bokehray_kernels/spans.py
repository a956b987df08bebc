"""Deposits: a source's aperture-shaped CoC as row spans in a difference buffer (docs/renderer.md).

Each source pixel spreads a ``vec4`` (premultiplied RGB, coverage) over its
aperture shape. The shape is cut into pixel rows; each row is one or more
spans deposited into a per-row *difference* buffer (a few adds per end), and a
prefix sum along each row turns the differences into per-pixel coverage. A
source therefore costs O(rows), not O(r^2). Sources whose radius exceeds ``r0``
are scattered on a coarser level ``l`` (pixel size ``2^l``) where their radius is
at most ``r0``, unless the launcher routes them to level 0 (``exact`` flag: the
salient sources, ``bokehray_kernels.routing``); ``bokehray_kernels.pyramid`` brings the levels
back to full resolution (bilinear, energy preserving).

Area-exact spans: a pixel row (clipped to the shape's vertical extent) is split
into ``n`` sub-rows where its chord ends bend (``n`` from the sag of the ends at
mid-row, at most ``MAX_SUB``; graded towards the shape's top and bottom). In a
sub-row each end moves linearly between its positions at the sub-row's edges,
shifted by 2/3 of its sag at mid-height (Simpson's rule for its mean position),
and is deposited as the exact pixel-box integral of that moving step (a ramp
over the columns it crosses). Spans carry density ``v / (area * rho^2)`` (the
shape's exact area); what the sub-rows' summed area differs from it goes on
the centre row's chord, so every source deposits exactly its value (minus what
falls outside the image), at every radius, including radii below one pixel.
The pyramid levels (:func:`scatter_sharp`) use one sharp span per row at its
mid-height chord, with the same normalisation: the upsampling blurs their
outline by a coarse pixel anyway.
"""

import warp as wp

from .aperture import chord

wp.set_module_options({"enable_backward": False})

SAG_PX = wp.constant(0.25)
"""Largest sag [px] of a chord end inside a sub-row (before the ``MAX_SUB`` cap)."""

MAX_SUB = wp.constant(4)
"""Most sub-rows per pixel row (reached only next to the poles of a shape)."""


@wp.struct
class Shape:
    """The aperture every source of a render is drawn with: its blades (``bokehray.lens.Aperture``), their count,
    its vertical extent ``(y_top, y_bottom)`` and its area, both at unit circumradius."""

    blades: wp.array(dtype=wp.vec4)
    n_blades: int
    extent: wp.vec2
    area: float


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
    if span <= 1.0 and lo >= 0.0 and hi <= w:
        # the common case in closed form: three columns k, k + 1, k + 2
        k = int(wp.floor(lo))
        f = lo - float(k)
        g = f + span
        wk = 0.5 * (1.0 - f) * (1.0 - f)
        w2 = float(0.0)
        if g <= 1.0:
            wk -= 0.5 * (1.0 - g) * (1.0 - g)
        else:
            w2 = 0.5 * (g - 1.0) * (g - 1.0) * inv
        wk *= inv
        wp.atomic_add(buf, row, k, v * wk)
        wp.atomic_add(buf, row, k + 1, v * (1.0 - wk - w2))
        if w2 > 0.0:
            wp.atomic_add(buf, row, k + 2, v * w2)
        return
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
def _deposit_step(buf: wp.array2d(dtype=wp.vec4), row: int, p: float, v: wp.vec4):
    # a sharp end at p (``_deposit_end`` with p0 = p1): the pixel-box integrated step, clipped to [0, W]
    q = wp.clamp(p, 0.0, float(buf.shape[1] - 2))
    k = int(wp.floor(q))
    f = q - float(k)
    wp.atomic_add(buf, row, k, v * (1.0 - f))
    wp.atomic_add(buf, row, k + 1, v * f)


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
def _n_sub(c0: wp.vec2, cm: wp.vec2, c1: wp.vec2) -> int:
    """Sub-rows of a row part with chords ``c0``, ``cm``, ``c1`` at its top, middle and bottom.

    The sag is how far the chord ends at mid-height lie from the straight line between
    the ends at top and bottom; splitting in ``n`` divides a smooth sag by ``n^2``.
    """
    sag = wp.max(wp.abs(cm[0] - 0.5 * (c0[0] + c1[0])), wp.abs(cm[1] - 0.5 * (c0[1] + c1[1])))
    if sag <= SAG_PX:
        return 1
    return wp.min(int(wp.ceil(wp.sqrt(sag / SAG_PX))), MAX_SUB)


@wp.func
def _sub_edge(t0: float, t1: float, j: int, n: int, at_top: int, at_bot: int) -> float:
    """Height of the j-th of n sub-row edges of ``[t0, t1]``.

    Uniform, except in a row holding the shape's top (bottom) end, where a rounded shape's
    chord ends move like the square root of the distance to it: there the edges are graded
    (quadratically near that end, cosine spacing), so the ends move about equally per sub-row.
    """
    u = float(j) / float(n)
    if at_top != 0 and at_bot != 0:
        u = 0.5 - 0.5 * wp.cos(u * 3.14159265358979)
    elif at_top != 0:
        u = 1.0 - wp.cos(u * 1.5707963267949)
    elif at_bot != 0:
        u = wp.sin(u * 1.5707963267949)
    if j == n:
        u = 1.0
    return t0 + (t1 - t0) * u


@wp.func
def _signed_extent(extent: wp.vec2, rho: float, sgn: float) -> wp.vec2:
    # the shape's vertical extent (top, bottom) at radius rho, point-reflected for sgn < 0 (in front of focus)
    if sgn < 0.0:
        return wp.vec2(-extent[1] * rho, -extent[0] * rho)
    return wp.vec2(extent[0] * rho, extent[1] * rho)


@wp.func
def _deposit_rest(buf: wp.array2d(dtype=wp.vec4), xc: float, yc: float, rho: float, v: wp.vec4, rest: float,
                  shape: Shape, sgn: float):
    # the share ``rest`` of ``v`` the rows did not deposit (the exact-area normalisation's remainder): on the
    # centre row's chord (at least one pixel wide), so every source deposits exactly its value
    if rest == 0.0:
        return
    r = wp.clamp(int(wp.floor(yc)), 0, buf.shape[0] - 1)
    cc = _signed_chord(0.0, rho, shape.blades, shape.n_blades, sgn)
    a = xc + cc[0]
    b = xc + cc[1]
    if b - a < 1.0:
        a = wp.floor(xc)
        b = a + 1.0
    vr = v * (rest / (b - a))
    _deposit_step(buf, r, a, vr)
    _deposit_step(buf, r, b, -vr)


@wp.struct
class Rows:
    """The pixel rows a shape of radius ``rho`` centred at height ``yc`` covers: its vertical extent relative to the
    centre ``(u_top, u_bot)`` and the rows ``k0 .. k1`` holding it."""

    u_top: float
    u_bot: float
    k0: int
    k1: int


@wp.func
def rows_of(yc: float, rho: float, shape: Shape, sgn: float) -> Rows:
    """The row walk both span rules take (point-reflected for ``sgn < 0``).

    The first and last rows come from the centre's fraction (``yc = iy + fy``, both exact in float32): ``floor(yc +
    u)`` rounds the sum at ``yc``'s magnitude, so a shape's end within a few ulps of a row edge fell in another row
    in a tile's window than in the whole frame (the graded sub-rows of :func:`_sub_edge` on another row: tiled
    renders 1e-4 off the untiled one)."""
    span = _signed_extent(shape.extent, rho, sgn)
    r = Rows()
    r.u_top = span[0]
    r.u_bot = span[1]
    iy = wp.floor(yc)
    fy = yc - iy
    r.k0 = int(iy) + int(wp.floor(fy + r.u_top))
    r.k1 = int(iy) + int(wp.floor(fy + r.u_bot))
    return r


@wp.func
def scatter_exact(buf: wp.array2d(dtype=wp.vec4), xc: float, yc: float, rho: float, v: wp.vec4, shape: Shape,
                  sgn: float):
    """Scatter one source of value ``v`` centred at ``(xc, yc)`` with the area-exact spans (module docstring)."""
    # sgn = -1 draws the shape point-reflected (sources in front of the focal plane). Heights
    # are relative to the centre (u = y - yc; exact for row edges while yc has at most 8 fractional
    # bits: pixel centres, the clusters' 1/256 px grid), so the same source is cut into the same
    # sub-rows wherever it lies (tiles equal the untiled render).
    rows = rows_of(yc, rho, shape, sgn)
    u_top = rows.u_top
    u_bot = rows.u_bot
    ky0 = rows.k0
    ky1 = rows.k1
    h = buf.shape[0]
    blades = shape.blades
    n_blades = shape.n_blades
    # One pass. Each sub-row is deposited with density v / (area rho^2) (the shape's exact
    # area); its ends are exact pixel-integrated ramps. What the sub-rows' summed area ``tr``
    # (the whole shape's, inside the image or not) differs from the exact area goes on the
    # centre row's chord, so the source deposits exactly v.
    inv = 1.0 / (shape.area * rho * rho)
    tr = wp.float64(0.0)  # float64: at r = 300 a float32 sum's rounding would be as large as a pixel's share
    # the extent is padded by 1e-5 (aperture.vertical_extent): the chords at the shape's ends are
    # taken 2e-5 inside, where they are not empty (a vertex, or a flat blade edge)
    inset = 2.0e-5 * rho
    u_prev = u_top
    c_prev = _signed_chord(u_top + inset, rho, blades, n_blades, sgn)
    for k in range(ky0, ky1 + 1):
        u0 = u_prev
        u1 = wp.min(float(k + 1) - yc, u_bot)
        if u1 <= u0:
            continue
        c0 = c_prev
        c1 = wp.vec2()
        if u1 >= u_bot:
            c1 = _signed_chord(u_bot - inset, rho, blades, n_blades, sgn)
        else:
            c1 = _signed_chord(u1, rho, blades, n_blades, sgn)
        cm = _signed_chord(0.5 * (u0 + u1), rho, blades, n_blades, sgn)
        n = _n_sub(c0, cm, c1)
        at_top = int(k == ky0)
        at_bot = int(k == ky1)
        inside = k >= 0 and k < h
        ca = c0
        ua = u0
        for j in range(n):
            ub = u1
            cb = c1
            if j < n - 1:
                ub = _sub_edge(u0, u1, j + 1, n, at_top, at_bot)
                cb = _signed_chord(ub, rho, blades, n_blades, sgn)
            cmid = cm
            if n > 1:
                cmid = _signed_chord(0.5 * (ua + ub), rho, blades, n_blades, sgn)
            # Simpson: the ends' mean positions are (a0 + 4 a_mid + a1) / 6, so the straight
            # ramps are shifted by 2/3 of the sag; the sub-row's area is Simpson's
            da = (2.0 / 3.0) * (cmid[0] - 0.5 * (ca[0] + cb[0]))
            db = (2.0 / 3.0) * (cmid[1] - 0.5 * (ca[1] + cb[1]))
            hh = ub - ua
            wsum = (ca[1] - ca[0]) + (cb[1] - cb[0]) + 2.0 * (db - da)
            tr += wp.float64(hh * 0.5 * wsum)
            if inside and wsum > 0.0:
                vv = v * (hh * inv)
                _deposit_end(buf, k, xc + ca[0] + da, xc + cb[0] + da, vv)
                _deposit_end(buf, k, xc + ca[1] + db, xc + cb[1] + db, -vv)
            ca = cb
            ua = ub
        u_prev = u1
        c_prev = c1
    _deposit_rest(buf, xc, yc, rho, v, float(wp.float64(1.0) - tr * wp.float64(inv)), shape, sgn)


@wp.func
def scatter_sharp(buf: wp.array2d(dtype=wp.vec4), xc: float, yc: float, rho: float, v: wp.vec4, shape: Shape,
                  sgn: float):
    """The cheap span rule: one sharp-ended span per row (its mid-height chord).

    For the pyramid levels, whose outline the bilinear upsampling blurs anyway (about one coarse
    pixel): the sub-row ramps of :func:`scatter_exact` would buy nothing there. Same normalisation: density
    ``v / (area rho^2)``, the remainder on the centre row's chord, so the source deposits exactly v.
    """
    rows = rows_of(yc, rho, shape, sgn)
    u_top = rows.u_top
    u_bot = rows.u_bot
    ky0 = rows.k0
    ky1 = rows.k1
    h = buf.shape[0]
    inv = 1.0 / (shape.area * rho * rho)
    tr = wp.float64(0.0)
    for k in range(ky0, ky1 + 1):
        u0 = wp.max(float(k) - yc, u_top)
        u1 = wp.min(float(k + 1) - yc, u_bot)
        if u1 > u0:
            c = _signed_chord(0.5 * (u0 + u1), rho, shape.blades, shape.n_blades, sgn)
            hh = u1 - u0
            tr += wp.float64(hh * (c[1] - c[0]))
            if k >= 0 and k < h and c[1] > c[0]:
                vv = v * (hh * inv)
                _deposit_step(buf, k, xc + c[0], vv)
                _deposit_step(buf, k, xc + c[1], -vv)
    _deposit_rest(buf, xc, yc, rho, v, float(wp.float64(1.0) - tr * wp.float64(inv)), shape, sgn)
