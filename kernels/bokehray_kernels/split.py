"""The split of band pixels into a near and a far part, from their edge estimate (``bokehray.matting``).

One thread a band pixel, after ``bokehray_kernels.matting.matting_band_kernel``:

1. the model's alpha fused with the projection of the pixel's colour on its F-B line, each weighted by the inverse
   of its variance (float64; skipped when ``model_sd`` is negative);
2. the decision: the window holds an edge, F and B differ by more than ``min_contrast`` of the brighter, the
   alpha is mixed (on a sharp map also the colour's projection) or the map puts the pixel on the other side than
   its alpha says, and the near part is nearer;
3. for a split pixel: alpha clipped into ``[min_alpha, max_alpha]`` and (F, B) moved the least, per channel, so
   that ``alpha F + (1 - alpha) B`` is the photo's pixel (float64), each kept between 0 and its share's bound.

Oracle: ``tests/reference/split_ref.py``.
"""

import warp as wp

from .matting import BAND_OK, BAND_OWN_NEAR, BandEstimate

wp.set_module_options({"enable_backward": False})


@wp.struct
class SplitRule:
    """The split's constants (``bokehray.edge_estimate.MattingRule``) and the band's scale and offset."""

    min_alpha: float
    max_alpha: float
    min_contrast: float
    model_sd: float
    """< 0: the model's alpha alone (no fusion)."""
    sharp: int
    """1: the map's edges are steps (ramp width 0): the colour's projection must be mixed as well."""
    scale: float
    """The estimate's colours are in units of this (the image was divided by it)."""
    y0: int
    x0: int
    """The band box's corner in the photo."""


@wp.struct
class SplitOut:
    """One entry a band pixel: split or not, and a split pixel's alpha, F and B (in the photo's units)."""

    split: wp.array(dtype=wp.uint8)
    alpha: wp.array(dtype=float)
    fg: wp.array(dtype=wp.vec3)
    bg: wp.array(dtype=wp.vec3)


@wp.func
def fused_alpha(a32: float, c: wp.vec3, f: wp.vec3, b: wp.vec3, vf: wp.vec3, vb: wp.vec3, model_sd: float) -> float:
    """The model's alpha and the projection, fused by their inverse variances, in [0, 1]."""
    a = wp.float64(a32)
    d0 = wp.float64(f[0] - b[0])
    d1 = wp.float64(f[1] - b[1])
    d2 = wp.float64(f[2] - b[2])
    den = wp.max(d0 * d0 + d1 * d1 + d2 * d2, wp.float64(1.0e-30))
    proj = ((wp.float64(c[0]) - wp.float64(b[0])) * d0 + (wp.float64(c[1]) - wp.float64(b[1])) * d1
            + (wp.float64(c[2]) - wp.float64(b[2])) * d2) / den
    svf = wp.float64(vf[0]) + wp.float64(vf[1]) + wp.float64(vf[2])
    svb = wp.float64(vb[0]) + wp.float64(vb[1]) + wp.float64(vb[2])
    one = wp.float64(1.0)
    vp = (a * a * svf + (one - a) * (one - a) * svb) / den
    vm = wp.float64(model_sd) * wp.float64(model_sd)
    out = (a * vp + proj * vm) / (vp + vm)
    return float(wp.min(wp.max(out, wp.float64(0.0)), one))


@wp.func
def exact_channel(i: float, a: float, f: float, b: float, vf: float, vb: float) -> wp.vec2:
    """One channel's (F, B) moved the least (by ``dF^2 / vf + dB^2 / vb``) so that ``a F + (1 - a) B = i``, F kept
    between 0 and ``i / a``, B between 0 and ``i / (1 - a)``."""
    I = wp.float64(i)
    A = wp.float64(a)
    F = wp.float64(f)
    B = wp.float64(b)
    VF = wp.float64(vf)
    VB = wp.float64(vb)
    one = wp.float64(1.0)
    zero = wp.float64(0.0)
    r = I - A * F - (one - A) * B
    norm = A * A * VF + (one - A) * (one - A) * VB
    fn = F + r * A * VF / norm
    fn = wp.min(wp.max(fn, wp.min(zero, I / A)), wp.max(zero, I / A))
    bn = (I - A * fn) / (one - A)
    bn = wp.min(wp.max(bn, wp.min(zero, I / (one - A))), wp.max(zero, I / (one - A)))
    return wp.vec2(float(fn), float(bn))


@wp.func
def contrasted(f: wp.vec3, b: wp.vec3, min_contrast: float) -> bool:
    """F and B differ by more than ``min_contrast`` of the brighter of the two."""
    d = f - b
    den = d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
    bright = wp.max(f[0] * f[0] + f[1] * f[1] + f[2] * f[2], b[0] * b[0] + b[1] * b[1] + b[2] * b[2])
    return den > min_contrast * min_contrast * bright and den > 1.0e-20


@wp.func
def projection(c: wp.vec3, f: wp.vec3, b: wp.vec3) -> float:
    """The place of the colour ``c`` on the line from B (0) to F (1), in [0, 1]."""
    d = f - b
    den = d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
    p = ((c[0] - b[0]) * d[0] + (c[1] - b[1]) * d[1] + (c[2] - b[2]) * d[2]) / wp.max(den, 1.0e-30)
    return wp.min(wp.max(p, 0.0), 1.0)


@wp.kernel
def split_kernel(
    est: BandEstimate,
    image: wp.array2d(dtype=wp.vec3),
    photo: wp.array2d(dtype=wp.vec3),
    band_y: wp.array(dtype=wp.int32),
    band_x: wp.array(dtype=wp.int32),
    rule: SplitRule,
    out: SplitOut,
):
    i = wp.tid()
    py = band_y[i]
    px = band_x[i]
    f = est.fg[i]
    b = est.bg[i]
    vf = est.fg_var[i]
    vb = est.bg_var[i]
    c = image[py, px]
    alpha = est.alpha[i]
    if rule.model_sd >= 0.0:
        alpha = fused_alpha(alpha, c, f, b, vf, vb, rule.model_sd)
    mixed = alpha >= rule.min_alpha and alpha <= rule.max_alpha
    if rule.sharp != 0 and mixed:
        p = projection(c, f, b)
        mixed = p >= rule.min_alpha and p <= rule.max_alpha
    flags = est.flags[i]
    own_near = (flags & BAND_OWN_NEAR) != 0
    misplaced = (alpha < rule.min_alpha and own_near) or (alpha > rule.max_alpha and not own_near)
    split = ((flags & BAND_OK) != 0 and contrasted(f, b, rule.min_contrast) and (mixed or misplaced)
             and est.near_coc[i] > est.far_coc[i])
    if not split:
        out.split[i] = wp.uint8(0)
        return
    a = wp.min(wp.max(alpha, rule.min_alpha), rule.max_alpha)
    q = photo[rule.y0 + py, rule.x0 + px]
    fo = wp.vec3()
    bo = wp.vec3()
    for k in range(3):
        fk = f[k] * rule.scale
        bk = b[k] * rule.scale
        floor = 1.0e-4 * (f[k] * f[k] + b[k] * b[k]) + 1.0e-20
        fb = exact_channel(q[k], a, fk, bk, vf[k] + floor, vb[k] + floor)
        fo[k] = fb[0]
        bo[k] = fb[1]
    out.split[i] = wp.uint8(1)
    out.alpha[i] = a
    out.fg[i] = fo
    out.bg[i] = bo
