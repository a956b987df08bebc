"""The 2 x 2 reduction of the image pyramids (the fill's pull-push, the preview's radiance pyramid)."""

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.func
def sum_2x2_vec4(a: wp.array2d(dtype=wp.vec4), cy: int, cx: int) -> wp.vec4:
    """Sum of the (up to) 2 x 2 children of coarse texel ``(cy, cx)``: children beyond ``a``'s edge are left out."""
    acc = wp.vec4()
    for dy in range(2):
        for dx in range(2):
            y = 2 * cy + dy
            x = 2 * cx + dx
            if y < a.shape[0] and x < a.shape[1]:
                acc = acc + a[y, x]
    return acc


@wp.func
def sum_2x2_float(a: wp.array2d(dtype=float), cy: int, cx: int) -> float:
    """:func:`sum_2x2_vec4` of a float array."""
    acc = float(0.0)
    for dy in range(2):
        for dx in range(2):
            y = 2 * cy + dy
            x = 2 * cx + dx
            if y < a.shape[0] and x < a.shape[1]:
                acc = acc + a[y, x]
    return acc


@wp.func
def children_2x2(h: int, w: int, cy: int, cx: int) -> float:
    """How many of the 2 x 2 children of coarse texel ``(cy, cx)`` lie inside an ``h x w`` level."""
    return float(wp.min(2, h - 2 * cy) * wp.min(2, w - 2 * cx))
