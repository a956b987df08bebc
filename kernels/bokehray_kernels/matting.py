"""Matting of the pixels in the unknown band around depth edges (``bokehray.matting.split_mixed_pixels``).

One thread a band pixel, over its window (``offset_y``, ``offset_x``; Gaussian weight ``offset_g``):

1. the window's CoC range, split at its middle into a near and a far side;
2. ``alpha = w . I + c`` fitted by weighted ridge regression (Gaussian weights, unknown pixels at
   ``unknown_weight``; targets 1 near, 0 far), solved in float64;
3. the model's alpha of every window pixel weights the side means: F from the near side by ``alpha^purity``,
   B from the far side by ``(1 - alpha)^purity``; the parts' CoC are the window's largest and smallest CoC
   (the plateaus on either side of the edge, not the pixel's own, mixed or ramp value).

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
