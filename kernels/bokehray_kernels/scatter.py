"""Row-span scatter of aperture-shaped CoCs on a radius pyramid, and layer compositing.

Each source pixel spreads a ``vec4`` (premultiplied RGB, coverage) over its
aperture shape. The shape is cut into pixel rows; each row is one or more
spans deposited into a per-row *difference* buffer (a few adds per end), and a
prefix sum along each row turns the differences into per-pixel coverage. A
source therefore costs O(rows), not O(r^2). Sources whose radius exceeds ``r0``
are scattered on a coarser level ``l`` (pixel size ``2^l``) where their radius is
at most ``r0``, unless the launcher routes them to level 0 (``exact`` flag: the
salient sources, docs/renderer.md); ``resolve_levels_kernel`` brings the levels
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
The pyramid levels (``_scatter_coarse``) use one sharp span per row at its
mid-height chord, with the same normalisation: the upsampling blurs their
outline by a coarse pixel anyway.
"""

import warp as wp

from .aperture import chord
from .sampling import bilinear_taps
from .support import in_support, span_in_support

wp.set_module_options({"enable_backward": False})

MAX_LEVELS = 6
"""Pyramid levels 0..5: radii up to ``r0 * 32`` cost O(r0) per source."""

SAG_PX = wp.constant(0.25)
"""Largest sag [px] of a chord end inside a sub-row (before the ``MAX_SUB`` cap)."""

MAX_SUB = wp.constant(4)
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
                  blades: wp.array(dtype=wp.vec4), n_blades: int, sgn: float):
    # the share ``rest`` of ``v`` the rows did not deposit (the exact-area normalisation's remainder): on the
    # centre row's chord (at least one pixel wide), so every source deposits exactly its value
    if rest == 0.0:
        return
    r = wp.clamp(int(wp.floor(yc)), 0, buf.shape[0] - 1)
    cc = _signed_chord(0.0, rho, blades, n_blades, sgn)
    a = xc + cc[0]
    b = xc + cc[1]
    if b - a < 1.0:
        a = wp.floor(xc)
        b = a + 1.0
    vr = v * (rest / (b - a))
    _deposit_step(buf, r, a, vr)
    _deposit_step(buf, r, b, -vr)


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
    area: float,
    sgn: float,
):
    # sgn = -1 draws the shape point-reflected (sources in front of the focal plane). Heights
    # are relative to the centre (u = y - yc; exact for row edges while yc has at most 8 fractional
    # bits: pixel centres, the clusters' 1/256 px grid), so the same source is cut into the same
    # sub-rows wherever it lies (tiles equal the untiled render).
    span = _signed_extent(extent, rho, sgn)
    u_top = span[0]
    u_bot = span[1]
    ky0 = int(wp.floor(yc + u_top))
    ky1 = int(wp.floor(yc + u_bot))
    h = buf.shape[0]
    # One pass. Each sub-row is deposited with density v / (area rho^2) (the shape's exact
    # area); its ends are exact pixel-integrated ramps. What the sub-rows' summed area ``tr``
    # (the whole shape's, inside the image or not) differs from the exact area goes on the
    # centre row's chord, so the source deposits exactly v.
    inv = 1.0 / (area * rho * rho)
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
    _deposit_rest(buf, xc, yc, rho, v, float(wp.float64(1.0) - tr * wp.float64(inv)), blades, n_blades, sgn)


@wp.func
def _scatter_coarse(
    buf: wp.array2d(dtype=wp.vec4),
    xc: float,
    yc: float,
    rho: float,
    v: wp.vec4,
    blades: wp.array(dtype=wp.vec4),
    n_blades: int,
    extent: wp.vec2,
    area: float,
    sgn: float,
):
    """The cheap span rule: one sharp-ended span per row (its mid-height chord).

    For the pyramid levels, whose outline the bilinear upsampling blurs anyway (about one coarse
    pixel): the sub-row ramps of ``_scatter_one`` would buy nothing there. Same normalisation: density
    ``v / (area rho^2)``, the remainder on the centre row's chord, so the source deposits exactly v.
    """
    span = _signed_extent(extent, rho, sgn)
    u_top = span[0]
    u_bot = span[1]
    ky0 = int(wp.floor(yc + u_top))
    ky1 = int(wp.floor(yc + u_bot))
    h = buf.shape[0]
    inv = 1.0 / (area * rho * rho)
    tr = wp.float64(0.0)
    for k in range(ky0, ky1 + 1):
        u0 = wp.max(float(k) - yc, u_top)
        u1 = wp.min(float(k + 1) - yc, u_bot)
        if u1 > u0:
            c = _signed_chord(0.5 * (u0 + u1), rho, blades, n_blades, sgn)
            hh = u1 - u0
            tr += wp.float64(hh * (c[1] - c[0]))
            if k >= 0 and k < h and c[1] > c[0]:
                vv = v * (hh * inv)
                _deposit_step(buf, k, xc + c[0], vv)
                _deposit_step(buf, k, xc + c[1], -vv)
    _deposit_rest(buf, xc, yc, rho, v, float(wp.float64(1.0) - tr * wp.float64(inv)), blades, n_blades, sgn)


@wp.func
def level_of(r: float, r0: float, n_levels: int) -> int:
    """Pyramid level of a source of radius ``r``: the first where ``r / 2^l <= r0`` (at most ``n_levels - 1``)."""
    lev = int(0)
    scale = float(1.0)
    while r * scale > r0 and lev < n_levels - 1:
        lev += 1
        scale *= 0.5
    return lev


@wp.kernel
def scatter_kernel(
    src: wp.array2d(dtype=wp.vec4),
    coc: wp.array2d(dtype=float),
    exact: wp.array2d(dtype=wp.uint8),
    cell_total: wp.array3d(dtype=wp.vec4),
    cell_pixels: wp.array3d(dtype=float),
    blades: wp.array(dtype=wp.vec4),
    n_blades: int,
    extent: wp.vec2,
    area: float,
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

    ``extent`` is the shape's vertical extent ``(y_top, y_bottom)`` and ``area`` its area,
    both at unit circumradius. A positive (in-front-of-focus) ``coc`` draws the shape
    point-reflected, as a thin lens does: the aperture's orientation is that of background bokeh.
    ``exact[y, x] != 0`` routes a salient source: the light it carries beyond its coverage of the
    local colour of the layer's other sources around it (``cell_total``, ``cell_pixels``: the
    neighbourhoods ``route_cells_kernel`` stored) is scattered at level 0 (full resolution) whatever its radius, the rest (its coverage, and
    the local colour over it) on its pyramid level like its neighbours. A constant colour thus
    stays on the pyramid, exactly as smooth as its coverage. ``exact`` may be a 1 x 1 array when
    nothing is routed (then ``cell_total`` and ``cell_pixels`` are not read).

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
    lev = level_of(r, r0, n_levels)
    if lev > 0 and exact.shape[0] == src.shape[0] and exact.shape[1] == src.shape[1]:
        if exact[y, x] != wp.uint8(0):
            # a salient source: its excess light over the local colour of the sources around it (itself
            # left out) at full resolution, the exact outline; its coverage of that colour on its pyramid
            # level like its neighbours'. Alone in its neighbourhood, all of its light goes to level 0.
            nb = stored_neighbourhood(cell_total, cell_pixels, lev, y >> lev, x >> lev)
            base = routed_base(v, nb)
            if exact[y, x] == wp.uint8(1):  # routed alone; 2: its excess is in its cell's cluster source
                _scatter_one(buf0, float(x) + 0.5, float(y) + 0.5, r,
                             wp.vec4(v[0] - base[0], v[1] - base[1], v[2] - base[2], 0.0), blades, n_blades, extent,
                             area, sgn)
            v = base
    scale = 1.0 / float(1 << lev)
    xc = (float(x) + 0.5) * scale
    yc = (float(y) + 0.5) * scale
    rho = r * scale
    if lev == 0:
        _scatter_one(buf0, xc, yc, rho, v, blades, n_blades, extent, area, sgn)
    elif lev == 1:
        _scatter_coarse(buf1, xc, yc, rho, v, blades, n_blades, extent, area, sgn)
    elif lev == 2:
        _scatter_coarse(buf2, xc, yc, rho, v, blades, n_blades, extent, area, sgn)
    elif lev == 3:
        _scatter_coarse(buf3, xc, yc, rho, v, blades, n_blades, extent, area, sgn)
    elif lev == 4:
        _scatter_coarse(buf4, xc, yc, rho, v, blades, n_blades, extent, area, sgn)
    else:
        _scatter_coarse(buf5, xc, yc, rho, v, blades, n_blades, extent, area, sgn)


@wp.kernel
def radiance_mean_kernel(src: wp.array2d(dtype=wp.vec4), means: wp.array3d(dtype=wp.vec4),
                         counts: wp.array3d(dtype=float)):
    """Level 1 of the radiance pyramid: mean over each 2 x 2 cell of the sources (premultiplied RGB, coverage).

    Sources of zero coverage count as black; cells cut by the array's edge average the pixels they hold
    (``counts``). Level ``k`` lives in ``means[k - 1]``.
    """
    cy, cx = wp.tid()
    acc = wp.vec4()
    n = float(0.0)
    for dy in range(2):
        for dx in range(2):
            y = 2 * cy + dy
            x = 2 * cx + dx
            if y < src.shape[0] and x < src.shape[1]:
                acc += src[y, x]
                n += 1.0
    means[0, cy, cx] = acc / n
    counts[0, cy, cx] = n


@wp.kernel
def halve_mean_kernel(means: wp.array3d(dtype=wp.vec4), counts: wp.array3d(dtype=float), k: int, fine_h: int,
                      fine_w: int):
    """Radiance pyramid level ``k + 1`` (in ``means[k]``) from level ``k``: pixel-count-weighted 2 x 2 means."""
    cy, cx = wp.tid()
    acc = wp.vec4()
    n = float(0.0)
    for dy in range(2):
        for dx in range(2):
            y = 2 * cy + dy
            x = 2 * cx + dx
            if y < fine_h and x < fine_w:
                c = counts[k - 1, y, x]
                acc += means[k - 1, y, x] * c
                n += c
    means[k, cy, cx] = acc / n
    counts[k, cy, cx] = n


@wp.struct
class Neighbourhood:
    """Sum of the sources (premultiplied RGB, coverage) over some cells, and how many pixels they hold."""

    total: wp.vec4
    pixels: float


@wp.func
def neighbourhood(means: wp.array3d(dtype=wp.vec4), counts: wp.array3d(dtype=float), lev: int, cy: int, cx: int,
                  hl: int, wl: int) -> Neighbourhood:
    """The sources of the 3 x 3 level-``lev`` cells around cell ``(cy, cx)`` (cells beyond the ``hl x wl`` level
    left out): the layer's local colour there is ``total.rgb / total.a``."""
    acc = wp.vec4()
    nc = float(0.0)
    for dy in range(-1, 2):
        for dx in range(-1, 2):
            yy = cy + dy
            xx = cx + dx
            if yy >= 0 and yy < hl and xx >= 0 and xx < wl:
                c = counts[lev - 1, yy, xx]
                acc += means[lev - 1, yy, xx] * c
                nc += c
    nb = Neighbourhood()
    nb.total = acc
    nb.pixels = nc
    return nb


@wp.func
def stored_neighbourhood(cell_total: wp.array3d(dtype=wp.vec4), cell_pixels: wp.array3d(dtype=float), lev: int,
                         cy: int, cx: int) -> Neighbourhood:
    """The neighbourhood of level-``lev`` cell ``(cy, cx)`` as ``route_cells_kernel`` stored it."""
    nb = Neighbourhood()
    nb.total = cell_total[lev - 1, cy, cx]
    nb.pixels = cell_pixels[lev - 1, cy, cx]
    return nb


@wp.func
def routed_base(v: wp.vec4, nb: Neighbourhood) -> wp.vec4:
    """What of a routed source stays on the pyramid: its coverage, carrying the local colour of the other sources
    in its neighbourhood ``nb`` (itself left out; none there: black). The rest of its light goes to level 0."""
    rest = nb.total - v
    if rest[3] > 1.0e-6 * nb.pixels:
        k = v[3] / rest[3]
        return wp.vec4(wp.max(rest[0], 0.0) * k, wp.max(rest[1], 0.0) * k, wp.max(rest[2], 0.0) * k, v[3])
    return wp.vec4(0.0, 0.0, 0.0, v[3])


@wp.func
def _local_mean(nb: Neighbourhood) -> wp.vec2:
    # (mean premultiplied radiance m, mean coverage a_m) of a neighbourhood: its local colour is m / a_m
    return wp.vec2((nb.total[0] + nb.total[1] + nb.total[2]) / (3.0 * nb.pixels), nb.total[3] / nb.pixels)


@wp.func
def _raw_excess(v: wp.vec4, mean: wp.vec2) -> float:
    # the light a source (premultiplied radiance, coverage v) carries beyond its coverage of the local colour
    return (v[0] + v[1] + v[2]) / 3.0 - v[3] * mean[0] / mean[1]  # mean[1] > 0: the source itself has coverage


@wp.func
def _excess(v: wp.vec4, r: float, mean: wp.vec2, visible: float, floor: float) -> float:
    # how far a source of radius r stands out of the local colour: its excess beyond the visibility threshold
    return _raw_excess(v, mean) - visible * wp.max(mean[0], floor) * 3.14159265 * r * r


@wp.func
def _cluster_excess(v: wp.vec4, r: float, flag: wp.uint8, mean: wp.vec2, r0: float, n_levels: int,
                    lev: int) -> float:
    # a cluster member's excess (> 0): a source of level lev, not routed alone, brighter than the local colour
    if flag == wp.uint8(0) and _on_level(v, r, r0, n_levels, lev):
        return wp.max(_raw_excess(v, mean), 0.0)
    return 0.0


@wp.func
def _on_level(v: wp.vec4, r: float, r0: float, n_levels: int, lev: int) -> bool:
    # the source has coverage and scatters on pyramid level ``lev`` >= 1 (level_of(r) == lev, without its loop:
    # r * 2^-l is exact in binary floating point, as in level_of)
    if v[3] == 0.0 or r < 0.5:
        return False
    scale = 1.0 / float(1 << lev)
    if r * (2.0 * scale) <= r0:
        return False  # a lower level
    return r * scale <= r0 or lev == n_levels - 1


@wp.kernel
def route_cells_kernel(
    src: wp.array2d(dtype=wp.vec4),
    coc: wp.array2d(dtype=float),
    means: wp.array3d(dtype=wp.vec4),
    counts: wp.array3d(dtype=float),
    r0: float,
    n_levels: int,
    lev: int,
    per_cell: int,
    visible: float,
    floor: float,
    support: wp.array2d(dtype=wp.uint8),
    shift: int,
    oy: int,
    ox: int,
    exact: wp.array2d(dtype=wp.uint8),
    cell_total: wp.array3d(dtype=wp.vec4),
    cell_pixels: wp.array3d(dtype=float),
    cluster_light: wp.array3d(dtype=wp.vec4),
    cluster_shape: wp.array3d(dtype=wp.vec4),
):
    """Route the level-``lev`` sources of each level cell: at most ``per_cell`` salient ones alone to level 0, and
    the rest of the cell's excess light, when together it is visible, as its cluster.

    One thread per cell of ``2^lev x 2^lev`` px. Salience: how far a source's own disc stands
    out of its layer's neighbourhood, the 3 x 3 level-``lev`` cells around its own (cells beyond
    the array left out): mean premultiplied radiance ``m`` and coverage ``a_m``, so the layer's
    local colour is ``m / a_m``. A source of radiance ``q`` and coverage ``a`` carries
    ``e = q - a m / a_m`` more light than its coverage of the local colour (0 on a constant
    image, whatever the layer's shape); its disc then lights ``e / (pi r^2)`` above the blurred
    surroundings (about ``m``), and its outline is visible when that exceeds
    ``visible * max(m, floor)``: the score is the excess beyond that, salient where > 0. The
    cell keeps its sources of that level with the largest scores (ties: the first in row order),
    marked 1 in ``exact``. A level-0 source costs ``2^lev`` times the rows of its pyramid scatter, so
    the routed work is at most ``per_cell / 2^lev`` times what the cell's pyramid sources cost.

    *Extended lights.* A lamp or a window is many sources, each too faint alone to show its outline,
    whose outlines coincide: together they draw a sharp-edged ball. The cell's sources of that level not
    routed alone and with positive excess are its *cluster*; when their summed excess ``E`` beats the
    visibility threshold at the excess-weighted mean radius, their excess light (what ``routed_base`` does
    not keep on the pyramid) goes to level 0 gathered per block of ``2^b`` px, ``b = max(1, lev - 2)``, one
    source at each block's excess-weighted centroid: ``cluster_light[lev - 1, by, bx] = (RGB, summed
    excess)``, ``cluster_shape[...] = (x, y, signed CoC, 1)``, and the members are marked 2 in ``exact``. At
    most 16 level-0 sources per cell, whose rows are at most twice those of the cell's pyramid sources
    (level 3), whatever the radius. ``E`` is the excess of all the cell's sources with a positive one less
    that of the routed ones, summed in float64 in the pass that counts the salient ones.

    ``means[k]``, ``counts[k]``: radiance pyramid level ``k + 1`` (padded to level 1). Each cell's
    neighbourhood sums are stored in ``cell_total``, ``cell_pixels`` for the scatter. Cells outside the
    layer's ``support`` (``bokehray_kernels.support``) hold no source: skipped, nothing stored.
    """
    cy, cx = wp.tid()
    side = 1 << lev
    y0 = cy * side
    x0 = cx * side
    y1 = wp.min(y0 + side, src.shape[0])
    x1 = wp.min(x0 + side, src.shape[1])
    if not span_in_support(support, shift, oy, ox, y0, y1, x0, x1):
        return
    hl = (src.shape[0] + side - 1) >> lev
    wl = (src.shape[1] + side - 1) >> lev
    nb = neighbourhood(means, counts, lev, cy, cx, hl, wl)
    cell_total[lev - 1, cy, cx] = nb.total
    cell_pixels[lev - 1, cy, cx] = nb.pixels
    mean = _local_mean(nb)
    n = int(0)  # salient sources of this level in the cell; only a few cells have any
    e_all = wp.float64(0.0)  # excess (> 0) of the level's sources, and its CoC moment: all of them ...
    ps_all = wp.float64(0.0)
    e_sal = wp.float64(0.0)  # ... and the salient ones
    ps_sal = wp.float64(0.0)
    for y in range(y0, y1):
        for x in range(x0, x1):
            v = src[y, x]
            r = wp.abs(coc[y, x])
            if _on_level(v, r, r0, n_levels, lev):
                e = _raw_excess(v, mean)
                if e > 0.0:
                    e_all += wp.float64(e)
                    ps_all += wp.float64(e * coc[y, x])
                    if _excess(v, r, mean, visible, floor) > 0.0:
                        n += 1
                        e_sal += wp.float64(e)
                        ps_sal += wp.float64(e * coc[y, x])
    if e_all == wp.float64(0.0):
        return
    if n <= per_cell:
        if n > 0:
            for y in range(y0, y1):
                for x in range(x0, x1):
                    v = src[y, x]
                    r = wp.abs(coc[y, x])
                    if _on_level(v, r, r0, n_levels, lev):
                        if _excess(v, r, mean, visible, floor) > 0.0:
                            exact[y, x] = wp.uint8(1)
    else:
        e_sal = wp.float64(0.0)
        ps_sal = wp.float64(0.0)
        bound = float(1.0e38)  # scores above it (or equal, earlier in row order) are already taken
        by = int(-1)
        bx = int(-1)
        for _ in range(per_cell):
            best = float(0.0)
            iy = int(-1)
            ix = int(-1)
            for y in range(y0, y1):
                for x in range(x0, x1):
                    v = src[y, x]
                    r = wp.abs(coc[y, x])
                    if _on_level(v, r, r0, n_levels, lev):
                        s = _excess(v, r, mean, visible, floor)
                        if s > best:
                            after = s < bound or (s == bound and (y > by or (y == by and x > bx)))
                            if after:
                                best = s
                                iy = y
                                ix = x
            if iy < 0:
                break
            exact[iy, ix] = wp.uint8(1)
            e = _raw_excess(src[iy, ix], mean)
            e_sal += wp.float64(e)
            ps_sal += wp.float64(e * coc[iy, ix])
            bound = best
            by = iy
            bx = ix
    e_sum = float(e_all - e_sal)  # the cluster's
    if e_sum <= 0.0:
        return
    s_mean = float((ps_all - ps_sal) / (e_all - e_sal))
    if e_sum - visible * wp.max(mean[0], floor) * 3.14159265 * s_mean * s_mean <= 0.0:
        return
    # visible together: its members' excess goes to level 0, gathered per block of 2^b px, b = max(1, lev - 2)
    # (a block's members lie within 2^(b-1) px of their centroid, at most 1/32 of the radius, so the gathered
    # sources keep the cluster's own soft outline; at most 16 blocks a cell, so the cost stays flat in R)
    b = wp.max(1, lev - 2)
    bs = 1 << b
    for by in range(y0 >> b, (y1 + bs - 1) >> b):
        for bx in range(x0 >> b, (x1 + bs - 1) >> b):
            b_e = float(0.0)
            b_light = wp.vec3()
            b_x = float(0.0)
            b_y = float(0.0)
            b_s = float(0.0)
            for y in range(by * bs, wp.min(by * bs + bs, y1)):
                for x in range(bx * bs, wp.min(bx * bs + bs, x1)):
                    v = src[y, x]
                    e = _cluster_excess(v, wp.abs(coc[y, x]), exact[y, x], mean, r0, n_levels, lev)
                    if e > 0.0:
                        base = routed_base(v, nb)
                        b_light += wp.vec3(v[0] - base[0], v[1] - base[1], v[2] - base[2])
                        b_e += e
                        b_x += e * (float(x - bx * bs) + 0.5)  # relative to the block: the same sums
                        b_y += e * (float(y - by * bs) + 0.5)  # in a tile's window as in the whole box
                        b_s += e * coc[y, x]
                        exact[y, x] = wp.uint8(2)
            if b_e > 0.0:
                # the centroid on a 1/256 px grid: exact in float32 in a window's coordinates and in the box's,
                # so the scatter cuts the same sub-rows in both (tiled renders equal the untiled one)
                cx_rel = wp.floor(b_x / b_e * 256.0 + 0.5) / 256.0
                cy_rel = wp.floor(b_y / b_e * 256.0 + 0.5) / 256.0
                cluster_light[lev - 1, by, bx] = wp.vec4(b_light[0], b_light[1], b_light[2], b_e)
                cluster_shape[lev - 1, by, bx] = wp.vec4(float(bx * bs) + cx_rel, float(by * bs) + cy_rel,
                                                         b_s / b_e, 1.0)


@wp.kernel
def scatter_clusters_kernel(
    cluster_light: wp.array3d(dtype=wp.vec4),
    cluster_shape: wp.array3d(dtype=wp.vec4),
    lev: int,
    blades: wp.array(dtype=wp.vec4),
    n_blades: int,
    extent: wp.vec2,
    area: float,
    buf0: wp.array2d(dtype=wp.vec4),
):
    """Scatter the level-``lev`` cluster sources (``route_cells_kernel``; one thread per block) at level 0:
    light, no coverage, with the exact area-integrated spans (a block is 2 px wide up to level 3: the pyramid
    levels' sharp spans cost small lamps 2-3 dB)."""
    by, bx = wp.tid()
    shape = cluster_shape[lev - 1, by, bx]
    if shape[3] == 0.0:
        return
    light = cluster_light[lev - 1, by, bx]
    sgn = float(1.0)
    if shape[2] > 0.0:
        sgn = -1.0
    _scatter_one(buf0, shape[0], shape[1], wp.abs(shape[2]), wp.vec4(light[0], light[1], light[2], 0.0), blades,
                 n_blades, extent, area, sgn)


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
    first: int,
    buf0: wp.array2d(dtype=wp.vec4),
    buf1: wp.array2d(dtype=wp.vec4),
    buf2: wp.array2d(dtype=wp.vec4),
    buf3: wp.array2d(dtype=wp.vec4),
    buf4: wp.array2d(dtype=wp.vec4),
    buf5: wp.array2d(dtype=wp.vec4),
    support: wp.array2d(dtype=wp.uint8),
    shift: int,
    oy: int,
    ox: int,
    out: wp.array2d(dtype=wp.vec4),
):
    """Sum level 0 and the bilinearly upsampled coarser levels ``first .. n_levels - 1`` (density-preserving)
    into ``out``; the levels between 0 and ``first`` hold no source (``bokehray.scene.lowest_level``).

    Pixels outside the layer's ``support`` are left as they are: the caller passes ``out`` zero there (the
    preview reuses the layer's sources, which are zero there).
    """
    y, x = wp.tid()
    if not in_support(support, shift, oy, ox, y, x):
        return
    h = out.shape[0]
    w = out.shape[1]
    acc = buf0[y, x]
    if n_levels > 1 and first <= 1:
        acc = acc + _level_sample(buf1, x, y, 1, h, w)
    if n_levels > 2 and first <= 2:
        acc = acc + _level_sample(buf2, x, y, 2, h, w)
    if n_levels > 3 and first <= 3:
        acc = acc + _level_sample(buf3, x, y, 3, h, w)
    if n_levels > 4 and first <= 4:
        acc = acc + _level_sample(buf4, x, y, 4, h, w)
    if n_levels > 5 and first <= 5:
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
