"""Aperture shapes as horizontal chords.

A shape of circumradius ``rho`` centred at the origin is the CoC disc
intersected with one constraint per blade (rows of ``blades``, see
``bokehray.lens.Aperture.blade_discs``): ``(nx, ny, h, R)`` is the half-plane
``nx*x + ny*y <= h*rho`` when ``R == 0`` and otherwise the disc of radius
``R*rho`` centred at ``h*rho*(nx, ny)``. Every such shape is convex, so a
horizontal line cuts it in one interval, the chord, which is all the
row-span scatter needs.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.func
def chord(y: float, rho: float, blades: wp.array(dtype=wp.vec4), n_blades: int) -> wp.vec2:
    """Interval ``(x_lo, x_hi)`` of the shape on the line at height ``y``; empty when ``x_lo >= x_hi``."""
    q = rho * rho - y * y
    if q <= 0.0:
        return wp.vec2(0.0, 0.0)
    w = wp.sqrt(q)
    lo = -w
    hi = w
    for i in range(n_blades):
        b = blades[i]
        nx = b[0]
        ny = b[1]
        h = b[2] * rho
        big_r = b[3] * rho
        if b[3] == 0.0:
            rhs = h - ny * y
            if nx > 1.0e-7:
                hi = wp.min(hi, rhs / nx)
            elif nx < -1.0e-7:
                lo = wp.max(lo, rhs / nx)
            elif rhs < 0.0:
                hi = lo
        else:
            dy = y - h * ny
            qq = big_r * big_r - dy * dy
            if qq <= 0.0:
                hi = lo
            else:
                s = wp.sqrt(qq)
                cx = h * nx
                lo = wp.max(lo, cx - s)
                hi = wp.min(hi, cx + s)
    return wp.vec2(lo, hi)
