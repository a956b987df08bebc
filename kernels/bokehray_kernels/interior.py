"""A layer covers whole the pixels whose cone meets no farther surface.

A layer's coverage is the sum of its sources' footprints. Where the sources' radii differ (a surface turning a
little, a depth model's noise near the focus), the footprints no longer tile: a pixel of radius 0.6 among pixels of
radius 0.5 gathers 0.9, and the blurred layer behind shows through by a tenth, although a continuous opaque surface
blocks every ray of the pixel's cone. The cone of pixel ``p`` meets the scene within its own CoC radius ``r_p`` of
``p``; where no pixel within ``r_p + 1`` (Euclidean) lies beside a farther surface (a 4-neighbour farther by more
than ``jump`` of CoC, the matting's ``jump_px``: a depth edge, as the matting reads one), none is split or copied,
every ray of the cone stops at ``p``'s surface or nearer: ``p``'s own layer covers it whole (the composite takes
its coverage as 1 and its colour as its sources' coverage-weighted mean, ``composite._composite_at``), and nearer
layers go over it as always. A smooth surface cut by a layer boundary is no edge: its two layers' pixels may interleave.

The frame's map of such pixels, once per window: :func:`boundary_kernel` (0 at a pixel beside a farther surface or
copied, a large value elsewhere), :func:`mark_split_kernel` (0 at the split pixels), :func:`row_sweep_kernel` and
``fill.column_distance_kernel`` (the city-block distance to the nearest such pixel), :func:`opaque_flag_kernel` (1
where that distance exceeds ``sqrt(2) (r_p + 1)``, which holds the disc of radius ``r_p + 1``).

Oracle: ``tests/reference/interior_ref.py``.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})

FAR = wp.constant(1.0e9)


@wp.func
def _beside_farther(coc: wp.array2d(dtype=float), c: float, y: int, x: int, jump: float) -> bool:
    return coc[y, x] < c - jump


@wp.kernel
def boundary_kernel(span: int, ids: wp.array2d(dtype=wp.int32), coc: wp.array2d(dtype=float), jump: float,
                    dist: wp.array2d(dtype=float)):
    """0 at a copied pixel (``ids < 0``) or one with a 4-neighbour farther by more than ``jump`` of signed CoC (a
    depth edge; the frame's outside is no neighbour), ``FAR`` elsewhere. A launch of ``(rows, ceil(W / span))``."""
    y, j = wp.tid()
    h = coc.shape[0]
    w = coc.shape[1]
    for x in range(j * span, wp.min(w, j * span + span)):
        c = coc[y, x]
        edge = ids[y, x] < 0
        if x > 0:
            edge = edge or _beside_farther(coc, c, y, x - 1, jump)
        if x + 1 < w:
            edge = edge or _beside_farther(coc, c, y, x + 1, jump)
        if y > 0:
            edge = edge or _beside_farther(coc, c, y - 1, x, jump)
        if y + 1 < h:
            edge = edge or _beside_farther(coc, c, y + 1, x, jump)
        if edge:
            dist[y, x] = 0.0
        else:
            dist[y, x] = FAR


@wp.kernel
def mark_split_kernel(py: wp.array(dtype=wp.int32), px: wp.array(dtype=wp.int32), dist: wp.array2d(dtype=float)):
    """0 at each split pixel (its near part is a partial source: the layers there are not whole)."""
    i = wp.tid()
    dist[py[i], px[i]] = 0.0


@wp.kernel
def row_sweep_kernel(dist: wp.array2d(dtype=float)):
    """First pass of the city-block distance transform along row ``tid``, in place (forward, then backward)."""
    y = wp.tid()
    w = dist.shape[1]
    for x in range(1, w):
        dist[y, x] = wp.min(dist[y, x], dist[y, x - 1] + 1.0)
    for i in range(1, w):
        x = w - 1 - i
        dist[y, x] = wp.min(dist[y, x], dist[y, x + 1] + 1.0)


@wp.kernel
def opaque_flag_kernel(span: int, dist: wp.array2d(dtype=float), coc: wp.array2d(dtype=float),
                       flag: wp.array2d(dtype=wp.uint8)):
    """1 where the city-block distance ``dist`` exceeds ``sqrt(2) (|coc| + 1)``, else 0. A launch of ``(rows,
    ceil(W / span))``."""
    y, j = wp.tid()
    for x in range(j * span, wp.min(dist.shape[1], j * span + span)):
        if dist[y, x] > 1.4142135 * (wp.abs(coc[y, x]) + 1.0):
            flag[y, x] = wp.uint8(1)
        else:
            flag[y, x] = wp.uint8(0)
