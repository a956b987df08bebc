"""Compositing the scattered layers back to front ("over"), and the final division by the accumulated opacity."""

import warp as wp

from .support import Support, in_support, tile_end

wp.set_module_options({"enable_backward": False})


@wp.func
def _composite_at(layer: wp.array2d(dtype=wp.vec4), y: int, x: int, x0: int, y0: int, opaque: wp.array2d(dtype=wp.uint8),
                  ids: wp.array2d(dtype=wp.int32), index: int, acc: wp.array2d(dtype=wp.vec4)):
    # the layer's pixel (y, x) over the accumulator's (y + y0, x + x0)
    l = layer[y, x]
    cov = l[3]
    if cov <= 1.0e-6:
        return
    gy = y + y0
    gx = x + x0
    alpha = wp.min(cov, 1.0)
    if opaque[gy, gx] != wp.uint8(0) and ids[gy, gx] == index:
        alpha = 1.0  # the pixel's own layer, whole within its cone: it covers the pixel (``interior``)
    k = alpha / cov
    a = acc[gy, gx]
    t = 1.0 - alpha
    acc[gy, gx] = wp.vec4(l[0] * k + t * a[0], l[1] * k + t * a[1], l[2] * k + t * a[2], alpha + t * a[3])


@wp.kernel
def composite_kernel(span: int, layer: wp.array2d(dtype=wp.vec4), support: Support, x0: int, y0: int,
                     opaque: wp.array2d(dtype=wp.uint8), ids: wp.array2d(dtype=wp.int32), index: int,
                     acc: wp.array2d(dtype=wp.vec4)):
    """Composite one scattered layer OVER the accumulator (back-to-front "over").

    ``layer`` holds (sum of premultiplied RGB, sum of coverage) in local
    coordinates offset by ``(x0, y0)``. Its opacity is ``min(coverage, 1)`` and
    its colour is normalised by its coverage (so overlapping sources of one
    layer average instead of adding up); its opacity is 1 at the pixels of the layer (``ids == index``, in the
    accumulator's coordinates) that the frame's ``opaque`` map marks (``bokehray_kernels.interior``: the pixel's
    cone meets only its own layer, whose unequal footprints need not sum to 1). ``acc`` holds (RGB, opacity).
    Outside the layer's ``support`` it holds no light and is not read.

    A thread takes ``span`` consecutive pixels of a row, a launch of (rows, ceil(width / span)): a row a thread
    on a CPU, a pixel a thread on a GPU (``bokehray.scene.row_span``).
    """
    y, j = wp.tid()
    x = j * span
    x_end = wp.min(layer.shape[1], j * span + span)
    while x < x_end:
        end = wp.min(tile_end(support, x), x_end)  # columns of one support tile: one test for all of them
        if in_support(support, y, x):
            for xi in range(x, end):
                _composite_at(layer, y, xi, x0, y0, opaque, ids, index, acc)
        x = end


@wp.kernel
def finalize_kernel(
    acc: wp.array2d(dtype=wp.vec4),
    image: wp.array2d(dtype=wp.vec3),
    slice_id: wp.array2d(dtype=wp.int32),
    out: wp.array2d(dtype=wp.vec3),
):
    """Divide by the accumulated opacity (renormalises holes and borders).

    Copied pixels (``slice_id < 0``) and pixels no source reached keep the input.
    """
    y, x = wp.tid()
    a = acc[y, x]
    if slice_id[y, x] >= 0 and a[3] > 1.0e-4:
        out[y, x] = wp.vec3(a[0], a[1], a[2]) / a[3]
    else:
        out[y, x] = image[y, x]
