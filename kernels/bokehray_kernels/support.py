"""A layer's support: the tiles of the scene where any of its sources or its light can lie.

A depth layer cut at a jump of the depth map is often a thin population (the mixed pixels along
silhouettes) spread over a box as large as the frame; its sources and light fill only the tiles
within its reach of its own pixels. The host marks those tiles (``bokehray.scene.LayerSupport`` builds a
:class:`Support`), and the kernels whose work per pixel or cell is more than a read skip the rest, where
every value is zero. A 1 x 1 mask of 1 with ``shift`` 30 is "everywhere".
"""

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.struct
class Support:
    """A layer's support: a ``uint8`` tile mask on a grid of ``2^shift`` px in the scene's coordinates, and the
    layer box's origin ``(oy, ox)`` there."""

    mask: wp.array2d(dtype=wp.uint8)
    shift: int
    oy: int
    ox: int


@wp.func
def in_support(support: Support, y: int, x: int) -> bool:
    """Whether box pixel ``(y, x)`` lies in a support tile."""
    return support.mask[(y + support.oy) >> support.shift, (x + support.ox) >> support.shift] != wp.uint8(0)


@wp.func
def span_in_support(support: Support, y0: int, y1: int, x0: int, x1: int) -> bool:
    """Whether any box pixel of ``[y0, y1) x [x0, x1)`` lies in a support tile."""
    shift = support.shift
    oy = support.oy
    ox = support.ox
    for ty in range((y0 + oy) >> shift, ((y1 - 1 + oy) >> shift) + 1):
        for tx in range((x0 + ox) >> shift, ((x1 - 1 + ox) >> shift) + 1):
            if support.mask[ty, tx] != wp.uint8(0):
                return True
    return False


@wp.func
def tile_end(support: Support, x: int) -> int:
    """The first box column past the support tile holding box column ``x`` (a run of columns of one tile: one
    :func:`in_support` answer for all of them)."""
    return (((x + support.ox) >> support.shift) + 1 << support.shift) - support.ox
