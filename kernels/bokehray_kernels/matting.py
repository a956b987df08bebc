"""Matting of the pixels in the unknown band around depth edges (``bokehray.matting.split_mixed_pixels``).

One thread a band pixel, over its window (``offset_y``, ``offset_x``; Gaussian weight ``offset_g``):

1. the window's CoC range, split at its middle into a near and a far side;
2. ``alpha = w . I + c`` fitted by weighted ridge regression (Gaussian weights, unknown pixels at
   ``unknown_weight``; targets 1 near, 0 far), solved in float64;
3. the model's alpha of every window pixel weights the side means: F from the near side by ``alpha^purity``,
   B from the far side by ``(1 - alpha)^purity``; the parts' CoC are the window's largest and smallest CoC
   (the plateaus on either side of the edge, not the pixel's own, mixed or ramp value);
4. a near pixel brighter than both its parts (above ``light_level`` and ``light_ratio`` times F and B): B is the
   dark side's and a light is behind the pixel, so B is the brightest far samples within ``LIT_REACH`` px
   (``_lit_far``) and alpha the pixel's place on the line from B to F;
5. a light behind a strand (B brighter than ``light_level`` and ``light_ratio`` times F, the near side under
   ``light_thin`` of the window's weight): every near sample of the window holds some of the light and the model
   calls them pure, so F is taken again: the strand's colour from its cross-sections over the light and over an
   unlit background within ``light_reach`` px where it crosses both (``_strand_colour``: the light measures its
   width; only where the pixel's strand is one a cross-section holds, ``_narrow_here``), else the near samples that
   hold the least of the light's colour and the most of the strand (``_light_free``), used where the window's F
   holds over ``light_share`` more of the light than that F; alpha is the pixel's place on the line from B to F,
   but with a measured F at most what the strand's width leaves the pixel after its near neighbours across the
   strand (``_cover_left``) where it exceeds that by over ``XS_LEFT``: the pixel is then darker than the strand can
   make it, the light's rim.

Oracle: ``tests/reference/matting_ref.py``.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})

BAND_OK = 1
"""Flag bit: the window holds a depth edge and samples of both sides."""
BAND_OWN_NEAR = 2
"""Flag bit: the pixel's own CoC lies on the near side of its window's middle."""


@wp.struct
class BandWindow:
    """A band pixel's window: the offsets (nearest first) and their Gaussian weights."""

    offset_y: wp.array(dtype=wp.int32)
    offset_x: wp.array(dtype=wp.int32)
    offset_g: wp.array(dtype=float)


@wp.struct
class BandParams:
    """The matting's constants (``bokehray.edge_estimate.MattingRule``)."""

    jump_px: float
    unknown_weight: float
    ridge: float
    purity: float
    purity_n: int
    """``purity`` as a whole number (0 to 64), raised by squaring; -1: ``purity`` is not one (``wp.pow``)."""
    light_level: float  # a far side brighter than this (mean of RGB, the image's units) may be a light ...
    light_ratio: float  # ... when it is also this many times brighter than F (summed RGB)
    light_reach: int  # ... then F also takes near-side samples out to this many px; 0: never
    light_thin: float  # ... where the near side holds less than this share of the window's weight (a strand)
    light_share: float  # ... and the window's F holds more than this share of the light's colour than the unlit F


@wp.struct
class BandEstimate:
    """The kernel's outputs, one entry a band pixel."""

    alpha: wp.array(dtype=float)
    fg: wp.array(dtype=wp.vec3)
    bg: wp.array(dtype=wp.vec3)
    fg_var: wp.array(dtype=wp.vec3)
    bg_var: wp.array(dtype=wp.vec3)
    near_coc: wp.array(dtype=float)
    far_coc: wp.array(dtype=float)
    flags: wp.array(dtype=wp.int32)


@wp.func
def purity_weight(a: float, params: BandParams) -> float:
    """``a^purity``: by squaring where the purity is a whole number (a fifth of ``wp.pow``'s cost on the CPU)."""
    n = params.purity_n
    if n < 0:
        return wp.pow(a, params.purity)
    out = float(1.0)
    base = a
    while n > 0:
        if n % 2 == 1:
            out = out * base
        base = base * base
        n = n // 2
    return out


@wp.func
def _reach_tap(window: BandWindow, k: int, side: int, reach: int, py: int, px: int, h: int, w: int) -> wp.vec3:
    """Tap ``k`` of the light's search around (py, px) as (y, x, weight): the window's taps at their Gaussian
    weights, then a ``side`` x ``side`` grid out to ``reach`` at the window's smallest weight (0 inside the window,
    beyond the reach or outside the image)."""
    m = window.offset_y.shape[0]
    gy = int(0)
    gx = int(0)
    g = float(0.0)
    if k < m:
        gy = window.offset_y[k]
        gx = window.offset_x[k]
        g = window.offset_g[k]
    else:
        gy = (k - m) / side - reach
        gx = (k - m) % side - reach
        r_in = float(window.offset_y[m - 1] * window.offset_y[m - 1] + window.offset_x[m - 1] * window.offset_x[m - 1])
        dd = float(gy * gy + gx * gx)
        if dd > r_in and dd <= float(reach * reach):
            g = window.offset_g[m - 1]
    y = py + gy
    x = px + gx
    if y < 0 or y >= h or x < 0 or x >= w:
        g = 0.0
    return wp.vec3(float(y), float(x), g)


XS_LIT = wp.constant(0.75)
"""A cross-section is lit when both its ends hold at least this share of the light's colour ..."""
XS_UNLIT = wp.constant(0.05)
"""... and unlit when both hold less than this."""
XS_MIN_W = wp.constant(0.05)
"""A strand's measured width (px across a pixel column or row) must exceed this ..."""
XS_MAX_W = wp.constant(2.5)
"""... and be at most this (the cross-section holds 3 px)."""


@wp.func
def _cross_section(image: wp.array2d(dtype=wp.vec3), coc: wp.array2d(dtype=float), y: int, x: int, ey: int,
                   ex: int, mid: float, mb: wp.vec3, bb: float):
    """The strand's cross-section through its map pixel (y, x) along (ey, ex): the sum over the pixels 1 px either
    side and itself of the photo less the background interpolated linearly between the pixels 2 px either side, and
    that background's mean; the kind: 1 lit (both ends hold at least ``XS_LIT`` of the light ``mb``), -1 unlit
    (both below ``XS_UNLIT``), 0 neither or no cross-section (an end outside the image or on the near side: no
    strand up to 3 px across there)."""
    y1 = y - 2 * ey
    x1 = x - 2 * ex
    y2 = y + 2 * ey
    x2 = x + 2 * ex
    zero = wp.vec3(0.0, 0.0, 0.0)
    if y1 < 0 or x1 < 0 or y2 >= coc.shape[0] or x2 >= coc.shape[1]:  # (ey, ex) is (1, 0) or (0, 1)
        return zero, zero, 0
    if coc[y1, x1] > mid or coc[y2, x2] > mid:
        return zero, zero, 0
    c1 = image[y1, x1]
    c2 = image[y2, x2]
    s = image[y - ey, x - ex] + image[y, x] + image[y + ey, x + ex] - 1.5 * (c1 + c2)
    l1 = wp.dot(c1, mb) / bb
    l2 = wp.dot(c2, mb) / bb
    kind = int(0)
    if wp.min(l1, l2) >= XS_LIT:
        kind = 1
    elif wp.max(l1, l2) < XS_UNLIT:
        kind = -1
    return s, 0.5 * (c1 + c2), kind


@wp.func
def _narrow_here(coc: wp.array2d(dtype=float), py: int, px: int, ey: int, ex: int, mid: float) -> int:
    """1 where the strand through (py, px) is one the cross-sections measure: no near pixel of its 3 x 3 has a
    pixel 2 px either side along (ey, ex) on the near side too (a strand wider than a cross-section there, or
    another near object beside it: the strands the reach measured are not this one); else 0."""
    h = coc.shape[0]
    w = coc.shape[1]
    for dy in range(-1, 2):
        for dx in range(-1, 2):
            y = py + dy
            x = px + dx
            if y >= 0 and y < h and x >= 0 and x < w:
                if coc[y, x] > mid:
                    for s in range(-1, 2, 2):
                        ye = y + 2 * s * ey
                        xe = x + 2 * s * ex
                        if ye >= 0 and ye < h and xe >= 0 and xe < w:
                            if coc[ye, xe] > mid:
                                return 0
    return 1


XS_LEFT = wp.constant(0.4)
"""A pixel whose place on the line from the light to the measured strand colour exceeds by more than this (px of
cover) what the strand's measured width leaves it after the near pixels beside it across the strand
(:func:`_cover_left`) is darker than the strand can make it: the light is dimmer there than B (its rim beside the
strand), and its alpha is what the width leaves it."""


@wp.func
def _cover_left(image: wp.array2d(dtype=wp.vec3), coc: wp.array2d(dtype=float), py: int, px: int, ey: int,
                mid: float, mb: wp.vec3, f: wp.vec3, width: float) -> float:
    """What a strand ``width`` px across, of colour ``f`` over the light ``mb``, leaves (py, px) of its cover after
    the near pixels within 2 px of it along (ey, 1 - ey) take theirs (each their place on the line from ``mb`` to
    ``f``, clipped to [0, 1]), counting only pixels the light is behind (holding at least ``XS_UNLIT`` of it: over an
    unlit background a pixel's place on that line is not its cover); at least 0, and 2 (no bound) where (py, px)
    itself holds less."""
    if wp.dot(image[py, px], mb) < XS_UNLIT * wp.dot(mb, mb):
        return 2.0
    fb = mb - f
    den = wp.max(wp.dot(fb, fb), 1.0e-30)
    h = image.shape[0]
    w = image.shape[1]
    ex = 1 - ey
    taken = float(0.0)
    for k in range(-2, 3):
        y = py + k * ey
        x = px + k * ex
        if k != 0 and y >= 0 and y < h and x >= 0 and x < w:
            c = image[y, x]
            if coc[y, x] > mid and wp.dot(c, mb) >= XS_UNLIT * wp.dot(mb, mb):  # a near pixel the light is behind
                taken += wp.clamp(wp.dot(mb - c, fb) / den, 0.0, 1.0)
    return wp.max(width - taken, 0.0)


@wp.func
def _strand_colour(su: wp.vec3, sl: wp.vec3, n: wp.vec2, d: wp.vec3, lt: wp.vec3) -> wp.vec4:
    """The strand's colour from its mean unlit cross-section ``su`` (over ``d``: ``W (F - D)``) and lit one ``sl``
    (over ``lt``: ``W (F - L)``), ``n`` the counts: its width ``W = (su - sl) . (L - D) / |L - D|^2`` (the light
    measures it), ``F = D + su / W``, and W as the fourth entry; 0 there without both kinds or a width in
    (``XS_MIN_W``, ``XS_MAX_W``]."""
    if n[0] < 1.0 or n[1] < 1.0:
        return wp.vec4(0.0, 0.0, 0.0, 0.0)
    u = su / n[0]
    dd = d / n[0]
    ld = lt / n[1] - dd
    den = wp.dot(ld, ld)
    if den <= 1.0e-30:
        return wp.vec4(0.0, 0.0, 0.0, 0.0)
    width = wp.dot(u - sl / n[1], ld) / den
    if width <= XS_MIN_W or width > XS_MAX_W:
        return wp.vec4(0.0, 0.0, 0.0, 0.0)
    f = wp.max(dd + u / width, wp.vec3(0.0, 0.0, 0.0))
    return wp.vec4(f[0], f[1], f[2], width)


@wp.func
def _light_free(image: wp.array2d(dtype=wp.vec3), coc: wp.array2d(dtype=float), window: BandWindow, py: int,
                px: int, mid: float, mu: wp.vec3, my: float, wv: wp.vec3, mb: wp.vec3, params: BandParams):
    """F of a near side lit from behind by a light of colour ``mb``: over the window and a full grid out to
    ``light_reach``, (1) the unlit background ``D``, the far samples weighted by ``(1 - l)^purity`` (``l``: the
    sample's projection on ``mb``); (2) the near samples weighted by ``(alpha (1 - l)^2)^purity`` (the model's
    alpha), their mean ``F0``; (3) F: their mean weighted by ``(alpha (1 - l)^2 t)^purity``, ``t`` the sample's place
    from ``D`` towards ``F0`` (clamped to [0, 1.5], so that a lit sample's brightness does not count as cover): the
    most covered of the unlit near samples (a strand thinner than a
    pixel is nowhere pure: the mean of its unlit samples is its colour times its mean coverage). (4) Where the near
    samples' cross-sections (:func:`_cross_section`, across the axis the near samples spread along least) show the
    strand both over the light and over an unlit background, its colour from them instead
    (:func:`_strand_colour`), unless a near pixel of (py, px)'s 3 x 3 lies in a strand wider than a cross-section
    (:func:`_narrow_here`). Returns (the weight sum and the cross-sections' ``ey`` as a vec3's first two entries, the
    weighted sum, the weighted sum of squares, the cross-sections' colour with the width as its fourth entry, or 0
    there)."""
    h = coc.shape[0]
    w = coc.shape[1]
    m = window.offset_y.shape[0]
    reach = params.light_reach
    side = 2 * reach + 1
    n = m + side * side
    bb = wp.max(wp.dot(mb, mb), 1.0e-30)
    sd = float(0.0)
    d1 = wp.vec3(0.0, 0.0, 0.0)
    s0 = float(0.0)
    f0 = wp.vec3(0.0, 0.0, 0.0)
    spread = wp.vec2(0.0, 0.0)  # the near samples' squared offsets along y and x
    for k in range(n):
        tap = _reach_tap(window, k, side, reach, py, px, h, w)
        g = tap[2]
        y = int(tap[0])
        x = int(tap[1])
        if g > 0.0:
            c = image[y, x]
            lq = wp.clamp(wp.dot(c, mb) / bb, 0.0, 1.0)
            if coc[y, x] > mid:
                aq = wp.clamp(my + wp.dot(c - mu, wv), 0.0, 1.0)
                wf = g * purity_weight(aq * (1.0 - lq) * (1.0 - lq), params)
                s0 += wf
                f0 += wf * c
                spread += wp.vec2(float((y - py) * (y - py)), float((x - px) * (x - px)))
            else:
                wd = g * purity_weight(1.0 - lq, params)
                sd += wd
                d1 += wd * c
    ey = int(1)  # a strand along x: its cross-sections down the pixel columns
    if spread[0] > spread[1]:
        ey = 0
    dk = d1 / wp.max(sd, 1.0e-30)
    fd = f0 / wp.max(s0, 1.0e-30) - dk
    ff = wp.max(wp.dot(fd, fd), 1.0e-30)
    sf = float(0.0)
    f1 = wp.vec3(0.0, 0.0, 0.0)
    f2 = wp.vec3(0.0, 0.0, 0.0)
    su = wp.vec3(0.0, 0.0, 0.0)  # the unlit cross-sections' sums and backgrounds, then the lit ones'
    du = wp.vec3(0.0, 0.0, 0.0)
    sl = wp.vec3(0.0, 0.0, 0.0)
    dl = wp.vec3(0.0, 0.0, 0.0)
    nx = wp.vec2(0.0, 0.0)
    for k in range(n):
        tap = _reach_tap(window, k, side, reach, py, px, h, w)
        g = tap[2]
        y = int(tap[0])
        x = int(tap[1])
        if g > 0.0:
            if coc[y, x] > mid:
                c = image[y, x]
                lq = wp.clamp(wp.dot(c, mb) / bb, 0.0, 1.0)
                aq = wp.clamp(my + wp.dot(c - mu, wv), 0.0, 1.0)
                tq = wp.clamp(wp.dot(c - dk, fd) / ff, 0.0, 1.5)
                wf = g * purity_weight(aq * (1.0 - lq) * (1.0 - lq) * tq, params)
                sf += wf
                f1 += wf * c
                f2 += wf * wp.cw_mul(c, c)
                xs, xb, kind = _cross_section(image, coc, y, x, ey, 1 - ey, mid, mb, bb)
                if kind < 0:
                    su += xs
                    du += xb
                    nx += wp.vec2(1.0, 0.0)
                elif kind > 0:
                    sl += xs
                    dl += xb
                    nx += wp.vec2(0.0, 1.0)
    nx = nx * float(_narrow_here(coc, py, px, ey, 1 - ey, mid))  # 0: this pixel's strand is not the one measured
    return wp.vec3(sf, float(ey), 0.0), f1, f2, _strand_colour(su, sl, nx, du, dl)


LIT_REACH = wp.constant(4)
"""A near pixel's light behind it is looked for this many px around it (a small light's disc)."""


@wp.func
def _lit_far(image: wp.array2d(dtype=wp.vec3), coc: wp.array2d(dtype=float), py: int, px: int, mid: float,
             params: BandParams):
    """The far samples within ``LIT_REACH`` px of (py, px) (a square) weighted by their brightness over the
    brightest's (summed RGB), to the power ``purity``: a light's colour where the far side holds one. Returns (the
    weight sum, the weighted sum, the weighted sum of squares)."""
    h = coc.shape[0]
    w = coc.shape[1]
    top = float(0.0)
    for y in range(wp.max(py - LIT_REACH, 0), wp.min(py + LIT_REACH + 1, h)):
        for x in range(wp.max(px - LIT_REACH, 0), wp.min(px + LIT_REACH + 1, w)):
            if coc[y, x] <= mid:
                c = image[y, x]
                top = wp.max(top, c[0] + c[1] + c[2])
    sw = float(0.0)
    s1 = wp.vec3(0.0, 0.0, 0.0)
    s2 = wp.vec3(0.0, 0.0, 0.0)
    for y in range(wp.max(py - LIT_REACH, 0), wp.min(py + LIT_REACH + 1, h)):
        for x in range(wp.max(px - LIT_REACH, 0), wp.min(px + LIT_REACH + 1, w)):
            if coc[y, x] <= mid:
                c = image[y, x]
                wt = purity_weight((c[0] + c[1] + c[2]) / wp.max(top, 1.0e-30), params)
                sw += wt
                s1 += wt * c
                s2 += wt * wp.cw_mul(c, c)
    return sw, s1, s2


@wp.kernel
def matting_band_kernel(  # noqa: C901
    image: wp.array2d(dtype=wp.vec3),
    coc: wp.array2d(dtype=float),
    unknown: wp.array2d(dtype=wp.uint8),
    band_y: wp.array(dtype=wp.int32),
    band_x: wp.array(dtype=wp.int32),
    window: BandWindow,
    params: BandParams,
    out: BandEstimate,
):
    i = wp.tid()
    h = coc.shape[0]
    w = coc.shape[1]
    py = band_y[i]
    px = band_x[i]
    m = window.offset_y.shape[0]
    hi = float(-1.0e30)
    lo = float(1.0e30)
    for k in range(m):
        y = py + window.offset_y[k]
        x = px + window.offset_x[k]
        if y >= 0 and y < h and x >= 0 and x < w:
            v = coc[y, x]
            hi = wp.max(hi, v)
            lo = wp.min(lo, v)
    mid = 0.5 * (hi + lo)

    # the model's weighted moments, in one pass (float64: the centred moments are differences of raw ones)
    sw = wp.float64(0.0)
    swy = wp.float64(0.0)
    s0 = wp.float64(0.0)
    s1 = wp.float64(0.0)
    s2 = wp.float64(0.0)
    c00 = wp.float64(0.0)
    c01 = wp.float64(0.0)
    c02 = wp.float64(0.0)
    c11 = wp.float64(0.0)
    c12 = wp.float64(0.0)
    c22 = wp.float64(0.0)
    y0 = wp.float64(0.0)
    y1 = wp.float64(0.0)
    y2 = wp.float64(0.0)
    for k in range(m):
        y = py + window.offset_y[k]
        x = px + window.offset_x[k]
        if y >= 0 and y < h and x >= 0 and x < w:
            wt = window.offset_g[k]
            if unknown[y, x] != wp.uint8(0):
                wt = wt * params.unknown_weight
            wd = wp.float64(wt)
            c = image[y, x]
            d0 = wp.float64(c[0])
            d1 = wp.float64(c[1])
            d2 = wp.float64(c[2])
            sw += wd
            s0 += wd * d0
            s1 += wd * d1
            s2 += wd * d2
            c00 += wd * d0 * d0
            c01 += wd * d0 * d1
            c02 += wd * d0 * d2
            c11 += wd * d1 * d1
            c12 += wd * d1 * d2
            c22 += wd * d2 * d2
            if coc[y, x] > mid:
                swy += wd
                y0 += wd * d0
                y1 += wd * d1
                y2 += wd * d2
    sw = wp.max(sw, wp.float64(1.0e-30))
    m0 = s0 / sw
    m1 = s1 / sw
    m2 = s2 / sw
    myd = swy / sw
    mu = wp.vec3(float(m0), float(m1), float(m2))
    my = float(myd)
    cy = wp.vec3d(y0 / sw - myd * m0, y1 / sw - myd * m1, y2 / sw - myd * m2)
    c00 = c00 / sw - m0 * m0
    c01 = c01 / sw - m0 * m1
    c02 = c02 / sw - m0 * m2
    c11 = c11 / sw - m1 * m1
    c12 = c12 / sw - m1 * m2
    c22 = c22 / sw - m2 * m2
    eps = wp.float64(params.ridge * params.ridge) * ((m0 * m0 + m1 * m1 + m2 * m2) / wp.float64(3.0) + wp.float64(1.0e-8))
    cov = wp.mat33d(c00 + eps, c01, c02, c01, c11 + eps, c12, c02, c12, c22 + eps)
    wvd = wp.inverse(cov) * cy
    wv = wp.vec3(float(wvd[0]), float(wvd[1]), float(wvd[2]))
    out.alpha[i] = wp.clamp(my + wp.dot(image[py, px] - mu, wv), 0.0, 1.0)

    # the side means weighted by the model's purity
    sf = float(0.0)
    sb = float(0.0)
    f1 = wp.vec3(0.0, 0.0, 0.0)
    b1 = wp.vec3(0.0, 0.0, 0.0)
    f2 = wp.vec3(0.0, 0.0, 0.0)
    b2 = wp.vec3(0.0, 0.0, 0.0)
    best_f = float(0.0)
    best_b = float(0.0)
    for k in range(m):
        y = py + window.offset_y[k]
        x = px + window.offset_x[k]
        if y >= 0 and y < h and x >= 0 and x < w:
            g = window.offset_g[k]
            c = image[y, x]
            aq = wp.clamp(my + wp.dot(c - mu, wv), 0.0, 1.0)
            v = coc[y, x]
            if v > mid:
                wf = g * purity_weight(aq, params)
                sf += wf
                f1 += wf * c
                f2 += wf * wp.cw_mul(c, c)
                best_f = wp.max(best_f, wf)
            else:
                wb = g * purity_weight(1.0 - aq, params)
                sb += wb
                b1 += wb * c
                b2 += wb * wp.cw_mul(c, c)
                best_b = wp.max(best_b, wb)
    sf = wp.max(sf, 1.0e-30)
    sb = wp.max(sb, 1.0e-30)
    mf = f1 / sf
    mb = b1 / sb
    own = image[py, px]
    osum = own[0] + own[1] + own[2]
    if params.light_reach > 0 and best_b > 0.0 and coc[py, px] > mid and osum > 3.0 * params.light_level:
        if osum > params.light_ratio * wp.max(mf[0] + mf[1] + mf[2], mb[0] + mb[1] + mb[2]):
            # a pixel of the near side brighter than both its parts, which ``alpha F + (1 - alpha) B`` cannot be: a
            # light is behind it and B, from the purest far samples, is the dark side's. B is the brightest far samples'
            # within ``LIT_REACH`` px
            bw, bs1, bs2 = _lit_far(image, coc, py, px, mid, params)
            lb = bs1 / wp.max(bw, 1.0e-30)
            if lb[0] + lb[1] + lb[2] > osum:
                sb = wp.max(bw, 1.0e-30)
                mb = lb
                b2 = bs2
                fb = mf - mb
                out.alpha[i] = wp.clamp(wp.dot(own - mb, fb) / wp.max(wp.dot(fb, fb), 1.0e-30), 0.0, 1.0)
    if params.light_reach > 0 and hi - lo > params.jump_px and best_f > 0.0 and best_b > 0.0:
        bsum = mb[0] + mb[1] + mb[2]
        thin = my < params.light_thin  # a strand's share of the window, not a body's
        if thin and bsum > 3.0 * params.light_level and bsum > params.light_ratio * (mf[0] + mf[1] + mf[2]):
            # a light behind the near side (a strand across a lamp): every near sample of the window holds some of
            # it and looks pure to the model. F is taken again where the near side crosses a darker background
            # (``_light_free``), and the pixel's alpha is its place on the line from B to that F
            lw, l1, l2, xf = _light_free(image, coc, window, py, px, mid, mu, my, wv, mb, params)
            lf = l1 / wp.max(lw[0], 1.0e-30)
            # only where the window's F holds clearly more of the light than the unlit one (an opaque wire's core
            # is its own colour over any light: its F stays), unless the strand's cross-sections measured its colour
            share = wp.dot(mf - lf, mb) / wp.max(wp.dot(mb, mb), 1.0e-30)
            left = float(2.0)  # the cover the strand's width leaves the pixel (2: no bound)
            if xf[3] > 0.0:  # the strand's colour from its cross-sections over the light and beside it
                var_f = l2 / wp.max(lw[0], 1.0e-30) - wp.cw_mul(lf, lf)
                lf = wp.vec3(xf[0], xf[1], xf[2])
                l2 = wp.max(lw[0], 1.0e-30) * (var_f + wp.cw_mul(lf, lf))  # the unlit samples' spread about it
                share = 1.0
                left = _cover_left(image, coc, py, px, int(lw[1]), mid, mb, lf, xf[3])
            if share > params.light_share:
                sf = wp.max(lw[0], 1.0e-30)
                mf = lf
                f2 = l2
                fb = mf - mb
                a = wp.clamp(wp.dot(image[py, px] - mb, fb) / wp.max(wp.dot(fb, fb), 1.0e-30), 0.0, 1.0)
                if a > left + XS_LEFT:
                    a = left  # darker than the strand can make it: the light is dimmer here (its rim), not covered
                out.alpha[i] = a
    out.fg[i] = mf
    out.bg[i] = mb
    zero = wp.vec3(0.0, 0.0, 0.0)
    out.fg_var[i] = wp.max(f2 / sf - wp.cw_mul(mf, mf), zero)
    out.bg_var[i] = wp.max(b2 / sb - wp.cw_mul(mb, mb), zero)
    out.near_coc[i] = hi
    out.far_coc[i] = lo
    fl = int(0)
    if hi - lo > params.jump_px and best_f > 0.0 and best_b > 0.0:
        fl = fl | BAND_OK
    if coc[py, px] > mid:
        fl = fl | BAND_OWN_NEAR
    out.flags[i] = fl
