"""Ramps in a soft depth map read as edges (``bokehray.ramps.snap_ramps``).

A depth model's, a brush's or an upsampled map ramps over several pixels between a subject and its background;
each ramp pixel carries a depth no surface has. Two kernels:

1. :func:`ramp_plateau_kernel`: where the map's gradient magnitude (Sobel / 8, borders clamped) is at most
   ``grad_min`` (a plateau; elsewhere a ramp's pixel, a candidate).
2. :func:`snap_ramps_kernel`, one thread a candidate pixel (gradient above ``grad_min``): from the pixel, walk
   along the gradient both ways, one pixel a step (nearest sample), to the first pixel whose gradient is at most
   ``grad_min`` (a plateau) within ``max_walk`` steps. A pixel strictly inside such a ramp (its value rises
   through it by steps of more than 2 % of the range or ``grad_min``, whichever is less, and of less than half the
   range, between the two plateaus, over at least ``min_len`` steps) takes the value of one plateau: the
   side its colour is closer to along the line between the plateaus' colours (the mean of ``samples`` pixels
   from each plateau's start), weighed against its place in the ramp (``place_weight``). A ramp that does not
   end within ``max_walk`` on both sides is a slope (a floor, a wall going away) and stays.

Oracle: ``tests/reference/ramps_ref.py``.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.struct
class RampParams:
    """The rule's constants (``bokehray.ramps.RampOptions``)."""

    grad_min: float  # a plateau pixel's gradient is at most this (CoC px per px)
    max_walk: int  # the longest walk to a plateau (px); longer ramps are slopes
    min_range: float  # plateaus closer than this (CoC px) are one surface
    min_len: int  # the shortest ramp (steps from plateau to plateau) read as an edge
    samples: int  # plateau colour: the mean of this many pixels from the plateau's start outwards
    place: float  # a pixel's place in the ramp strictly inside (place, 1 - place)
    min_contrast: float  # plateau colours closer than this share of the brighter one say nothing
    place_weight: float  # the weight of the place in the ramp against the colour's evidence


@wp.func
def _clamp_at(v: float, n: int) -> int:
    return wp.clamp(int(wp.floor(v + 0.5)), 0, n - 1)


@wp.func
def _sobel(coc: wp.array2d(dtype=float), y: int, x: int) -> wp.vec2:
    """(d/dy, d/dx) of the map at (y, x): the Sobel operator over 8, borders clamped."""
    h = coc.shape[0]
    w = coc.shape[1]
    ym = wp.max(y - 1, 0)
    yp = wp.min(y + 1, h - 1)
    xm = wp.max(x - 1, 0)
    xp = wp.min(x + 1, w - 1)
    gy = (coc[yp, xm] + 2.0 * coc[yp, x] + coc[yp, xp]) - (coc[ym, xm] + 2.0 * coc[ym, x] + coc[ym, xp])
    gx = (coc[ym, xp] + 2.0 * coc[y, xp] + coc[yp, xp]) - (coc[ym, xm] + 2.0 * coc[y, xm] + coc[yp, xm])
    return wp.vec2(gy / 8.0, gx / 8.0)


@wp.kernel
def ramp_plateau_kernel(coc: wp.array2d(dtype=float), row0: int, grad_min: float, flat: wp.array2d(dtype=wp.uint8)):
    """1 where the map's gradient is at most ``grad_min`` (a plateau pixel), 0 where it is steeper (a ramp's
    candidate), for rows ``row0`` on (a launch of ``(rows,)``: a thread a row, a band of rows a CPU thread; a byte a
    pixel, a quarter of the float gradient's memory for the walks to read)."""
    t = wp.tid()
    y = row0 + t
    h = coc.shape[0]
    w = coc.shape[1]
    ym = wp.max(y - 1, 0)
    yp = wp.min(y + 1, h - 1)
    # the three rows' values at x - 1, x and x + 1 (clamped), slid along the row: _sobel's sums on them
    u0 = coc[ym, 0]
    m0 = coc[y, 0]
    d0 = coc[yp, 0]
    u1 = u0
    m1 = m0
    d1 = d0
    for x in range(w):
        xp = wp.min(x + 1, w - 1)
        u2 = coc[ym, xp]
        m2 = coc[y, xp]
        d2 = coc[yp, xp]
        gy = (d0 + 2.0 * d1 + d2) - (u0 + 2.0 * u1 + u2)
        gx = (u2 + 2.0 * m2 + d2) - (u0 + 2.0 * m0 + d0)
        if wp.length(wp.vec2(gy / 8.0, gx / 8.0)) <= grad_min:
            flat[y, x] = wp.uint8(1)
        else:
            flat[y, x] = wp.uint8(0)
        u0 = u1
        m0 = m1
        d0 = d1
        u1 = u2
        m1 = m2
        d1 = d2


@wp.func
def _inside(v: float, n: int) -> int:
    """1 when ``floor(v + 0.5)`` lies in [0, n - 1] for v (and so for any float between it and a pixel's own)."""
    if v >= 0.0 and v <= float(n - 1):
        return 1
    return 0


@wp.func
def _plateau(flat: wp.array2d(dtype=wp.uint8), y: float, x: float, ny: float, nx: float, params: RampParams) -> int:
    """Steps from (y, x) along (ny, nx) to the first pixel whose gradient is at most ``grad_min`` (``flat``); 0: none
    within ``max_walk``. A walk whose last step lies inside the frame is inside at every step (``y + k ny`` is
    monotone in k in floats too): it rounds without clamping."""
    h = flat.shape[0]
    w = flat.shape[1]
    far = float(params.max_walk)
    if _inside(y + far * ny, h) == 1 and _inside(x + far * nx, w) == 1:
        for k in range(1, params.max_walk + 1):
            fk = float(k)
            if flat[int(wp.floor(y + fk * ny + 0.5)), int(wp.floor(x + fk * nx + 0.5))] != wp.uint8(0):
                return k
        return 0
    for k in range(1, params.max_walk + 1):
        if flat[_clamp_at(y + float(k) * ny, h), _clamp_at(x + float(k) * nx, w)] != wp.uint8(0):
            return k
    return 0


@wp.func
def _plateau_colour(image: wp.array2d(dtype=wp.vec3), y: float, x: float, ny: float, nx: float, k0: int,
                    samples: int) -> wp.vec3:
    h = image.shape[0]
    w = image.shape[1]
    c = wp.vec3(0.0, 0.0, 0.0)
    for j in range(samples):
        k = float(k0 + j)
        c += image[_clamp_at(y + k * ny, h), _clamp_at(x + k * nx, w)]
    return c / float(samples)


@wp.kernel
def snap_ramps_kernel(
    image: wp.array2d(dtype=wp.vec3),
    coc: wp.array2d(dtype=float),
    flat: wp.array2d(dtype=wp.uint8),
    cand: wp.array(dtype=wp.int32),
    first: int,
    params: RampParams,
    value: wp.array(dtype=float),
    snapped: wp.array(dtype=wp.uint8),
):
    """Candidates ``first`` on (``cand``: row-major pixel indices; a launch of (count,)), their results at the same
    places of ``value`` and ``snapped``."""
    i = first + wp.tid()
    h = coc.shape[0]
    w = coc.shape[1]
    py = cand[i] / w
    px = cand[i] % w
    own = coc[py, px]
    value[i] = own
    snapped[i] = wp.uint8(0)
    g = _sobel(coc, py, px)
    gl = wp.length(g)
    if gl <= 0.0:
        return
    ny = g[0] / gl
    nx = g[1] / gl
    y = float(py)
    x = float(px)
    k_near = _plateau(flat, y, x, ny, nx, params)
    if k_near == 0:  # a slope (most candidates of a steep floor): the other side is not walked
        return
    k_far = _plateau(flat, y, x, -ny, -nx, params)
    if k_far == 0 or k_near + k_far < params.min_len:
        return
    v_near = coc[_clamp_at(y + float(k_near) * ny, h), _clamp_at(x + float(k_near) * nx, w)]
    v_far = coc[_clamp_at(y - float(k_far) * ny, h), _clamp_at(x - float(k_far) * nx, w)]
    span = v_near - v_far
    if span <= params.min_range:
        return
    # strictly inside the ramp: the value rises through the pixel by steps of more than 2 % of the range, or than a
    # plateau's gradient where that is less (a wide ramp's tails: kept, they were a step inside the subject beside
    # their snapped neighbours), and less than half of the range (a hard map's pixel between two others, where
    # three depths meet, has one step of half or more)
    up = coc[_clamp_at(y + ny, h), _clamp_at(x + nx, w)] - own
    down = own - coc[_clamp_at(y - ny, h), _clamp_at(x - nx, w)]
    if wp.min(up, down) <= wp.min(0.02 * span, params.grad_min) or wp.max(up, down) >= 0.5 * span:
        return
    t = (own - v_far) / span
    if t <= params.place or t >= 1.0 - params.place:
        return
    c_near = _plateau_colour(image, y, x, ny, nx, k_near, params.samples)
    c_far = _plateau_colour(image, y, x, -ny, -nx, k_far, params.samples)
    d = c_near - c_far
    den = wp.dot(d, d)
    bright = wp.max(wp.dot(c_near, c_near), wp.dot(c_far, c_far))
    score = params.place_weight * (t - 0.5)
    if den > params.min_contrast * params.min_contrast * bright and den > 1.0e-20:
        a = wp.dot(image[py, px] - c_far, d) / den
        score += wp.clamp(a, -0.5, 1.5) - 0.5
    if score > 0.0:
        value[i] = v_near
    else:
        value[i] = v_far
    snapped[i] = wp.uint8(1)
