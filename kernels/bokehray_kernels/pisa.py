"""PISA physics masks (BokehDiff sec. 3.2, eq. 5-8), windowed.

Both kernels fill a *key-centric window*: entry ``[y, x, o]`` describes the pair
(key ``k = (y, x)``, query ``q = k + off(o)``) with ``off(o) = (o // n - w, o % n - w)``
and ``n = 2w + 1``. Key-centric because PISA normalises over the *query* axis
(eq. 2): one key's whole column sits in one contiguous row of the window.
Pairs whose query falls outside the image are 0 in both masks.

Units are latent pixels: ``k_lat`` is the CoC gain K rescaled to the latent
grid, so the CoC radius of a key is ``r_c(k) = k_lat * |d_k - d_f|`` (eq. 5).
The float64 NumPy oracle is ``tests/reference/pisa_ref.py``.
"""

import warp as wp

from .sampling import bilinear_taps

wp.set_module_options({"enable_backward": False})

# Collinearity models for eq. 7 (see docs/refiner.md, "Occlusion geometry").
COLLINEAR_THIN_LENS = 0
COLLINEAR_PAPER = 1

_GOLDEN_ANGLE = 2.399963229728653


@wp.func
def soft_edge(x: float, slope: float) -> float:
    """``sigmoid(slope * x)`` without overflow: ~1 inside the circle (x > 0), ~0 outside."""
    t = slope * x
    if t >= 0.0:
        return 1.0 / (1.0 + wp.exp(-t))
    e = wp.exp(t)
    return e / (1.0 + e)


@wp.func
def source_offset(j: int, n: int, sigma: float) -> wp.vec2:
    """Offset of the j-th of n jittered light sources around a key (eq. 8).

    A deterministic quasi-Monte-Carlo sample of N(0, sigma^2 I) whose mean is exactly the key:
    for odd n, source 0 sits on the key; the others come in mirrored pairs ``+-p_m`` at
    golden-angle directions with radii ``sigma * sqrt(-2 ln(1 - u_m))``, ``u_m = (m + 0.5) / M``
    for ``M`` pairs.
    """
    odd = n % 2
    if n <= 1 or (odd == 1 and j == 0):
        return wp.vec2(0.0, 0.0)
    idx = j - odd
    m = idx // 2
    sign = 1.0 - 2.0 * float(idx % 2)
    pairs = (n - odd) // 2
    u = (float(m) + 0.5) / float(pairs)
    rad = sign * sigma * wp.sqrt(-2.0 * wp.log(1.0 - u))
    a = float(m) * _GOLDEN_ANGLE
    return wp.vec2(rad * wp.cos(a), rad * wp.sin(a))


@wp.func
def disparity_at(disp: wp.array2d(dtype=float), px: float, py: float) -> float:
    h = disp.shape[0]
    w = disp.shape[1]
    t = bilinear_taps(px, py, h, w)
    top = disp[t.y0, t.x0] * (1.0 - t.tx) + disp[t.y0, t.x1] * t.tx
    bot = disp[t.y1, t.x0] * (1.0 - t.tx) + disp[t.y1, t.x1] * t.tx
    return top * (1.0 - t.ty) + bot * t.ty


@wp.func
def collinear_point(
    q: wp.vec2, ps: wp.vec2, ds: float, dt: float, d_f: float, k_lat: float, model: int, eps: float
) -> wp.vec2:
    """Image position of the point at disparity ``dt`` on the ray from source ``ps`` to sensor pixel ``q``.

    Thin lens: a ray through aperture point ``u`` (unit disc) reaching pixel ``q`` passes, at
    disparity ``d``, over image position ``q + k_lat * (d - d_f) * u``; the source fixes
    ``u = (ps - q) / (k_lat * (ds - d_f))``, clamped to the disc (no ray enters outside the
    aperture). Paper (eq. 7): ``q + f * (ps - q)`` with ``f = (1 - dt) ds / ((1 - ds) dt)``,
    singular at ``ds -> 1`` and ``dt -> 0``: both are clamped by ``eps``.
    """
    g = ps - q
    if model == COLLINEAR_PAPER:
        ds_c = wp.min(ds, 1.0 - eps)
        dt_c = wp.max(dt, eps)
        f = (1.0 - dt_c) * ds_c / ((1.0 - ds_c) * dt_c)
        return q + f * g
    den = k_lat * (ds - d_f)
    glen = wp.length(g)
    u = wp.vec2(0.0, 0.0)
    if wp.abs(den) > eps:
        u = g / den
    elif glen > 0.0:
        u = g / glen  # in-focus source seen from off its pixel: the aperture's rim
    ulen = wp.length(u)
    if ulen > 1.0:
        u = u / ulen
    return q + (k_lat * (dt - d_f)) * u


@wp.kernel
def pisa_coc_kernel(
    disp: wp.array2d(dtype=float),
    d_f: float,
    k_lat: float,
    dist_scale: float,
    slope: float,
    w: int,
    out: wp.array3d(dtype=float),
):
    """CoC constraint ``C[q, k] = Soft(r_c(k) - c |P_q - P_k|)`` (eq. 6) over the key-centric window."""
    y, x, o = wp.tid()
    n = 2 * w + 1
    oy = o // n - w
    ox = o % n - w
    qy = y + oy
    qx = x + ox
    if qy < 0 or qy >= disp.shape[0] or qx < 0 or qx >= disp.shape[1]:
        out[y, x, o] = 0.0
        return
    r = k_lat * wp.abs(disp[y, x] - d_f)
    dist = wp.sqrt(float(oy * oy + ox * ox))
    out[y, x, o] = soft_edge(r - dist_scale * dist, slope)


@wp.kernel
def pisa_visibility_kernel(
    disp: wp.array2d(dtype=float),
    d_f: float,
    k_lat: float,
    w: int,
    n_sources: int,
    source_sigma: float,
    n_steps: int,
    margin: float,
    model: int,
    eps: float,
    out: wp.array3d(dtype=float),
):
    """Visibility ``E_s[M_vis]`` (eq. 7-8) over the key-centric window.

    For each jittered source ``s`` near the key (disparity ``d_s`` read bilinearly),
    the ray towards the query is sampled at ``n_steps`` stratified disparities
    ``d~ in (d_s, 1)``; it is blocked where the scene at the collinear point
    (nearest texel) is nearer than ``d~ + margin``. Collinear points outside the
    image do not block.
    """
    y, x, o = wp.tid()
    h = disp.shape[0]
    wd = disp.shape[1]
    n = 2 * w + 1
    oy = o // n - w
    ox = o % n - w
    qy = y + oy
    qx = x + ox
    if qy < 0 or qy >= h or qx < 0 or qx >= wd:
        out[y, x, o] = 0.0
        return
    q = wp.vec2(float(qx), float(qy))
    acc = float(0.0)
    for j in range(n_sources):
        ps = wp.vec2(float(x), float(y)) + source_offset(j, n_sources, source_sigma)
        ds = disparity_at(disp, ps[0], ps[1])
        visible = float(1.0)
        for i in range(n_steps):
            dt = ds + (1.0 - ds) * (float(i) + 0.5) / float(n_steps)
            p = collinear_point(q, ps, ds, dt, d_f, k_lat, model, eps)
            ix = int(wp.floor(p[0] + 0.5))
            iy = int(wp.floor(p[1] + 0.5))
            if ix >= 0 and ix < wd and iy >= 0 and iy < h:
                if disp[iy, ix] > dt + margin:
                    visible = 0.0
        acc += visible
    out[y, x, o] = acc / float(n_sources)
