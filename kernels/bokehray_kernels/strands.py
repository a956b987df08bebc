"""Strands broken in the map bridged where the photo shows them whole (``bokehray.strands.bridge_strands``).

A strand thinner than about a pixel (a grass stem, a hair, a wire) gets its depth only where its coverage reaches
1/2: its map is a row of dashes, and the pixels between two dashes keep the background's depth while they hold a
share of the strand's colour. Two kernels:

1. :func:`strand_pixels_kernel`: the map's strand pixels, nearer by more than ``jump_px`` than a pixel within
   ``thin_px`` on both sides along one of the four axes (a structure at most ``2 thin_px - 1`` px across; outside
   the frame counts as farther).
2. :func:`bridge_strands_kernel`, one thread a strand pixel ``q1``: for every strand pixel ``q2`` of the same
   depth (within ``jump_px``) in the half window ``offsets`` (``q2`` after ``q1`` in row-major order, 2 to
   ``max_gap`` px away) such that both end their dashes towards each other (neither has an 8-neighbour of its own
   depth on the other's side), the pixels of the segment between them (one a step along its longer axis,
   rounded) that the map puts behind the strand are a gap. The gap is bridged, each of its pixels given the mean of the two ends'
   values (``atomic_max``: the nearest bridge wins, whatever the threads' order), when for every gap pixel ``p``:

   * the map is thin across the segment: the pixels 1 and 2 px from ``p`` on both sides across it (Chebyshev
     steps) are behind the strand too, or outside the frame (a gap inside a strand, not a notch in a solid
     outline);
   * the photo shows the strand there: ``p``'s colour, on the line from the background ``B`` (the mean of the two
     pixels 2 px across) to the strand ``F`` (the mean of the ends' colours), lies at least ``min_share`` of the
     way to ``F`` and at most ``max_off`` of ``|F - B|`` off the line (``B``: the one inside the frame at a border); ``|F - B|`` must exceed ``min_contrast``
     of the brighter of the two, and neither ``F`` nor ``B`` may be a light's colour (mean above ``light_level``).
     A gap the photo shows as background (a hole in a mesh) stays.

   The same thread then extends ``q1`` if it ends a dash (:func:`_extend_end`): away from its dash's pixels within
   2 px, when it and the pixel before it are thin across that way, over at most ``end_px`` pixels behind it, each
   passing the same test with ``F`` the end's colour and ``B`` on one surface with the pixel. Every raise above a
   pixel's map value is counted once, in ``changed`` (the host's count of changed pixels).

Oracle: ``tests/reference/strands_ref.py``.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.struct
class StrandParams:
    """The rule's constants (``bokehray.strands.StrandRule``)."""

    jump_px: float  # nearer / farther: a CoC difference of more than this (px)
    thin_px: int  # a strand pixel has a farther pixel within this on both sides along one axis
    min_share: float  # a gap pixel's colour lies at least this far from B towards F
    max_off: float  # ... and at most this share of |F - B| off the B-F line
    min_contrast: float  # |F - B| above this share of the brighter of the two
    end_px: int  # a dash end is extended along its strand by at most this many px
    light_level: float  # a colour whose mean of RGB is above this is a light's (linear; 1: a white surface)


@wp.func
def _farther(coc: wp.array2d(dtype=float), y: int, x: int, level: float) -> int:
    """1 when (y, x) lies outside the map (nothing nearer there) or its value is below ``level``."""
    if y < 0 or y >= coc.shape[0] or x < 0 or x >= coc.shape[1]:
        return 1
    if coc[y, x] < level:
        return 1
    return 0


@wp.func
def _thin_along(coc: wp.array2d(dtype=float), y: int, x: int, dy: int, dx: int, level: float, n: int) -> int:
    """1 when a pixel below ``level`` lies within ``n`` px of (y, x) both ways along (dy, dx)."""
    for k in range(1, n + 1):
        if _farther(coc, y + k * dy, x + k * dx, level) == 1:
            for j in range(1, n + 1):
                if _farther(coc, y - j * dy, x - j * dx, level) == 1:
                    return 1
            return 0
    return 0


@wp.func
def _is_strand(coc: wp.array2d(dtype=float), y: int, x: int, params: StrandParams) -> int:
    """1 when (y, x) is nearer by more than ``jump_px`` than a pixel within ``thin_px`` on both sides along one of
    the four axes."""
    level = coc[y, x] - params.jump_px
    n = params.thin_px
    if _thin_along(coc, y, x, 0, 1, level, n) == 1 or _thin_along(coc, y, x, 1, 0, level, n) == 1:
        return 1
    if _thin_along(coc, y, x, 1, 1, level, n) == 1 or _thin_along(coc, y, x, 1, -1, level, n) == 1:
        return 1
    return 0


@wp.kernel
def strand_pixels_kernel(coc: wp.array2d(dtype=float), params: StrandParams, tile_y: wp.array(dtype=wp.int32),
                         tile_x: wp.array(dtype=wp.int32), tile: int, strand: wp.array2d(dtype=wp.uint8),
                         slot: wp.array2d(dtype=wp.uint8)):
    """The pixels of the ``tile`` x ``tile`` tiles whose corners are (``tile_y``, ``tile_x``) (a launch of (tiles,
    tile): a thread a tile's row), in the map ``strand`` and a tile's slot ``slot[i, r * tile + c]`` (so that the
    host finds them among the tiles' pixels, not the frame's); pixels outside the map are skipped."""
    i, r = wp.tid()
    y = tile_y[i] + r
    if y >= coc.shape[0]:
        return
    for c in range(tile):
        x = tile_x[i] + c
        if x < coc.shape[1]:
            t = _is_strand(coc, y, x, params)
            strand[y, x] = wp.uint8(t)
            slot[i, r * tile + c] = wp.uint8(t)


@wp.func
def _round(v: float) -> int:
    return int(wp.floor(v + 0.5))


@wp.func
def _thin_across(coc: wp.array2d(dtype=float), py: int, px: int, ny: float, nx: float, level: float) -> int:
    """1 when the pixels 1 and 2 px from (py, px) on both sides along (ny, nx) are behind ``level`` (or outside)."""
    for m in range(1, 3):
        fm = float(m)
        if _farther(coc, py + _round(fm * ny), px + _round(fm * nx), level) == 0:
            return 0
        if _farther(coc, py - _round(fm * ny), px - _round(fm * nx), level) == 0:
            return 0
    return 1


@wp.func
def _background_across(image: wp.array2d(dtype=wp.vec3), coc: wp.array2d(dtype=float), py: int, px: int, ny: float,
                       nx: float, flat: float) -> wp.vec4:
    """The mean colour of the pixels 2 px from (py, px) on both sides along (ny, nx) inside the frame, and their
    count (0: none, or with ``flat`` >= 0 one of them further than ``flat`` from the pixel's CoC)."""
    b = wp.vec3(0.0, 0.0, 0.0)
    nb = float(0.0)
    for side in range(2):
        sg = 1.0 - 2.0 * float(side)
        qy = py + _round(sg * 2.0 * ny)
        qx = px + _round(sg * 2.0 * nx)
        if qy >= 0 and qy < coc.shape[0] and qx >= 0 and qx < coc.shape[1]:
            if flat >= 0.0 and wp.abs(coc[qy, qx] - coc[py, px]) > flat:
                return wp.vec4(0.0, 0.0, 0.0, 0.0)
            b += image[qy, qx]
            nb += 1.0
    if nb == 0.0:
        return wp.vec4(0.0, 0.0, 0.0, 0.0)
    return wp.vec4(b[0] / nb, b[1] / nb, b[2] / nb, nb)


@wp.func
def _shows_strand(c: wp.vec3, f: wp.vec3, b: wp.vec3, params: StrandParams) -> int:
    """1 when colour ``c`` lies on the line from the background ``b`` to the strand ``f``, at least ``min_share``
    of the way and at most ``max_off`` of ``|f - b|`` off it, ``|f - b|`` above ``min_contrast`` of the brighter,
    and neither ``f`` nor ``b`` a light's colour (over a light the test cannot read the strand's share)."""
    lit = params.light_level * 3.0
    if f[0] + f[1] + f[2] > lit or b[0] + b[1] + b[2] > lit:
        return 0
    d = f - b
    den = wp.dot(d, d)
    bright = wp.max(wp.dot(f, f), wp.dot(b, b))
    if den <= params.min_contrast * params.min_contrast * bright or den <= 1.0e-20:
        return 0
    r = c - b
    a = wp.dot(r, d) / den
    off = r - a * d
    if a < params.min_share or wp.dot(off, off) > params.max_off * params.max_off * den:
        return 0
    return 1


@wp.func
def _gap_pixel_ok(image: wp.array2d(dtype=wp.vec3), coc: wp.array2d(dtype=float), py: int, px: int, ny: float,
                  nx: float, level: float, f: wp.vec3, flat: float, params: StrandParams) -> int:
    """1 when gap pixel (py, px) is thin across the segment (normal (ny, nx), Chebyshev length 1) and its colour
    continues the strand's ``f`` over the background 2 px across; with ``flat`` >= 0 that background must also lie
    within ``flat`` of the pixel's own CoC (one surface behind the strand, not a third object's edge)."""
    if _thin_across(coc, py, px, ny, nx, level) == 0:
        return 0
    bq = _background_across(image, coc, py, px, ny, nx, flat)
    if bq[3] == 0.0:
        return 0
    return _shows_strand(image[py, px], f, wp.vec3(bq[0], bq[1], bq[2]), params)


@wp.func
def _ends_towards(coc: wp.array2d(dtype=float), y: int, x: int, oy: int, ox: int, jump: float) -> int:
    """1 when (y, x) ends its dash towards (oy, ox): none of its 8-neighbours of its own depth (within ``jump``)
    lies on that side (a dot product with (oy, ox) above 0)."""
    v = coc[y, x]
    for dy in range(-1, 2):
        for dx in range(-1, 2):
            if dy * oy + dx * ox > 0:
                yy = y + dy
                xx = x + dx
                if yy >= 0 and yy < coc.shape[0] and xx >= 0 and xx < coc.shape[1]:
                    if wp.abs(coc[yy, xx] - v) <= jump:
                        return 0
    return 1


@wp.func
def _raise(out: wp.array2d(dtype=float), changed: wp.array(dtype=wp.int32), y: int, x: int, v: float, was: float):
    """``out[y, x] = max(out[y, x], v)`` (the nearest wins, whatever the threads' order); ``changed[0]`` counts the
    pixel once, at the first raise above its map value ``was``."""
    old = wp.atomic_max(out, y, x, v)
    if old == was and v > old:
        wp.atomic_add(changed, 0, 1)


@wp.func
def _bridge(image: wp.array2d(dtype=wp.vec3), coc: wp.array2d(dtype=float), y1: int, x1: int, oy: int, ox: int,
            params: StrandParams, out: wp.array2d(dtype=float), changed: wp.array(dtype=wp.int32)):
    """Bridge the gap between strand pixels (y1, x1) and (y1 + oy, x1 + ox) when the photo shows it whole."""
    y2 = y1 + oy
    x2 = x1 + ox
    v = 0.5 * (coc[y1, x1] + coc[y2, x2])
    level = wp.min(coc[y1, x1], coc[y2, x2]) - params.jump_px
    f = 0.5 * (image[y1, x1] + image[y2, x2])
    steps = wp.max(wp.abs(oy), wp.abs(ox))
    ny = float(ox) / float(steps)  # the normal across the segment, Chebyshev length 1
    nx = -float(oy) / float(steps)
    gaps = int(0)
    for k in range(1, steps):
        t = float(k) / float(steps)
        py = y1 + _round(t * float(oy))
        px = x1 + _round(t * float(ox))
        if coc[py, px] < level:
            if _gap_pixel_ok(image, coc, py, px, ny, nx, level, f, -1.0, params) == 0:
                return
            gaps += 1
    if gaps == 0:
        return
    for k in range(1, steps):
        t = float(k) / float(steps)
        py = y1 + _round(t * float(oy))
        px = x1 + _round(t * float(ox))
        if coc[py, px] < level:
            _raise(out, changed, py, px, v, coc[py, px])


@wp.func
def _own(coc: wp.array2d(dtype=float), y: int, x: int, v: float, jump: float) -> int:
    """1 when (y, x) lies inside the map within ``jump`` of ``v``."""
    if y < 0 or y >= coc.shape[0] or x < 0 or x >= coc.shape[1]:
        return 0
    if wp.abs(coc[y, x] - v) <= jump:
        return 1
    return 0


@wp.func
def _own_ring(coc: wp.array2d(dtype=float), y: int, x: int, jump: float) -> int:
    """The 8-neighbours of (y, x) inside the map within ``jump`` of its value: bit ``(dy + 1) * 3 + (dx + 1)``."""
    v = coc[y, x]
    near = int(0)
    for dy in range(-1, 2):
        for dx in range(-1, 2):
            if (dy != 0 or dx != 0) and _own(coc, y + dy, x + dx, v, jump) == 1:
                near = near | (1 << ((dy + 1) * 3 + dx + 1))
    return near


@wp.func
def _ends_in_ring(near: int, oy: int, ox: int) -> int:
    """:func:`_ends_towards` from the pixel's :func:`_own_ring` ``near``: 1 when none of its neighbours of its own
    depth lies on the side of (oy, ox)."""
    for dy in range(-1, 2):
        for dx in range(-1, 2):
            if dy * oy + dx * ox > 0 and (near >> ((dy + 1) * 3 + dx + 1)) & 1 == 1:
                return 0
    return 1


@wp.func
def _joined(near: int, dy: int, dx: int) -> int:
    """1 when offset (dy, dx) (within 2 px, not 0) is an 8-neighbour or 8-adjacent to one set in ``near``."""
    if dy == 0 and dx == 0:
        return 0
    if wp.abs(dy) <= 1 and wp.abs(dx) <= 1:
        return 1
    for my in range(wp.max(dy - 1, -1), wp.min(dy + 1, 1) + 1):
        for mx in range(wp.max(dx - 1, -1), wp.min(dx + 1, 1) + 1):
            if (near >> ((my + 1) * 3 + mx + 1)) & 1 == 1:
                return 1
    return 0


@wp.func
def _way_out(coc: wp.array2d(dtype=float), y1: int, x1: int, near: int, jump: float) -> wp.vec2i:
    """The summed offset of the pixels of (y1, x1)'s dash within 2 px (of its depth and joined to it: an
    8-neighbour, or 8-adjacent to one), negated: the way out of a dash end; (0, 0) for a lone pixel, a pixel inside
    a strand or of a body (more than 8 such pixels), and one with a pixel of its depth among its 8-neighbours on
    that side. ``near``: its :func:`_own_ring`."""
    v = coc[y1, x1]
    if near == 0:
        return wp.vec2i(0, 0)
    sy = int(0)
    sx = int(0)
    count = int(0)
    for dy in range(-2, 3):
        for dx in range(-2, 3):
            if _joined(near, dy, dx) == 1 and _own(coc, y1 + dy, x1 + dx, v, jump) == 1:
                sy += dy
                sx += dx
                count += 1
    if count > 8 or (sy == 0 and sx == 0):
        return wp.vec2i(0, 0)
    if _ends_in_ring(near, -sy, -sx) == 0:
        return wp.vec2i(0, 0)
    return wp.vec2i(-sy, -sx)


@wp.func
def _is_tip(coc: wp.array2d(dtype=float), y1: int, x1: int, uy: float, ux: float, params: StrandParams) -> int:
    """1 when the pixel before (y1, x1) along the way out (uy, ux) is of its depth and both are thin across that
    way: a strand's tip, not the side of a wider strand, a step of a whole one or a notch in a solid outline."""
    by = y1 - _round(uy)
    bx = x1 - _round(ux)
    if by < 0 or by >= coc.shape[0] or bx < 0 or bx >= coc.shape[1]:
        return 0
    v = coc[y1, x1]
    if wp.abs(coc[by, bx] - v) > params.jump_px:
        return 0
    level = v - params.jump_px
    ny = _round(ux)
    nx = -_round(uy)
    if _thin_along(coc, y1, x1, ny, nx, level, params.thin_px) == 0:
        return 0
    return _thin_along(coc, by, bx, ny, nx, level, params.thin_px)


@wp.func
def _extend_end(image: wp.array2d(dtype=wp.vec3), coc: wp.array2d(dtype=float), y1: int, x1: int, near: int,
                params: StrandParams, out: wp.array2d(dtype=float), changed: wp.array(dtype=wp.int32)):
    """Extend the dash ending at strand pixel (y1, x1) along its strand (:func:`_way_out`, :func:`_is_tip`) over the
    pixels behind it that the photo shows holding the strand (the end's colour over the background across, one
    surface there), up to ``end_px`` steps: each given the end's value."""
    way = _way_out(coc, y1, x1, near, params.jump_px)
    if way[0] == 0 and way[1] == 0:
        return
    steps = wp.max(wp.abs(way[0]), wp.abs(way[1]))
    uy = float(way[0]) / float(steps)  # Chebyshev length 1
    ux = float(way[1]) / float(steps)
    if _is_tip(coc, y1, x1, uy, ux, params) == 0:
        return
    v = coc[y1, x1]
    level = v - params.jump_px
    f = image[y1, x1]
    for k in range(1, params.end_px + 1):
        py = y1 + _round(float(k) * uy)
        px = x1 + _round(float(k) * ux)
        if py < 0 or py >= coc.shape[0] or px < 0 or px >= coc.shape[1]:
            return
        if coc[py, px] >= level:
            return  # another dash (the bridges' business) or something nearer
        if _gap_pixel_ok(image, coc, py, px, ux, -uy, level, f, params.jump_px, params) == 0:
            return
        _raise(out, changed, py, px, v, coc[py, px])


@wp.kernel
def bridge_strands_kernel(
    image: wp.array2d(dtype=wp.vec3),
    coc: wp.array2d(dtype=float),
    strand: wp.array2d(dtype=wp.uint8),
    strand_y: wp.array(dtype=wp.int32),
    strand_x: wp.array(dtype=wp.int32),
    offset_y: wp.array(dtype=wp.int32),
    offset_x: wp.array(dtype=wp.int32),
    params: StrandParams,
    out: wp.array2d(dtype=float),
    changed: wp.array(dtype=wp.int32),
):
    i = wp.tid()
    h = coc.shape[0]
    w = coc.shape[1]
    y1 = strand_y[i]
    x1 = strand_x[i]
    s1 = coc[y1, x1]
    near = _own_ring(coc, y1, x1, params.jump_px)  # read once: the offsets test their side of it
    for k in range(offset_y.shape[0]):
        oy = offset_y[k]
        ox = offset_x[k]
        y2 = y1 + oy
        x2 = x1 + ox
        # two dash ends facing each other: a chord along a whole (kinked) strand is no gap
        if _ends_in_ring(near, oy, ox) == 1 and y2 >= 0 and y2 < h and x2 >= 0 and x2 < w:
            if strand[y2, x2] != wp.uint8(0) and wp.abs(coc[y2, x2] - s1) <= params.jump_px:
                if _ends_towards(coc, y2, x2, -oy, -ox, params.jump_px) == 1:
                    _bridge(image, coc, y1, x1, oy, ox, params, out, changed)
    if params.end_px > 0:
        _extend_end(image, coc, y1, x1, near, params, out, changed)
