"""Soft maps' thin structures given back their depth (``bokehray.thin_depth.restore_thin``): the passes over the
frame, the window regressions and the hardening, each over what needs it only.

0. :func:`thin_ramp_kernel`, a thread a row: whether the map ramps anywhere (two steps in a row, along a row or a
   column, of the same sign and above ``grad_min``); rows started after a ramp is found are not read.
1. :func:`thin_level_kernel`, a thread a row of 2 x 2 blocks: the block's mean colour and map value, the map's
   smallest and largest value in it and its largest step to a right or lower neighbour. A block at an odd side
   repeats the last row / column (the index is clamped).
2. :func:`thin_fit_kernel`, a thread a run of samples along a row of a fit's grid (the samples whose window may be
   used): per window, the ridge regression of the map on the blurred colours, in float64 from the window's sums
   (the 3 x 3 solve is ill-conditioned where colours align), which slide along the run a column at a time.
3. :func:`thin_extremes_kernel`, a thread a usable block: the sharp model ``a . tone(photo) + b`` at its pixels,
   its largest and smallest value.
4. :func:`thin_harden_kernel`, a thread a block that holds a structure: each of its pixels at the far or the near
   value, written to the map where that moves it.

Oracles: ``tests/reference/thin_ref.py`` (``ramps_ref``, ``level_ref``, ``window_fit_ref``, ``extremes_ref``,
``harden_ref``).
"""

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.func
def _rising(d1: float, d2: float, g: float) -> int:
    """1 where two steps in a row are both above ``g``, or both below ``-g``."""
    if (d1 > g and d2 > g) or (d1 < -g and d2 < -g):
        return 1
    return 0


@wp.kernel
def thin_ramp_kernel(coc: wp.array2d(dtype=float), row0: int, grad_min: float, found: wp.array(dtype=wp.int32)):
    """Row ``row0 + t`` (a thread a row): ``found[0] = 1`` where two steps in a row start in it, along the row or down
    the columns, both above ``grad_min`` or both below ``-grad_min``; a row started once a ramp is found is not read
    (a soft map is known at its first ramp, a hard one is read once)."""
    y = row0 + wp.tid()
    if found[0] != 0:
        return
    h = coc.shape[0]
    w = coc.shape[1]
    for x in range(w):
        v = coc[y, x]
        if x + 2 < w:
            if _rising(coc[y, x + 1] - v, coc[y, x + 2] - coc[y, x + 1], grad_min) != 0:
                found[0] = 1
                return
        if y + 2 < h:
            if _rising(coc[y + 1, x] - v, coc[y + 2, x] - coc[y + 1, x], grad_min) != 0:
                found[0] = 1
                return


@wp.func
def _level_block(coc: wp.array2d(dtype=float), photo: wp.array2d(dtype=wp.vec3), i: int, j: int,
                 colour: wp.array2d(dtype=wp.vec3), mean: wp.array2d(dtype=float), low: wp.array2d(dtype=float),
                 high: wp.array2d(dtype=float), step: wp.array2d(dtype=float)):
    h = coc.shape[0]
    w = coc.shape[1]
    c = wp.vec3(0.0)
    m = float(0.0)
    lo = coc[wp.min(2 * i, h - 1), wp.min(2 * j, w - 1)]
    hi = lo
    st = float(0.0)
    for a in range(2):
        y = wp.min(2 * i + a, h - 1)
        for b in range(2):
            x = wp.min(2 * j + b, w - 1)
            v = coc[y, x]
            c = c + photo[y, x]
            m = m + v
            lo = wp.min(lo, v)
            hi = wp.max(hi, v)
            if y + 1 < h:
                st = wp.max(st, wp.abs(coc[y + 1, x] - v))
            if x + 1 < w:
                st = wp.max(st, wp.abs(coc[y, x + 1] - v))
    colour[i, j] = c * 0.25
    mean[i, j] = m * 0.25
    low[i, j] = lo
    high[i, j] = hi
    step[i, j] = st


@wp.kernel
def thin_level_kernel(coc: wp.array2d(dtype=float), photo: wp.array2d(dtype=wp.vec3), row0: int,
                      colour: wp.array2d(dtype=wp.vec3), mean: wp.array2d(dtype=float), low: wp.array2d(dtype=float),
                      high: wp.array2d(dtype=float), step: wp.array2d(dtype=float)):
    """The 2 x 2 blocks of row ``row0 + t`` of the half-resolution grid (a thread a row: no per-block overhead)."""
    t = wp.tid()
    i = row0 + t
    for j in range(colour.shape[1]):
        _level_block(coc, photo, i, j, colour, mean, low, high, step)


@wp.func
def _column(guide: wp.array2d(dtype=wp.vec3d), d: wp.array2d(dtype=wp.float64), y0: int, y1: int, x: int,
            y: int) -> wp.mat44d:
    """The sums over rows ``y0..y1`` of column ``x`` that a window's regression needs, as a 4 x 4 matrix: of the
    map, its square, the map times x and times the row's offset from ``y``; the colours; the colours times the map;
    the colours' six products."""
    zero = wp.float64(0.0)
    m = wp.mat44d(zero, zero, zero, zero, zero, zero, zero, zero, zero, zero, zero, zero, zero, zero, zero, zero)
    fx = wp.float64(x)
    for yy in range(y0, y1 + 1):
        v = d[yy, x]
        g = guide[yy, x]
        m += wp.mat44d(v, v * v, v * fx, v * wp.float64(yy - y), g[0], g[1], g[2], g[0] * v, g[1] * v, g[2] * v,
                       g[0] * g[0], g[0] * g[1], g[0] * g[2], g[1] * g[1], g[1] * g[2], g[2] * g[2])
    return m


@wp.kernel
def thin_fit_kernel(guide: wp.array2d(dtype=wp.vec3d), d: wp.array2d(dtype=wp.float64), ys: wp.array(dtype=wp.int32),
                    xs: wp.array(dtype=wp.int32), runs: wp.array(dtype=wp.int32), first: wp.array(dtype=wp.int32),
                    k: int, ridge: wp.float64, a: wp.array(dtype=wp.vec3d), b: wp.array(dtype=wp.float64),
                    res: wp.array(dtype=wp.float64), var: wp.array(dtype=wp.float64),
                    plane: wp.array(dtype=wp.float64)):
    """A run of ``runs[t]`` samples along a row, from sample ``first[t]`` (``ys``, ``xs``: the samples in row-major
    order): for each, over its window of radius ``k`` (cut at the grid's borders), the ridge regression
    ``d ~ a . guide + b``, its residual variance, the variance of ``d`` and the residual variance of the best plane.
    The window's sums slide along the run: a column added on the right, one taken off on the left."""
    t = wp.tid()
    i0 = first[t]
    y = ys[i0]
    x0 = xs[i0]
    w = d.shape[1]
    y0 = wp.max(y - k, 0)
    y1 = wp.min(y + k, d.shape[0] - 1)
    zero = wp.float64(0.0)
    sums = wp.mat44d(zero, zero, zero, zero, zero, zero, zero, zero, zero, zero, zero, zero, zero, zero, zero, zero)
    for xx in range(wp.max(x0 - k, 0), wp.min(x0 + k, w - 1) + 1):
        sums += _column(guide, d, y0, y1, xx, y)
    for i in range(runs[t]):
        x = x0 + i
        if i > 0:
            if x + k < w:
                sums += _column(guide, d, y0, y1, x + k, y)
            if x - k - 1 >= 0:
                sums -= _column(guide, d, y0, y1, x - k - 1, y)
        _window_fit(sums, wp.max(x - k, 0), wp.min(x + k, w - 1), x, y0, y1, y, ridge, i0 + i, a, b, res, var, plane)


@wp.func
def _window_fit(sums: wp.mat44d, x0: int, x1: int, x: int, y0: int, y1: int, y: int, ridge: wp.float64, o: int,
                a: wp.array(dtype=wp.vec3d), b: wp.array(dtype=wp.float64), res: wp.array(dtype=wp.float64),
                var: wp.array(dtype=wp.float64), plane: wp.array(dtype=wp.float64)):
    """The regression and the plane of one window from its sums (:func:`_column`'s), written at output ``o``."""
    zero = wp.float64(0.0)
    ny = y1 - y0 + 1
    nx = x1 - x0 + 1
    inv_n = wp.float64(1.0) / wp.float64(ny * nx)
    md = sums[0, 0] * inv_n
    mg = wp.vec3d(sums[1, 0], sums[1, 1], sums[1, 2]) * inv_n
    v_d = wp.max(sums[0, 1] * inv_n - md * md, zero)
    c = wp.vec3d(sums[1, 3], sums[2, 0], sums[2, 1]) * inv_n - mg * md
    c01 = sums[2, 3] * inv_n - mg[0] * mg[1]
    c02 = sums[3, 0] * inv_n - mg[0] * mg[2]
    c12 = sums[3, 2] * inv_n - mg[1] * mg[2]
    cov = wp.mat33d(sums[2, 2] * inv_n - mg[0] * mg[0], c01, c02, c01, sums[3, 1] * inv_n - mg[1] * mg[1], c12, c02,
                    c12, sums[3, 3] * inv_n - mg[2] * mg[2])
    coef = _solve3(cov, c, ridge)
    a[o] = coef
    b[o] = md - wp.dot(coef, mg)
    res[o] = wp.max(v_d - wp.float64(2.0) * wp.dot(coef, c) + wp.dot(coef, cov * coef), zero)
    var[o] = v_d
    # the plane: x and y over a rectangle are uncorrelated; their means and variances are a run of integers'
    mx = wp.float64(x0 + x1) * wp.float64(0.5)
    my = wp.float64(y0 + y1) * wp.float64(0.5) - wp.float64(y)
    vx = wp.float64(nx * nx - 1) / wp.float64(12.0)
    vy = wp.float64(ny * ny - 1) / wp.float64(12.0)
    cx = sums[0, 2] * inv_n - md * mx
    cy = sums[0, 3] * inv_n - md * my
    plane[o] = wp.max(v_d - cx * cx / vx - cy * cy / vy, zero)


@wp.func
def _solve3(cov: wp.mat33d, c: wp.vec3d, ridge: wp.float64) -> wp.vec3d:
    """``(cov + ridge I)^-1 c`` for the symmetric positive semi-definite ``cov``, by cofactors (the ridge bounds the
    determinant)."""
    a00 = cov[0, 0] + ridge
    a11 = cov[1, 1] + ridge
    a22 = cov[2, 2] + ridge
    a01 = cov[0, 1]
    a02 = cov[0, 2]
    a12 = cov[1, 2]
    i00 = a11 * a22 - a12 * a12
    i01 = a02 * a12 - a01 * a22
    i02 = a01 * a12 - a02 * a11
    i11 = a00 * a22 - a02 * a02
    i12 = a01 * a02 - a00 * a12
    i22 = a00 * a11 - a01 * a01
    det = a00 * i00 + a01 * i01 + a02 * i02
    inv = wp.float64(1.0) / wp.max(det, ridge * ridge * ridge)
    return wp.vec3d((i00 * c[0] + i01 * c[1] + i02 * c[2]) * inv, (i01 * c[0] + i11 * c[1] + i12 * c[2]) * inv,
                    (i02 * c[0] + i12 * c[1] + i22 * c[2]) * inv)


@wp.func
def _tone(c: wp.vec3) -> wp.vec3:
    """The regression's colour, ``c / (1 + max(c, 0))`` (``bokehray.thin_depth.tone``)."""
    return wp.vec3(c[0] / (1.0 + wp.max(c[0], 0.0)), c[1] / (1.0 + wp.max(c[1], 0.0)), c[2] / (1.0 + wp.max(c[2], 0.0)))


@wp.func
def _estimate(photo: wp.array2d(dtype=wp.vec3), y: int, x: int, a: wp.vec3, b: float) -> float:
    g = _tone(photo[y, x])
    return a[0] * g[0] + a[1] * g[1] + a[2] * g[2] + b


@wp.kernel
def thin_extremes_kernel(photo: wp.array2d(dtype=wp.vec3), iy: wp.array(dtype=wp.int32), ix: wp.array(dtype=wp.int32),
                         a: wp.array(dtype=wp.vec3), b: wp.array(dtype=float), f: int, est: wp.array3d(dtype=float),
                         top: wp.array(dtype=float), bottom: wp.array(dtype=float)):
    """Block ``t`` (grid sample ``(iy[t], ix[t])``, ``f x f`` pixels, the last row / column repeated at the image's
    edge): the sharp model ``a . tone(photo) + b`` at its pixels, and its largest and smallest value."""
    t = wp.tid()
    h = photo.shape[0]
    w = photo.shape[1]
    hi = float(-1.0e30)
    lo = float(1.0e30)
    for p in range(f):
        y = wp.min(iy[t] * f + p, h - 1)
        for q in range(f):
            e = _estimate(photo, y, wp.min(ix[t] * f + q, w - 1), a[t], b[t])
            est[t, p, q] = e
            hi = wp.max(hi, e)
            lo = wp.min(lo, e)
    top[t] = hi
    bottom[t] = lo


@wp.struct
class HardenParams:
    """What :func:`thin_harden_kernel` needs beyond the blocks (``bokehray.thin_depth``'s normalisation and rule)."""

    f: int  # the blocks' size (px)
    centre: float  # the map is normalised as (s - centre) / scale
    scale: float
    keep: float  # a pixel in the lowest ``keep`` of its window's map range is not moved near ...
    keep_top: float  # ... nor one above ``keep_top`` (``1 - keep``) far
    lo: float  # the values written are clamped to [lo, hi]
    hi: float


@wp.kernel
def thin_harden_kernel(photo: wp.array2d(dtype=wp.vec3), coc: wp.array2d(dtype=float), iy: wp.array(dtype=wp.int32),
                       ix: wp.array(dtype=wp.int32), a: wp.array(dtype=wp.vec3), b: wp.array(dtype=float),
                       far: wp.array(dtype=float), near: wp.array(dtype=float), top: wp.array(dtype=float),
                       p: HardenParams, out: wp.array2d(dtype=float), moved: wp.array(dtype=wp.int32)):
    """Each pixel block ``t`` holds (not the repeats at the image's edge) at its window's far or near value
    (normalised): near where its sharp model ``a . tone(photo) + b`` is past the middle of the two and its map value
    lies above the lowest ``keep`` of the window's map range ``[far, top]``, or where the map value lies in its
    highest ``keep``. The value, back in CoC px and clamped, is written to ``out`` where it differs from ``coc``;
    ``moved[0]`` counts those pixels."""
    t = wp.tid()
    h = coc.shape[0]
    w = coc.shape[1]
    lo = far[t]
    hi = near[t]
    mid = 0.5 * (lo + hi)
    span = wp.max(top[t] - lo, 1.0e-12)
    for i in range(p.f):
        y = iy[t] * p.f + i
        for j in range(p.f):
            x = ix[t] * p.f + j
            if y < h and x < w:
                d = (coc[y, x] - p.centre) / p.scale
                place = (d - lo) / span
                hard = lo
                if (wp.max(_estimate(photo, y, x, a[t], b[t]), lo) > mid and place > p.keep) or place > p.keep_top:
                    hard = hi
                if hard != d:
                    v = wp.clamp(hard * p.scale + p.centre, p.lo, p.hi)
                    if v != coc[y, x]:
                        out[y, x] = v
                        wp.atomic_add(moved, 0, 1)
