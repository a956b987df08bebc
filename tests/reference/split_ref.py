"""Slow, obvious float64 reference for ``bokehray_kernels.split.split_kernel``: one band pixel at a time, plain
loops (the fused alpha is ``matting_ref.fuse_alpha_ref``)."""

from reference.matting_ref import fuse_alpha_ref

OK, OWN_NEAR = 1, 2


def composite_exact(i, a, f, b, vf, vb):
    """One channel's (F, B) moved the least (by dF^2 / vf + dB^2 / vb) so that a F + (1 - a) B = i, F kept between
    0 and i / a, B between 0 and i / (1 - a)."""
    r = i - a * f - (1 - a) * b
    fn = f + r * a * vf / (a * a * vf + (1 - a) ** 2 * vb)
    fn = min(max(fn, min(0.0, i / a)), max(0.0, i / a))
    bn = (i - a * fn) / (1 - a)
    return fn, min(max(bn, min(0.0, i / (1 - a))), max(0.0, i / (1 - a)))


def split_pixel(alpha, c, f, b, vf, vb, near, far, flags, q, *, scale, min_alpha, max_alpha, min_contrast, model_sd,
                sharp):
    """(split, alpha, F, B) of one band pixel: ``c`` its colour in the estimate's units (the image over ``scale``),
    ``q`` its colour in the photo; F and B come back in the photo's units."""
    f, b, c, vf, vb = ([float(v) for v in x] for x in (f, b, c, vf, vb))
    a = float(alpha) if model_sd is None else float(fuse_alpha_ref([alpha], [c], [f], [b], [vf], [vb], model_sd)[0])
    d = [f[k] - b[k] for k in range(3)]
    den = sum(x * x for x in d)
    mixed = min_alpha <= a <= max_alpha
    if sharp:
        p = min(1.0, max(0.0, sum((c[k] - b[k]) * d[k] for k in range(3)) / max(den, 1e-30)))
        mixed = mixed and min_alpha <= p <= max_alpha
    own_near = bool(flags & OWN_NEAR)
    misplaced = (a < min_alpha and own_near) or (a > max_alpha and not own_near)
    bright = max(sum(x * x for x in f), sum(x * x for x in b))
    contrast = den > min_contrast ** 2 * bright and den > 1e-20
    if not (flags & OK and contrast and (mixed or misplaced) and near > far):
        return False, None, None, None
    a = min(max(a, min_alpha), max_alpha)
    fb = [composite_exact(float(q[k]), a, f[k] * scale, b[k] * scale, vf[k] + 1e-4 * (f[k] ** 2 + b[k] ** 2) + 1e-20,
                          vb[k] + 1e-4 * (f[k] ** 2 + b[k] ** 2) + 1e-20) for k in range(3)]
    return True, a, [x[0] for x in fb], [x[1] for x in fb]
