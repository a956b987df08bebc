"""The radius pyramid: every source scattered on the level where its radius is at most ``r0`` (level ``l``: pixels of
``2^l``), unless routed to level 0; the levels' prefix sums and their bilinear, density-preserving resolve to full
resolution (docs/renderer.md)."""

import warp as wp

from .routing import Routing, level_of, on_level, routed_base, stored_neighbourhood
from .sampling import bilinear_taps
from .spans import Shape, scatter_exact, scatter_sharp
from .support import Support, in_support, span_in_support, tile_end

wp.set_module_options({"enable_backward": False})

MAX_LEVELS = 6
"""Pyramid levels 0..5: radii up to ``r0 * 32`` cost O(r0) per source."""

MERGE_GROUPS = wp.constant(4)
"""Most merged sources a pyramid cell scatters (:func:`scatter_merged_kernel`): a cell whose sources' CoCs span more
bins than this scatters each of them."""

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
def _routed(routing: Routing, h: int, w: int, y: int, x: int) -> wp.uint8:
    """The routing's flag of source ``(y, x)`` (0 where nothing is routed: a 1 x 1 ``exact``)."""
    exact = routing.exact
    if exact.shape[0] == h and exact.shape[1] == w:
        return exact[y, x]
    return wp.uint8(0)


@wp.func
def pyramid_share(v: wp.vec4, routing: Routing, h: int, w: int, y: int, x: int, lev: int) -> wp.vec4:
    """What of level-``lev`` source ``(y, x)`` (value ``v``) is scattered on its pyramid level: all of it, or for a
    routed source its coverage carrying the local colour of the sources around it (``routed_base``)."""
    if _routed(routing, h, w, y, x) == wp.uint8(0):
        return v
    nb = stored_neighbourhood(routing.cell_total, routing.cell_pixels, lev, y >> lev, x >> lev)
    return routed_base(v, nb)


@wp.func
def deposit_routed(v: wp.vec4, r: float, sgn: float, routing: Routing, h: int, w: int, y: int, x: int, lev: int,
                   shape: Shape, buf0: wp.array2d(dtype=wp.vec4)):
    """A source routed alone (``exact == 1``): its excess light over :func:`pyramid_share` at level 0, exactly (a
    cluster member's excess is its cluster's, scattered by ``route_cells_kernel``)."""
    if _routed(routing, h, w, y, x) == wp.uint8(1):
        base = pyramid_share(v, routing, h, w, y, x, lev)
        scatter_exact(buf0, float(x) + 0.5, float(y) + 0.5, r,
                      wp.vec4(v[0] - base[0], v[1] - base[1], v[2] - base[2], 0.0), shape, sgn)


@wp.func
def _scatter_scaled(levels: Levels, lev: int, xl: float, yl: float, rho: float, v: wp.vec4, shape: Shape, sgn: float):
    # a source at (xl, yl) of radius rho, all in level lev's pixels, with that level's sharp spans
    if lev == 1:
        scatter_sharp(levels.l1, xl, yl, rho, v, shape, sgn)
    elif lev == 2:
        scatter_sharp(levels.l2, xl, yl, rho, v, shape, sgn)
    elif lev == 3:
        scatter_sharp(levels.l3, xl, yl, rho, v, shape, sgn)
    elif lev == 4:
        scatter_sharp(levels.l4, xl, yl, rho, v, shape, sgn)
    else:
        scatter_sharp(levels.l5, xl, yl, rho, v, shape, sgn)


@wp.func
def scatter_on_level(levels: Levels, lev: int, xc: float, yc: float, r: float, v: wp.vec4, shape: Shape, sgn: float):
    """Scatter a source centred at ``(xc, yc)`` [px] of radius ``r`` [px] on pyramid level ``lev`` >= 1 (sharp
    spans, in the level's pixels of ``2^lev``)."""
    scale = 1.0 / float(1 << lev)
    _scatter_scaled(levels, lev, xc * scale, yc * scale, r * scale, v, shape, sgn)


@wp.func
def _sign(s: float) -> float:
    # a thin lens images the aperture point-reflected in front of the focal plane (s > 0)
    if s > 0.0:
        return -1.0
    return 1.0


@wp.func
def _scatter_source(src: wp.array2d(dtype=wp.vec4), coc: wp.array2d(dtype=float), routing: Routing, shape: Shape,
                    r0: float, n_levels: int, levels: Levels, merged: int, y: int, x: int):
    # one source of scatter_kernel, in the support
    buf0 = levels.l0
    v = src[y, x]
    if v[3] == 0.0:
        return
    r = wp.abs(coc[y, x])
    sgn = _sign(coc[y, x])
    if r < 0.5:
        # the disc lies inside the source pixel: a plain copy
        wp.atomic_add(buf0, y, x, v)
        wp.atomic_add(buf0, y, x + 1, -v)
        return
    lev = level_of(r, r0, n_levels)
    if lev > 0:
        if merged != 0:
            return
        h = src.shape[0]
        w = src.shape[1]
        # a salient source: its excess light over the local colour of the sources around it (itself left out) at
        # full resolution, the exact outline; its coverage of that colour on its pyramid level like its
        # neighbours'. Alone in its neighbourhood, all of its light goes to level 0.
        deposit_routed(v, r, sgn, routing, h, w, y, x, lev, shape, buf0)
        v = pyramid_share(v, routing, h, w, y, x, lev)
    scale = 1.0 / float(1 << lev)
    xc = (float(x) + 0.5) * scale
    yc = (float(y) + 0.5) * scale
    rho = r * scale
    if lev == 0:
        scatter_exact(buf0, xc, yc, rho, v, shape, sgn)
    else:
        _scatter_scaled(levels, lev, xc, yc, rho, v, shape, sgn)


@wp.kernel
def scatter_kernel(
    span: int,
    src: wp.array2d(dtype=wp.vec4),
    coc: wp.array2d(dtype=float),
    support: Support,
    routing: Routing,
    shape: Shape,
    r0: float,
    n_levels: int,
    levels: Levels,
    merged: int,
):
    """Scatter every source of ``src`` (local coordinates) with radius ``|coc|`` [px]; with ``merged`` != 0 only
    those of level 0, :func:`scatter_merged_kernel` scattering the others.

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

    A thread takes ``span`` consecutive pixels of a row, a launch of (rows, ceil(width / span)): a row a thread
    on a CPU, a pixel a thread on a GPU (``bokehray.scene.row_span``).
    """
    y, j = wp.tid()
    x = j * span
    x_end = wp.min(src.shape[1], j * span + span)
    while x < x_end:
        end = wp.min(tile_end(support, x), x_end)  # columns of one support tile: one test for all of them
        if in_support(support, y, x):
            for xi in range(x, end):
                _scatter_source(src, coc, routing, shape, r0, n_levels, levels, merged, y, xi)
        x = end


@wp.struct
class Cell:
    """A pyramid cell of ``2^lev`` px (rows ``y0 .. y1 - 1``, columns ``x0 .. x1 - 1`` of the layer's box) and what
    :func:`scatter_merged_kernel` reads of its sources."""

    y0: int
    y1: int
    x0: int
    x1: int
    lev: int
    n_levels: int
    r0: float


@wp.func
def _scatter_each(src: wp.array2d(dtype=wp.vec4), coc: wp.array2d(dtype=float), cell: Cell, routing: Routing,
                  shape: Shape, levels: Levels):
    """Every source of the cell's level on its own (a cell whose CoCs span more than ``MERGE_GROUPS`` bins)."""
    for y in range(cell.y0, cell.y1):
        for x in range(cell.x0, cell.x1):
            v = src[y, x]
            s = coc[y, x]
            if on_level(v, wp.abs(s), cell.r0, cell.n_levels, cell.lev):
                share = pyramid_share(v, routing, src.shape[0], src.shape[1], y, x, cell.lev)
                scatter_on_level(levels, cell.lev, float(x) + 0.5, float(y) + 0.5, wp.abs(s), share, shape, _sign(s))


MERGE_SPLIT = wp.constant(0.0625)
"""A merged source one of whose colour channels has its centroid farther than this share of its cell from its
coverage's is scattered as two (:func:`_scatter_bin`)."""


@wp.func
def _grid_256(u: float) -> float:
    # a centroid within its cell on a 1/256 px grid: exact in float32 in a window's coordinates and in the box's, so
    # the scatter cuts the same rows in both (tiled renders equal the untiled one)
    return wp.floor(u * 256.0 + 0.5) / 256.0


@wp.struct
class Moments:
    """A merged source's summed value and its first moments (x and y, relative to its cell: the same sums in a
    tile's window as in the whole box) per channel (R, G, B, coverage), and its coverage-weighted signed CoC."""

    total: wp.vec4
    mx: wp.vec4
    my: wp.vec4
    s: float


@wp.func
def _centroid(m: Moments, k: int, fallback: wp.vec2) -> wp.vec2:
    # channel k's centroid within the cell (on the 1/256 px grid); ``fallback`` where it holds nothing
    if m.total[k] <= 0.0:
        return fallback
    return wp.vec2(_grid_256(m.mx[k] / m.total[k]), _grid_256(m.my[k] / m.total[k]))


@wp.func
def _apart(a: wp.vec2, b: wp.vec2) -> float:
    return wp.max(wp.abs(a[0] - b[0]), wp.abs(a[1] - b[1]))


@wp.func
def _scatter_moments(m: Moments, cell: Cell, levels: Levels, shape: Shape):
    """Scatter a merged source: at its coverage's centroid ``a``; where a colour channel's centroid lies farther than
    ``MERGE_SPLIT`` of the cell from it, as two, the channels whose centroids lie nearer to the farthest one's at
    that one, the rest (the coverage always) at ``a``: a channel that is constant over the cell stays with the
    coverage (the layer's colour there stays constant), and a light does not move."""
    s_mean = m.s / m.total[3]
    a = _centroid(m, 3, wp.vec2())
    far = a
    gap = float(0.0)
    for k in range(3):
        c = _centroid(m, k, a)
        if _apart(c, a) > gap:
            gap = _apart(c, a)
            far = c
    at_a = m.total
    at_far = wp.vec4()
    if gap > MERGE_SPLIT * float(1 << cell.lev):
        for k in range(3):
            c = _centroid(m, k, a)
            if _apart(c, far) < _apart(c, a):
                at_far[k] = m.total[k]
                at_a[k] = 0.0
        scatter_on_level(levels, cell.lev, float(cell.x0) + far[0], float(cell.y0) + far[1], wp.abs(s_mean), at_far,
                         shape, _sign(s_mean))
    scatter_on_level(levels, cell.lev, float(cell.x0) + a[0], float(cell.y0) + a[1], wp.abs(s_mean), at_a, shape,
                     _sign(s_mean))


@wp.struct
class CellSources:
    """What one pass over a pyramid cell's sources of its level finds (:func:`_cell_sources`): their smallest and
    largest signed CoC (none: ``lo > hi``) and the :class:`Moments` of them all, in row order (one bin's merged
    source when their CoCs span one bin)."""

    lo: float
    hi: float
    m: Moments


@wp.func
def _cell_sources(src: wp.array2d(dtype=wp.vec4), coc: wp.array2d(dtype=float), cell: Cell, routing: Routing,
                  shape: Shape, buf0: wp.array2d(dtype=wp.vec4)) -> CellSources:
    """The cell's sources of its level (:class:`CellSources`), their routed excess deposited at level 0 on the way."""
    c = CellSources()
    c.lo = float(1.0e30)
    c.hi = float(-1.0e30)
    m = Moments()
    for y in range(cell.y0, cell.y1):
        for x in range(cell.x0, cell.x1):
            v = src[y, x]
            s = coc[y, x]
            r = wp.abs(s)
            if on_level(v, r, cell.r0, cell.n_levels, cell.lev):
                c.lo = wp.min(c.lo, s)
                c.hi = wp.max(c.hi, s)
                deposit_routed(v, r, _sign(s), routing, src.shape[0], src.shape[1], y, x, cell.lev, shape, buf0)
                share = pyramid_share(v, routing, src.shape[0], src.shape[1], y, x, cell.lev)
                m.total += share
                m.mx += share * (float(x - cell.x0) + 0.5)
                m.my += share * (float(y - cell.y0) + 0.5)
                m.s += share[3] * s
    c.m = m
    return c


@wp.func
def _scatter_bin(src: wp.array2d(dtype=wp.vec4), coc: wp.array2d(dtype=float), cell: Cell, routing: Routing,
                 shape: Shape, levels: Levels, lo: float, tol: float, n_bins: int, b: int):
    """The cell's sources of its level whose signed CoC falls in bin ``b`` (of width ``tol`` from ``lo``; the last
    bin takes the rest) as one: their summed value at their centroid, with their coverage-weighted mean signed CoC
    (:func:`_scatter_moments`)."""
    m = Moments()
    for y in range(cell.y0, cell.y1):
        for x in range(cell.x0, cell.x1):
            v = src[y, x]
            s = coc[y, x]
            if on_level(v, wp.abs(s), cell.r0, cell.n_levels, cell.lev):
                if wp.min(int((s - lo) / tol), n_bins - 1) == b:
                    share = pyramid_share(v, routing, src.shape[0], src.shape[1], y, x, cell.lev)
                    m.total += share
                    m.mx += share * (float(x - cell.x0) + 0.5)
                    m.my += share * (float(y - cell.y0) + 0.5)
                    m.s += share[3] * s
    if m.total[3] > 0.0:
        _scatter_moments(m, cell, levels, shape)


@wp.kernel
def scatter_merged_kernel(
    src: wp.array2d(dtype=wp.vec4),
    coc: wp.array2d(dtype=float),
    support: Support,
    routing: Routing,
    shape: Shape,
    r0: float,
    n_levels: int,
    lev: int,
    tol: float,
    levels: Levels,
):
    """Scatter the sources of pyramid level ``lev`` >= 1, merged: one thread per cell of ``2^lev x 2^lev`` px.

    On level ``lev`` a source's outline is blurred by about ``2^lev`` px (its sharp spans, the upsampling), so
    sources of one cell whose signed CoCs differ by less than ``tol`` [px] cannot be told apart from one source
    carrying their summed value (premultiplied RGB and coverage: the energy is kept) at their coverage-weighted
    centroid and mean signed CoC. The cell's CoC range is cut into bins of ``tol``; up to ``MERGE_GROUPS`` bins
    each scatter one merged source, more scatter every source alone (as ``scatter_kernel`` does). A routed source
    (``routing``) sends its excess light to level 0 exactly, as in ``scatter_kernel``, and merges what it leaves
    on the pyramid (:func:`pyramid_share`). Cells outside the layer's ``support`` hold no source: skipped.
    """
    cy, cx = wp.tid()
    cell = Cell()
    cell.y0 = cy << lev
    cell.x0 = cx << lev
    cell.y1 = wp.min(cell.y0 + (1 << lev), src.shape[0])
    cell.x1 = wp.min(cell.x0 + (1 << lev), src.shape[1])
    if not span_in_support(support, cell.y0, cell.y1, cell.x0, cell.x1):
        return
    cell.lev = lev
    cell.n_levels = n_levels
    cell.r0 = r0
    found = _cell_sources(src, coc, cell, routing, shape, levels.l0)
    if found.hi < found.lo:
        return
    n_bins = int((found.hi - found.lo) / tol) + 1
    if n_bins > MERGE_GROUPS:
        _scatter_each(src, coc, cell, routing, shape, levels)
        return
    if n_bins == 1:  # one bin holds them all: its merged source is the one the pass summed (no second pass)
        if found.m.total[3] > 0.0:
            _scatter_moments(found.m, cell, levels, shape)
        return
    for b in range(n_bins):
        _scatter_bin(src, coc, cell, routing, shape, levels, found.lo, tol, n_bins, b)


@wp.kernel
def prefix_rows_kernel(buf: wp.array2d(dtype=wp.vec4), support: Support, store: Support, width: int):
    """In-place running sum along each row's first ``width`` columns: differences -> per-pixel values, stored
    where they are read (in ``support`` and in ``store``: the preview's output, the frame without its clamped
    border; "everywhere" to store the whole support).

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
    x = int(0)
    while x < width:
        # a run of columns in one tile of both grids: one support test for all of them
        end = wp.min(wp.min(tile_end(support, x), tile_end(store, x)), width)
        inside = in_support(support, y, x)
        if inside:
            kept = in_support(store, y, x)
            for xi in range(x, end):
                d = buf[y, xi]
                if acc[0] != 0.0 or acc[1] != 0.0 or acc[2] != 0.0 or acc[3] != 0.0:
                    acc = acc + d
                    if kept:
                        buf[y, xi] = acc
                else:
                    acc = d
        elif before:  # the step down one column after a run of the support (nothing is stored there)
            d = buf[y, x]
            if acc[0] != 0.0 or acc[1] != 0.0 or acc[2] != 0.0 or acc[3] != 0.0:
                acc = acc + d
            else:
                acc = d
        before = inside
        x = end


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


@wp.func
def _resolve_at(n_levels: int, first: int, levels: Levels, y: int, x: int, h: int, w: int) -> wp.vec4:
    # level 0 and the bilinearly upsampled coarser levels first .. n_levels - 1 at box pixel (y, x)
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
    return acc


@wp.kernel
def resolve_levels_kernel(span: int, n_levels: int, first: int, levels: Levels, support: Support,
                          out: wp.array2d(dtype=wp.vec4)):
    """Sum level 0 and the bilinearly upsampled coarser levels ``first .. n_levels - 1`` (density-preserving)
    into ``out``; the levels between 0 and ``first`` hold no source (``bokehray.scene.lowest_level``).

    Pixels outside the layer's ``support`` are left as they are: the caller passes ``out`` zero there (the
    preview reuses the layer's sources, which are zero there).

    A thread takes ``span`` consecutive pixels of a row, a launch of (rows, ceil(width / span)): a row a thread
    on a CPU, a pixel a thread on a GPU (``bokehray.scene.row_span``).
    """
    y, j = wp.tid()
    x = j * span
    x_end = wp.min(out.shape[1], j * span + span)
    while x < x_end:
        end = wp.min(tile_end(support, x), x_end)  # columns of one support tile: one test for all of them
        if in_support(support, y, x):
            for xi in range(x, end):
                out[y, xi] = _resolve_at(n_levels, first, levels, y, xi, out.shape[0], out.shape[1])
        x = end


@wp.kernel
def clear_support_kernel(span: int, support: Support, width: int, buf: wp.array2d(dtype=wp.vec4)):
    """Store zero at the pixels of ``buf``'s first ``width`` columns in the layer's ``support`` (columns beyond the
    support's mask are left).

    The values do not change (``buf`` comes zeroed); on a lazily zeroed buffer the support's pages are then taken
    by a write, once, where a first read would map the shared zero page and the later write fault again to copy it.

    A thread takes ``span`` consecutive pixels of a row, a launch of (rows, ceil(width / span)): a row a thread
    on a CPU, a pixel a thread on a GPU (``bokehray.scene.row_span``).
    """
    y, j = wp.tid()
    x = j * span
    x_end = wp.min(width, j * span + span)
    while x < x_end:
        end = wp.min(tile_end(support, x), x_end)  # columns of one support tile: one test for all of them
        if in_support(support, y, x):
            for xi in range(x, end):
                buf[y, xi] = wp.vec4()
        x = end


