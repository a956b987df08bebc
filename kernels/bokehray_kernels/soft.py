"""The near parts of split mixed pixels (``bokehray.scene.split_scene``) as sources of their layers.

A pixel on a depth edge holds a near colour F with coverage alpha over a far colour B. The scene
keeps the far part as the pixel (a source of the far layer); the near part is a sparse list of
extra sources, each written into the layer its CoC falls in, where that layer has no source of
its own (the pixel belongs to a farther layer, and a layer's fill covers only pixels nearer
layers own).
"""

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.kernel
def near_sources_kernel(
    near_y: wp.array(dtype=wp.int32),
    near_x: wp.array(dtype=wp.int32),
    near_value: wp.array(dtype=wp.vec4),
    near_coc: wp.array(dtype=float),
    near_layer: wp.array(dtype=wp.int32),
    layer: int,
    x0: int,
    y0: int,
    src: wp.array2d(dtype=wp.vec4),
    coc: wp.array2d(dtype=float),
):
    """Write the near parts of ``layer`` that fall in the box at ``(y0, x0)`` (window coordinates) into its
    sources: ``src`` gets the premultiplied ``(alpha F, alpha)``, ``coc`` its signed CoC. One thread a part."""
    i = wp.tid()
    if near_layer[i] != layer:
        return
    y = near_y[i] - y0
    x = near_x[i] - x0
    if y < 0 or x < 0 or y >= src.shape[0] or x >= src.shape[1]:
        return
    src[y, x] = near_value[i]
    coc[y, x] = near_coc[i]
