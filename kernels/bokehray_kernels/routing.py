"""Routing of salient lights: which pyramid-level sources send their excess light to level 0 (alone, or gathered as
their cell's cluster), from a radiance pyramid of the layer's sources (docs/renderer.md, "exact highlights")."""

import warp as wp

from .reduce import children_2x2
from .spans import Shape, scatter_exact
from .support import Support, span_in_support

wp.set_module_options({"enable_backward": False})


@wp.struct
class Routing:
    """What :func:`route_cells_kernel` decides for one layer's sources, and what the scatter reads of it.

    ``exact``: per source, 1 routed alone to level 0, 2 in its cell's cluster, 0 on the pyramid (a 1 x 1 array:
    nothing routed, and then nothing else is read); ``cell_total``, ``cell_pixels``: per level-``l`` cell, its
    3 x 3 cells' sum of sources and their pixels (the routed sources' local colour). The clusters' light is
    deposited at level 0 as they are found: nothing of them is stored."""

    exact: wp.array2d(dtype=wp.uint8)
    cell_total: wp.array3d(dtype=wp.vec4)
    cell_pixels: wp.array3d(dtype=float)


@wp.struct
class Salience:
    """When a source is salient (:func:`route_cells_kernel`): at most ``per_cell`` a cell, its excess beyond
    ``visible`` times its disc's share of the local radiance (at least ``floor``)."""

    per_cell: int
    visible: float
    floor: float


@wp.func
def on_level(v: wp.vec4, r: float, r0: float, n_levels: int, lev: int) -> bool:
    # the source has coverage and scatters on pyramid level ``lev`` >= 1 (level_of(r) == lev, without its loop:
    # r * 2^-l is exact in binary floating point, as in level_of)
    if v[3] == 0.0 or r < 0.5:
        return False
    scale = 1.0 / float(1 << lev)
    if r * (2.0 * scale) <= r0:
        return False  # a lower level
    return r * scale <= r0 or lev == n_levels - 1


@wp.func
def level_of(r: float, r0: float, n_levels: int) -> int:
    """Pyramid level of a source of radius ``r``: the first where ``r / 2^l <= r0`` (at most ``n_levels - 1``)."""
    lev = int(0)
    scale = float(1.0)
    while r * scale > r0 and lev < n_levels - 1:
        lev += 1
        scale *= 0.5
    return lev


@wp.func
def level_bits(lo: float, hi: float, r0: float, n_levels: int) -> int:
    """Bits ``l`` (pyramid levels ``l >= 1``) from the level of radius ``lo`` to that of ``hi``: every level a source
    of a radius in ``[lo, hi]`` may scatter on (0 for an empty range, ``lo > hi``)."""
    if hi < lo:
        return 0
    top = level_of(hi, r0, n_levels)
    bottom = wp.max(level_of(lo, r0, n_levels), 1)
    if top < bottom:
        return 0
    return ((1 << (top + 1)) - 1) & ~((1 << bottom) - 1)


@wp.func
def _radiance_mean(src: wp.array2d(dtype=wp.vec4), coc: wp.array2d(dtype=float), support: Support, r0: float,
                   n_levels: int, means: wp.array3d(dtype=wp.vec4), counts: wp.array3d(dtype=float),
                   present: wp.array3d(dtype=wp.uint8), cy: int, cx: int):
    # one cell of radiance_mean_kernel: the sum in sum_2x2_vec4's order
    n = children_2x2(src.shape[0], src.shape[1], cy, cx)
    bits = int(0)
    if span_in_support(support, 2 * cy, wp.min(2 * cy + 2, src.shape[0]), 2 * cx, wp.min(2 * cx + 2, src.shape[1])):
        acc = wp.vec4()
        lo = float(1.0e30)  # the radii of the cell's sources with coverage, scattered (r >= 0.5)
        hi = float(-1.0e30)
        for y in range(2 * cy, wp.min(2 * cy + 2, src.shape[0])):
            for x in range(2 * cx, wp.min(2 * cx + 2, src.shape[1])):
                v = src[y, x]
                acc = acc + v
                if v[3] != 0.0:
                    r = wp.abs(coc[y, x])
                    if r >= 0.5:
                        lo = wp.min(lo, r)
                        hi = wp.max(hi, r)
        means[0, cy, cx] = acc / n
        bits = level_bits(lo, hi, r0, n_levels)
    counts[0, cy, cx] = n
    present[0, cy, cx] = wp.uint8(bits)


@wp.kernel
def radiance_mean_kernel(span: int, src: wp.array2d(dtype=wp.vec4), coc: wp.array2d(dtype=float), support: Support,
                         r0: float, n_levels: int, means: wp.array3d(dtype=wp.vec4), counts: wp.array3d(dtype=float),
                         present: wp.array3d(dtype=wp.uint8)):
    """Level 1 of the radiance pyramid: mean over each 2 x 2 cell of the sources (premultiplied RGB, coverage), and
    which pyramid levels its sources scatter on.

    Sources of zero coverage count as black; cells cut by the array's edge average the pixels they hold
    (``counts``). Level ``k`` lives in ``means[k - 1]``. A cell outside the layer's ``support`` holds no source:
    its mean is zero (``means`` comes zeroed there) and ``src`` is not read there. ``present``: bits ``l`` of the
    pyramid levels ``l >= 1`` from that of the cell's smallest radius to that of its largest (its sources with
    coverage and ``r >= 0.5``; :func:`level_bits`), a bit set for every level a source of the cell scatters on
    (``on_level`` with ``r0``, ``n_levels``), so that :func:`route_cells_kernel` reads only the cells that may hold
    sources of its level. ``counts`` and ``present`` are written everywhere (they may come uninitialised).

    A thread takes ``span`` consecutive cells of a row, a launch of (rows, ceil(width / span)): a row a thread
    on a CPU, a pixel a thread on a GPU (``bokehray.scene.row_span``).
    """
    cy, j = wp.tid()
    for cx in range(j * span, wp.min((src.shape[1] + 1) // 2, j * span + span)):
        _radiance_mean(src, coc, support, r0, n_levels, means, counts, present, cy, cx)


@wp.kernel
def halve_mean_kernel(means: wp.array3d(dtype=wp.vec4), counts: wp.array3d(dtype=float),
                      present: wp.array3d(dtype=wp.uint8), k: int, fine_h: int, fine_w: int):
    """Radiance pyramid level ``k + 1`` (in ``means[k]``) from level ``k``: pixel-count-weighted 2 x 2 means, and
    the levels present in any of the 2 x 2 cells."""
    cy, cx = wp.tid()
    acc = wp.vec4()
    n = float(0.0)
    bits = int(0)
    for dy in range(2):
        for dx in range(2):
            y = 2 * cy + dy
            x = 2 * cx + dx
            if y < fine_h and x < fine_w:
                c = counts[k - 1, y, x]
                acc += means[k - 1, y, x] * c
                n += c
                bits = bits | int(present[k - 1, y, x])
    means[k, cy, cx] = acc / n
    counts[k, cy, cx] = n
    present[k, cy, cx] = wp.uint8(bits)


@wp.struct
class Neighbourhood:
    """Sum of the sources (premultiplied RGB, coverage) over some cells, and how many pixels they hold."""

    total: wp.vec4
    pixels: float


@wp.func
def neighbourhood(means: wp.array3d(dtype=wp.vec4), counts: wp.array3d(dtype=float), lev: int, cy: int, cx: int,
                  hl: int, wl: int) -> Neighbourhood:
    """The sources of the 3 x 3 level-``lev`` cells around cell ``(cy, cx)`` (cells beyond the ``hl x wl`` level
    left out): the layer's local colour there is ``total.rgb / total.a``."""
    acc = wp.vec4()
    nc = float(0.0)
    for dy in range(-1, 2):
        for dx in range(-1, 2):
            yy = cy + dy
            xx = cx + dx
            if yy >= 0 and yy < hl and xx >= 0 and xx < wl:
                c = counts[lev - 1, yy, xx]
                acc += means[lev - 1, yy, xx] * c
                nc += c
    nb = Neighbourhood()
    nb.total = acc
    nb.pixels = nc
    return nb


@wp.func
def stored_neighbourhood(cell_total: wp.array3d(dtype=wp.vec4), cell_pixels: wp.array3d(dtype=float), lev: int,
                         cy: int, cx: int) -> Neighbourhood:
    """The neighbourhood of level-``lev`` cell ``(cy, cx)`` as ``route_cells_kernel`` stored it."""
    nb = Neighbourhood()
    nb.total = cell_total[lev - 1, cy, cx]
    nb.pixels = cell_pixels[lev - 1, cy, cx]
    return nb


@wp.func
def routed_base(v: wp.vec4, nb: Neighbourhood) -> wp.vec4:
    """What of a routed source stays on the pyramid: its coverage, carrying the local colour of the other sources
    in its neighbourhood ``nb`` (itself left out; none there: black). The rest of its light goes to level 0."""
    rest = nb.total - v
    if rest[3] > 1.0e-6 * nb.pixels:
        k = v[3] / rest[3]
        return wp.vec4(wp.max(rest[0], 0.0) * k, wp.max(rest[1], 0.0) * k, wp.max(rest[2], 0.0) * k, v[3])
    return wp.vec4(0.0, 0.0, 0.0, v[3])


@wp.func
def _local_mean(nb: Neighbourhood) -> wp.vec2:
    # (mean premultiplied radiance m, mean coverage a_m) of a neighbourhood: its local colour is m / a_m
    return wp.vec2((nb.total[0] + nb.total[1] + nb.total[2]) / (3.0 * nb.pixels), nb.total[3] / nb.pixels)


@wp.func
def _raw_excess(v: wp.vec4, mean: wp.vec2) -> float:
    # the light a source (premultiplied radiance, coverage v) carries beyond its coverage of the local colour
    return (v[0] + v[1] + v[2]) / 3.0 - v[3] * mean[0] / mean[1]  # mean[1] > 0: the source itself has coverage


@wp.func
def _excess(v: wp.vec4, r: float, mean: wp.vec2, visible: float, floor: float) -> float:
    # how far a source of radius r stands out of the local colour: its excess beyond the visibility threshold
    return _raw_excess(v, mean) - visible * wp.max(mean[0], floor) * 3.14159265 * r * r


@wp.func
def _cluster_excess(v: wp.vec4, r: float, flag: wp.uint8, mean: wp.vec2, r0: float, n_levels: int,
                    lev: int) -> float:
    # a cluster member's excess (> 0): a source of level lev, not routed alone, brighter than the local colour
    if flag == wp.uint8(0) and on_level(v, r, r0, n_levels, lev):
        return wp.max(_raw_excess(v, mean), 0.0)
    return 0.0


@wp.func
def _scatter_blocks(src: wp.array2d(dtype=wp.vec4), coc: wp.array2d(dtype=float), exact: wp.array2d(dtype=wp.uint8),
                    nb: Neighbourhood, mean: wp.vec2, r0: float, n_levels: int, lev: int, y0: int, y1: int, x0: int,
                    x1: int, shape: Shape, buf0: wp.array2d(dtype=wp.vec4)):
    """A visible cluster of cell ``[y0, y1) x [x0, x1)`` to level 0: its members (marked 2 in ``exact``) gathered per
    block of ``2^b`` px, ``b = max(1, lev - 2)``, one source a block at their excess-weighted centroid with their
    excess-weighted mean radius (signed as their mean signed CoC), carrying their excess light (what
    ``routed_base`` does not keep on the pyramid), scattered with the exact spans of level 0 (a block is 2 px wide
    up to level 3: the pyramid levels' sharp spans cost small lamps 2-3 dB).

    A block's members lie within ``2^(b-1)`` px of its centroid, at most 1/32 of the radius, so the gathered
    sources keep the cluster's own soft outline; at most 16 blocks a cell, so the cost stays flat in R."""
    b = wp.max(1, lev - 2)
    bs = 1 << b
    for by in range(y0 >> b, (y1 + bs - 1) >> b):
        for bx in range(x0 >> b, (x1 + bs - 1) >> b):
            b_e = float(0.0)
            b_light = wp.vec3()
            b_x = float(0.0)
            b_y = float(0.0)
            b_s = float(0.0)
            b_sign = float(0.0)
            for y in range(by * bs, wp.min(by * bs + bs, y1)):
                for x in range(bx * bs, wp.min(bx * bs + bs, x1)):
                    v = src[y, x]
                    e = _cluster_excess(v, wp.abs(coc[y, x]), exact[y, x], mean, r0, n_levels, lev)
                    if e > 0.0:
                        base = routed_base(v, nb)
                        b_light += wp.vec3(v[0] - base[0], v[1] - base[1], v[2] - base[2])
                        b_e += e
                        b_x += e * (float(x - bx * bs) + 0.5)  # relative to the block: the same sums
                        b_y += e * (float(y - by * bs) + 0.5)  # in a tile's window as in the whole box
                        b_s += e * wp.abs(coc[y, x])
                        b_sign += e * coc[y, x]
                        exact[y, x] = wp.uint8(2)
            if b_e > 0.0:
                # the centroid on a 1/256 px grid: exact in float32 in a window's coordinates and in the box's,
                # so the scatter cuts the same sub-rows in both (tiled renders equal the untiled one)
                cx_rel = wp.floor(b_x / b_e * 256.0 + 0.5) / 256.0
                cy_rel = wp.floor(b_y / b_e * 256.0 + 0.5) / 256.0
                sgn = float(1.0)
                if b_sign >= 0.0:
                    sgn = -1.0  # in front of the focus (or on it): the shape point-reflected
                scatter_exact(buf0, float(bx * bs) + cx_rel, float(by * bs) + cy_rel, b_s / b_e,
                              wp.vec4(b_light[0], b_light[1], b_light[2], 0.0), shape, sgn)


@wp.kernel
def route_cells_kernel(  # noqa: C901
    src: wp.array2d(dtype=wp.vec4),
    coc: wp.array2d(dtype=float),
    means: wp.array3d(dtype=wp.vec4),
    counts: wp.array3d(dtype=float),
    present: wp.array3d(dtype=wp.uint8),
    r0: float,
    n_levels: int,
    lev: int,
    salience: Salience,
    support: Support,
    routing: Routing,
    shape: Shape,
    buf0: wp.array2d(dtype=wp.vec4),
):
    """Route the level-``lev`` sources of each level cell: at most ``per_cell`` salient ones alone to level 0, and
    the rest of the cell's excess light, when together it is visible, as its cluster.

    One thread per cell of ``2^lev x 2^lev`` px. Salience: how far a source's own disc stands
    out of its layer's neighbourhood, the 3 x 3 level-``lev`` cells around its own (cells beyond
    the array left out): mean premultiplied radiance ``m`` and coverage ``a_m``, so the layer's
    local colour is ``m / a_m``. A source of radiance ``q`` and coverage ``a`` carries
    ``e = q - a m / a_m`` more light than its coverage of the local colour (0 on a constant
    image, whatever the layer's shape); its disc then lights ``e / (pi r^2)`` above the blurred
    surroundings (about ``m``), and its outline is visible when that exceeds
    ``visible * max(m, floor)``: the score is the excess beyond that, salient where > 0. The
    cell keeps its sources of that level with the largest scores (ties: the first in row order),
    marked 1 in ``exact``. A level-0 source costs ``2^lev`` times the rows of its pyramid scatter, so
    the routed work is at most ``per_cell / 2^lev`` times what the cell's pyramid sources cost.

    *Extended lights.* A lamp or a window is many sources, each too faint alone to show its outline,
    whose outlines coincide: together they draw a sharp-edged ball. The cell's sources of that level not
    routed alone and with positive excess are its *cluster*; when their summed excess ``E`` beats the
    visibility threshold at the excess-weighted mean radius, their excess light (what ``routed_base`` does
    not keep on the pyramid) is scattered into ``buf0`` (level 0's difference plane) gathered per block of
    ``2^b`` px, ``b = max(1, lev - 2)``, one source at each block's excess-weighted centroid
    (:func:`_scatter_blocks`), and the members are marked 2 in ``exact``. At
    most 16 level-0 sources per cell, whose rows are at most twice those of the cell's pyramid sources
    (level 3), whatever the radius. ``E`` is the excess of all the cell's sources with a positive one less
    that of the routed ones, summed in float64 in the pass that counts the salient ones.

    ``means[k]``, ``counts[k]``, ``present[k]``: radiance pyramid level ``k + 1`` (padded to level 1). Each
    routing cell's neighbourhood sums are stored in ``cell_total``, ``cell_pixels`` for the scatter (which reads
    them for routed sources only). Cells outside the layer's ``support`` (``bokehray_kernels.support``) hold no
    source, and cells whose ``present`` bits hold no source of level ``lev`` route none: both skipped unread,
    nothing stored.
    """
    cy, cx = wp.tid()
    side = 1 << lev
    y0 = cy * side
    x0 = cx * side
    y1 = wp.min(y0 + side, src.shape[0])
    x1 = wp.min(x0 + side, src.shape[1])
    if not span_in_support(support, y0, y1, x0, x1):
        return
    if (int(present[lev - 1, cy, cx]) & (1 << lev)) == 0:
        return  # no source of this level in the cell: nothing to route, and nothing reads its neighbourhood
    per_cell = salience.per_cell
    visible = salience.visible
    floor = salience.floor
    exact = routing.exact
    cell_total = routing.cell_total
    cell_pixels = routing.cell_pixels
    hl = (src.shape[0] + side - 1) >> lev
    wl = (src.shape[1] + side - 1) >> lev
    nb = neighbourhood(means, counts, lev, cy, cx, hl, wl)
    cell_total[lev - 1, cy, cx] = nb.total
    cell_pixels[lev - 1, cy, cx] = nb.pixels
    mean = _local_mean(nb)
    n = int(0)  # salient sources of this level in the cell; only a few cells have any
    e_all = wp.float64(0.0)  # excess (> 0) of the level's sources, and its CoC moment: all of them ...
    ps_all = wp.float64(0.0)
    e_sal = wp.float64(0.0)  # ... and the salient ones
    ps_sal = wp.float64(0.0)
    for y in range(y0, y1):
        for x in range(x0, x1):
            v = src[y, x]
            r = wp.abs(coc[y, x])
            if on_level(v, r, r0, n_levels, lev):
                e = _raw_excess(v, mean)
                if e > 0.0:
                    e_all += wp.float64(e)
                    ps_all += wp.float64(e * r)
                    if _excess(v, r, mean, visible, floor) > 0.0:
                        n += 1
                        e_sal += wp.float64(e)
                        ps_sal += wp.float64(e * r)
    if e_all == wp.float64(0.0):
        return
    if n <= per_cell:
        if n > 0:
            for y in range(y0, y1):
                for x in range(x0, x1):
                    v = src[y, x]
                    r = wp.abs(coc[y, x])
                    if on_level(v, r, r0, n_levels, lev):
                        if _excess(v, r, mean, visible, floor) > 0.0:
                            exact[y, x] = wp.uint8(1)
    else:
        e_sal = wp.float64(0.0)
        ps_sal = wp.float64(0.0)
        bound = float(1.0e38)  # scores above it (or equal, earlier in row order) are already taken
        by = int(-1)
        bx = int(-1)
        for _ in range(per_cell):
            best = float(0.0)
            iy = int(-1)
            ix = int(-1)
            for y in range(y0, y1):
                for x in range(x0, x1):
                    v = src[y, x]
                    r = wp.abs(coc[y, x])
                    if on_level(v, r, r0, n_levels, lev):
                        s = _excess(v, r, mean, visible, floor)
                        if s > best:
                            after = s < bound or (s == bound and (y > by or (y == by and x > bx)))
                            if after:
                                best = s
                                iy = y
                                ix = x
            if iy < 0:
                break
            exact[iy, ix] = wp.uint8(1)
            e = _raw_excess(src[iy, ix], mean)
            e_sal += wp.float64(e)
            ps_sal += wp.float64(e * wp.abs(coc[iy, ix]))
            bound = best
            by = iy
            bx = ix
    e_sum = float(e_all - e_sal)  # the cluster's
    if e_sum <= 0.0:
        return
    s_mean = float((ps_all - ps_sal) / (e_all - e_sal))
    if e_sum - visible * wp.max(mean[0], floor) * 3.14159265 * s_mean * s_mean <= 0.0:
        return
    # visible together: its members' excess goes to level 0, gathered per block
    _scatter_blocks(src, coc, exact, nb, mean, r0, n_levels, lev, y0, y1, x0, x1, shape, buf0)
