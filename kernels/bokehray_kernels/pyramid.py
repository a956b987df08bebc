"""The radius pyramid: every source scattered on the level where its radius is at most ``r0`` (level ``l``: pixels of
``2^l``), unless routed to level 0; the levels' prefix sums and their bilinear, density-preserving resolve to full
resolution (docs/renderer.md)."""

import warp as wp

from .routing import Routing, routed_base, stored_neighbourhood
from .sampling import bilinear_taps
from .spans import Shape, scatter_exact, scatter_sharp
from .support import Support, in_support

wp.set_module_options({"enable_backward": False})

MAX_LEVELS = 6
"""Pyramid levels 0..5: radii up to ``r0 * 32`` cost O(r0) per source."""

@wp.struct
class Levels:
    """The difference buffers of the radius pyramid's levels 0 .. 5 (a level a layer does not use may alias level 0:
    nothing is scattered there and it is not resolved)."""

    l0: wp.array2d(dtype=wp.vec4)
    l1: wp.array2d(dtype=wp.vec4)
    l2: wp.array2d(dtype=wp.vec4)
    l3: wp.array2d(dtype=wp.vec4)
    l4: wp.array2d(dtype=wp.vec4)
    l5: wp.array2d(dtype=wp.vec4)


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
def scatter_kernel(  # noqa: C901
    src: wp.array2d(dtype=wp.vec4),
    coc: wp.array2d(dtype=float),
    support: Support,
    routing: Routing,
    shape: Shape,
    r0: float,
    n_levels: int,
    levels: Levels,
):
    """Scatter every source of ``src`` (local coordinates) with radius ``|coc|`` [px].

    Pixels outside the layer's ``support`` hold no source and are not read (a lazily zeroed ``src`` keeps its
    pages there untouched).

    ``shape`` is the aperture (its blades, vertical extent and area at unit circumradius). A positive (in-front-of-focus) ``coc`` draws the shape
    point-reflected, as a thin lens does: the aperture's orientation is that of background bokeh.
    ``routing.exact[y, x] != 0`` routes a salient source: the light it carries beyond its coverage of the
    local colour of the layer's other sources around it (``routing.cell_total``, ``routing.cell_pixels``: the
    neighbourhoods ``route_cells_kernel`` stored) is scattered at level 0 (full resolution) whatever its radius, the rest (its coverage, and
    the local colour over it) on its pyramid level like its neighbours. A constant colour thus
    stays on the pyramid, exactly as smooth as its coverage. ``routing.exact`` may be a 1 x 1 array when
    nothing is routed (then nothing else of ``routing`` is read).

    ``levels.l<l>`` is the difference buffer of level ``l``, ``(ceil(H/2^l), ceil(W/2^l) + 2)``.
    """
    y, x = wp.tid()
    if not in_support(support, y, x):
        return
    buf0 = levels.l0
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
    exact = routing.exact
    if lev > 0 and exact.shape[0] == src.shape[0] and exact.shape[1] == src.shape[1]:
        if exact[y, x] != wp.uint8(0):
            # a salient source: its excess light over the local colour of the sources around it (itself
            # left out) at full resolution, the exact outline; its coverage of that colour on its pyramid
            # level like its neighbours'. Alone in its neighbourhood, all of its light goes to level 0.
            nb = stored_neighbourhood(routing.cell_total, routing.cell_pixels, lev, y >> lev, x >> lev)
            base = routed_base(v, nb)
            if exact[y, x] == wp.uint8(1):  # routed alone; 2: its excess is in its cell's cluster source
                scatter_exact(buf0, float(x) + 0.5, float(y) + 0.5, r,
                              wp.vec4(v[0] - base[0], v[1] - base[1], v[2] - base[2], 0.0), shape, sgn)
            v = base
    scale = 1.0 / float(1 << lev)
    xc = (float(x) + 0.5) * scale
    yc = (float(y) + 0.5) * scale
    rho = r * scale
    if lev == 0:
        scatter_exact(buf0, xc, yc, rho, v, shape, sgn)
    elif lev == 1:
        scatter_sharp(levels.l1, xc, yc, rho, v, shape, sgn)
    elif lev == 2:
        scatter_sharp(levels.l2, xc, yc, rho, v, shape, sgn)
    elif lev == 3:
        scatter_sharp(levels.l3, xc, yc, rho, v, shape, sgn)
    elif lev == 4:
        scatter_sharp(levels.l4, xc, yc, rho, v, shape, sgn)
    else:
        scatter_sharp(levels.l5, xc, yc, rho, v, shape, sgn)


@wp.kernel
def prefix_rows_kernel(buf: wp.array2d(dtype=wp.vec4), support: Support, width: int):
    """In-place running sum along each row's first ``width`` columns: differences -> per-pixel values, stored
    where they are read.

    While the running sum is zero an element already holds its sum (``0 + d == d``: the buffers start at +0 and
    only ever receive sums, so no -0 arises), so it is not stored. Nor is a sum outside the layer's ``support``
    (:func:`resolve_levels_kernel` reads level 0 at the support's pixels only; coarser levels, read between
    their cells, take the support "everywhere" and their full width). Every deposit lies in the support, but
    for the step down one column after a run of it: the sum reads those columns only (adding the others' zeros
    would change nothing), so every stored value is the one a full pass stores, and a lazily zeroed buffer
    (``bokehray.levels.buffers.lazy_zeros``) is neither read nor written where the layer's light is not."""
    y = wp.tid()
    acc = wp.vec4()
    before = bool(False)  # whether the previous column is in the support
    for x in range(width):
        inside = in_support(support, y, x)
        if inside or before:  # elsewhere nothing is deposited (the light lies in the support): nothing to add
            d = buf[y, x]
            if acc[0] != 0.0 or acc[1] != 0.0 or acc[2] != 0.0 or acc[3] != 0.0:
                acc = acc + d
                if inside:
                    buf[y, x] = acc
            else:
                acc = d
        before = inside


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
def resolve_levels_kernel(n_levels: int, first: int, levels: Levels, support: Support, out: wp.array2d(dtype=wp.vec4)):
    """Sum level 0 and the bilinearly upsampled coarser levels ``first .. n_levels - 1`` (density-preserving)
    into ``out``; the levels between 0 and ``first`` hold no source (``bokehray.scene.lowest_level``).

    Pixels outside the layer's ``support`` are left as they are: the caller passes ``out`` zero there (the
    preview reuses the layer's sources, which are zero there).
    """
    y, x = wp.tid()
    if not in_support(support, y, x):
        return
    h = out.shape[0]
    w = out.shape[1]
    acc = levels.l0[y, x]
    if n_levels > 1 and first <= 1:
        acc = acc + _level_sample(levels.l1, x, y, 1, h, w)
    if n_levels > 2 and first <= 2:
        acc = acc + _level_sample(levels.l2, x, y, 2, h, w)
    if n_levels > 3 and first <= 3:
        acc = acc + _level_sample(levels.l3, x, y, 3, h, w)
    if n_levels > 4 and first <= 4:
        acc = acc + _level_sample(levels.l4, x, y, 4, h, w)
    if n_levels > 5 and first <= 5:
        acc = acc + _level_sample(levels.l5, x, y, 5, h, w)
    out[y, x] = acc


@wp.kernel
def clear_support_kernel(support: Support, buf: wp.array2d(dtype=wp.vec4)):
    """Store zero at the pixels of ``buf`` in the layer's ``support`` (columns beyond the support's mask are left).

    The values do not change (``buf`` comes zeroed); on a lazily zeroed buffer the support's pages are then taken
    by a write, once, where a first read would map the shared zero page and the later write fault again to copy it.
    """
    y, x = wp.tid()
    if in_support(support, y, x):
        buf[y, x] = wp.vec4()
