"""Layer sources and pull-push filling of the region a layer hides behind nearer layers.

A photo shows each depth layer only where nothing nearer covers it. When the
nearer layer is defocused, the thin-lens image sees *behind* its edges, so each
layer is extended into its hidden region by pull-push interpolation (a
weighted image pyramid: average down where the layer is present, interpolate
back up where it is not). Colour is filled in tone-mapped form ``c / (1 + c)``
so that a bright light next to an occluder does not flood the hidden area; the
4th channel carries the signed CoC so a tilted surface continues its tilt.
"""

import warp as wp

from .reduce import sum_2x2_float, sum_2x2_vec4
from .sampling import bilinear_taps

wp.set_module_options({"enable_backward": False})

FILL_GATE_SLOPE = 1.4142135
"""sqrt(2): a layer is filled where its visible pixels lie within ``FILL_GATE_SLOPE * r + 1`` px (L1) of a hidden
pixel whose hider has CoC radius ``r`` (the L1 bound of a Euclidean disc). The host pads layer boxes by it."""
_GATE = wp.constant(FILL_GATE_SLOPE)


@wp.struct
class PullPushLevel:
    """One level of a layer's pull-push pyramid: sums of (tone-mapped RGB, signed CoC) ``total``, of the layer's
    pixels ``weight`` and of the visible pixels ``known``; pushed in place to (mean value, density, has)."""

    total: wp.array2d(dtype=wp.vec4)
    weight: wp.array2d(dtype=float)
    known: wp.array2d(dtype=float)


@wp.func
def _tonemap(c: float) -> float:
    return c / (1.0 + wp.max(c, 0.0))


@wp.func
def _fill_texel(image: wp.array2d(dtype=wp.vec3), signed_coc: wp.array2d(dtype=float), gy: int, gx: int) -> wp.vec4:
    """Level 0 of the pull-push pyramid at a pixel of the layer: (tone-mapped RGB, signed CoC), weight 1."""
    c = image[gy, gx]
    return wp.vec4(_tonemap(c[0]), _tonemap(c[1]), _tonemap(c[2]), signed_coc[gy, gx])


@wp.func
def _untonemap(t: float) -> float:
    t = wp.clamp(t, 0.0, 0.999999)
    return t / (1.0 - t)


@wp.func
def _layer_source(image: wp.array2d(dtype=wp.vec3), signed_coc: wp.array2d(dtype=float),
                  slice_id: wp.array2d(dtype=wp.int32), layer: int, x0: int, y0: int, with_fill: int,
                  src: wp.array2d(dtype=wp.vec4), coc: wp.array2d(dtype=float), fill: PullPushLevel, y: int, x: int):
    # one pixel of layer_sources_kernel
    gy = y + y0
    gx = x + x0
    sid = slice_id[gy, gx]
    if sid < 0 or sid > layer:
        return  # copied, or hidden by a nearer layer: the arrays' zeros stand
    if with_fill != 0:
        fill.known[y, x] = 1.0
    if sid == layer:
        c = image[gy, gx]
        src[y, x] = wp.vec4(c[0], c[1], c[2], 1.0)
        coc[y, x] = signed_coc[gy, gx]
        if with_fill != 0:
            fill.total[y, x] = _fill_texel(image, signed_coc, gy, gx)
            fill.weight[y, x] = 1.0


@wp.kernel
def layer_sources_kernel(
    span: int,
    image: wp.array2d(dtype=wp.vec3),
    signed_coc: wp.array2d(dtype=float),
    slice_id: wp.array2d(dtype=wp.int32),
    layer: int,
    x0: int,
    y0: int,
    with_fill: int,
    src: wp.array2d(dtype=wp.vec4),
    coc: wp.array2d(dtype=float),
    fill: PullPushLevel,
):
    """Sources of one layer in local coordinates: (RGB, 1) on its pixels; every array must come zeroed.

    ``coc`` receives the *signed* CoC (the scatter takes its magnitude; the
    ray tracer turns it back into disparity).

    With ``with_fill != 0`` also ``fill``, level 0 of the pull-push pyramid: (tone-mapped
    RGB, signed CoC) with weight 1 on the layer, and ``known = 1`` wherever the
    photo shows this layer or something behind it (not hidden by a nearer layer).

    A thread takes ``span`` consecutive pixels of a row, a launch of (rows, ceil(width / span)): a row a thread
    on a CPU, a pixel a thread on a GPU (``bokehray.scene.row_span``).
    """
    y, j = wp.tid()
    for x in range(j * span, wp.min(src.shape[1], j * span + span)):
        _layer_source(image, signed_coc, slice_id, layer, x0, y0, with_fill, src, coc, fill, y, x)


@wp.kernel
def pull_kernel(fine: PullPushLevel, coarse: PullPushLevel):
    """Coarse pixel = sum of its (up to) 2 x 2 children: values, weights and known counts."""
    y, x = wp.tid()
    coarse.total[y, x] = sum_2x2_vec4(fine.total, y, x)
    coarse.weight[y, x] = sum_2x2_float(fine.weight, y, x)
    coarse.known[y, x] = sum_2x2_float(fine.known, y, x)


@wp.func
def _layer_pull(image: wp.array2d(dtype=wp.vec3), signed_coc: wp.array2d(dtype=float),
                slice_id: wp.array2d(dtype=wp.int32), layer: int, x0: int, y0: int, h: int, w: int,
                coarse: PullPushLevel, cy: int, cx: int):
    # one texel of layer_pull_kernel
    total = wp.vec4()
    weight = float(0.0)
    known = float(0.0)
    for dy in range(2):
        for dx in range(2):
            y = 2 * cy + dy
            x = 2 * cx + dx
            if y < h and x < w:
                t = wp.vec4()
                wt = float(0.0)
                k = float(0.0)
                sid = slice_id[y + y0, x + x0]
                if sid >= 0 and sid <= layer:
                    k = 1.0
                    if sid == layer:
                        t = _fill_texel(image, signed_coc, y + y0, x + x0)
                        wt = 1.0
                total = total + t
                weight = weight + wt
                known = known + k
    coarse.total[cy, cx] = total
    coarse.weight[cy, cx] = weight
    coarse.known[cy, cx] = known


@wp.kernel
def layer_pull_kernel(
    span: int,
    image: wp.array2d(dtype=wp.vec3),
    signed_coc: wp.array2d(dtype=float),
    slice_id: wp.array2d(dtype=wp.int32),
    layer: int,
    x0: int,
    y0: int,
    h: int,
    w: int,
    coarse: PullPushLevel,
):
    """Level 1 of the pull-push pyramid of the ``h x w`` window at ``(y0, x0)``, straight from the photo: bit for bit
    :func:`pull_kernel` of the level 0 that :func:`layer_sources_kernel` writes with ``with_fill != 0`` (the same
    texels, summed in the same order), without storing level 0 (24 bytes a pixel of the layer's box).

    A thread takes ``span`` consecutive cells of a row, a launch of (rows, ceil(width / span)): a row a thread
    on a CPU, a pixel a thread on a GPU (``bokehray.scene.row_span``).
    """
    cy, j = wp.tid()
    for cx in range(j * span, wp.min(coarse.total.shape[1], j * span + span)):
        _layer_pull(image, signed_coc, slice_id, layer, x0, y0, h, w, coarse, cy, cx)


@wp.struct
class Pushed:
    """One texel of a pushed level: mean value, density, and whether the density is known (1) or not (0)."""

    value: wp.vec4
    density: float
    has: float


@wp.func
def push_texel(coarse: PullPushLevel, top: int, x: int, y: int, total: wp.vec4, w: float, k: float) -> Pushed:
    """Texel ``(y, x)`` of a level with sums (``total``, weight ``w``, known ``k``), pushed from the ``coarse`` level
    (already pushed: its ``total``, ``weight`` and ``known`` hold value, density and has).

    ``value``: mean (tone-mapped RGB, signed CoC) of the layer's own pixels.
    ``density``: the share of the visible (not hidden) pixels that belong to the
    layer, so a sparse layer (strokes, wires, twigs over a background) fills its
    hidden region sparsely, and a continuous surface fills it opaquely.
    ``has``: 1 where the density is known. Where this level has no visible
    pixel, both come from the coarser level (bilinear, weighted by what it has).
    With ``top != 0`` there is no coarser level.
    """
    v = wp.vec4()
    if w > 0.0:
        v = total / w
    density = float(0.0)
    has = float(0.0)
    if k > 0.0:
        density = w / k
        has = 1.0
    if (k <= 0.0 or w <= 0.0) and top == 0:
        coarse_value = coarse.total
        coarse_density = coarse.weight
        coarse_has = coarse.known
        t = bilinear_taps((float(x) + 0.5) * 0.5 - 0.5, (float(y) + 0.5) * 0.5 - 0.5, coarse_value.shape[0],
                          coarse_value.shape[1])
        b00 = (1.0 - t.tx) * (1.0 - t.ty)
        b01 = t.tx * (1.0 - t.ty)
        b10 = (1.0 - t.tx) * t.ty
        b11 = t.tx * t.ty
        if k <= 0.0:
            h00 = b00 * coarse_has[t.y0, t.x0]
            h01 = b01 * coarse_has[t.y0, t.x1]
            h10 = b10 * coarse_has[t.y1, t.x0]
            h11 = b11 * coarse_has[t.y1, t.x1]
            hs = h00 + h01 + h10 + h11
            if hs > 1.0e-8:
                density = (h00 * coarse_density[t.y0, t.x0] + h01 * coarse_density[t.y0, t.x1] + h10 * coarse_density[t.y1, t.x0]
                           + h11 * coarse_density[t.y1, t.x1]) / hs
                has = 1.0
        if w <= 0.0:
            # colour only from coarse pixels that hold some of the layer
            d00 = b00 * coarse_has[t.y0, t.x0] * coarse_density[t.y0, t.x0]
            d01 = b01 * coarse_has[t.y0, t.x1] * coarse_density[t.y0, t.x1]
            d10 = b10 * coarse_has[t.y1, t.x0] * coarse_density[t.y1, t.x0]
            d11 = b11 * coarse_has[t.y1, t.x1] * coarse_density[t.y1, t.x1]
            ds = d00 + d01 + d10 + d11
            if ds > 1.0e-8:
                v = (coarse_value[t.y0, t.x0] * d00 + coarse_value[t.y0, t.x1] * d01 + coarse_value[t.y1, t.x0] * d10
                     + coarse_value[t.y1, t.x1] * d11) / ds
    p = Pushed()
    p.value = v
    p.density = density
    p.has = has
    return p


@wp.func
def _push(coarse: PullPushLevel, top: int, level: PullPushLevel, y: int, x: int):
    # one texel of push_kernel
    p = push_texel(coarse, top, x, y, level.total[y, x], level.weight[y, x], level.known[y, x])
    level.total[y, x] = p.value
    level.weight[y, x] = p.density
    level.known[y, x] = p.has


@wp.kernel
def push_kernel(span: int, coarse: PullPushLevel, top: int, level: PullPushLevel):
    """Turn one level's sums into (value, density, has) in place, interpolating what it lacks (:func:`push_texel`).

    The preview pushes levels down to 1 only: :func:`fill_sources_kernel` pushes the level-0 texels it fills.

    A thread takes ``span`` consecutive pixels of a row, a launch of (rows, ceil(width / span)): a row a thread
    on a CPU, a pixel a thread on a GPU (``bokehray.scene.row_span``).
    """
    y, j = wp.tid()
    for x in range(j * span, wp.min(level.total.shape[1], j * span + span)):
        _push(coarse, top, level, y, x)


@wp.func
def _fill_source(slice_id: wp.array2d(dtype=wp.int32), layer: int, x0: int, y0: int, coarse: PullPushLevel,
                 dist_l1: wp.array2d(dtype=float), signed_coc: wp.array2d(dtype=float), s_lo: float, s_hi: float,
                 src: wp.array2d(dtype=wp.vec4), coc: wp.array2d(dtype=float), n_filled: wp.array(dtype=wp.int32),
                 y: int, x: int):
    # one pixel of fill_sources_kernel
    gy = y + y0
    gx = x + x0
    if slice_id[gy, gx] <= layer or dist_l1[y, x] > _GATE * wp.abs(signed_coc[gy, gx]) + 1.0:
        return  # not hidden, or behind a hider too sharp to reveal it
    p = push_texel(coarse, 0, x, y, wp.vec4(), 0.0, 0.0)  # a hidden pixel's level-0 sums: all zero
    density = p.density
    if density >= 0.02:
        v = p.value
        a = wp.min(density, 1.0)
        src[y, x] = wp.vec4(_untonemap(v[0]) * a, _untonemap(v[1]) * a, _untonemap(v[2]) * a, a)
        coc[y, x] = wp.clamp(v[3], s_lo, s_hi)
        wp.atomic_add(n_filled, layer, 1)


@wp.kernel
def fill_sources_kernel(
    span: int,
    slice_id: wp.array2d(dtype=wp.int32),
    layer: int,
    x0: int,
    y0: int,
    coarse: PullPushLevel,
    dist_l1: wp.array2d(dtype=float),
    signed_coc: wp.array2d(dtype=float),
    s_lo: float,
    s_hi: float,
    src: wp.array2d(dtype=wp.vec4),
    coc: wp.array2d(dtype=float),
    n_filled: wp.array(dtype=wp.int32),
):
    """Add the filled colour as sources where a nearer layer hides this one.

    ``coarse``: level 1, pushed. Each hidden pixel pushes its own level-0 texel (:func:`push_texel`, exactly
    what ``push_kernel`` would have stored there), so level 0 is never pushed, nor stored: a hidden pixel's
    level-0 sums are zero (:func:`layer_sources_kernel` writes none there).

    Opacity is the layer's extrapolated density: 1 for a continuous surface,
    the stroke coverage for a sparse layer (premultiplied, like every source).

    Only where the hiding pixel is itself blurred enough to reveal it: the L1
    distance to this layer's visible pixels is at most sqrt(2) times the
    hiding pixel's CoC radius (plus one pixel). Behind a sharp occluder
    nothing is filled; the coverage normalisation of the layer handles it.

    A thread takes ``span`` consecutive pixels of a row, a launch of (rows, ceil(width / span)): a row a thread
    on a CPU, a pixel a thread on a GPU (``bokehray.scene.row_span``).
    """
    y, j = wp.tid()
    for x in range(j * span, wp.min(src.shape[1], j * span + span)):
        _fill_source(slice_id, layer, x0, y0, coarse, dist_l1, signed_coc, s_lo, s_hi, src, coc, n_filled, y, x)


@wp.kernel
def row_distance_kernel(
    slice_id: wp.array2d(dtype=wp.int32),
    layer: int,
    x0: int,
    y0: int,
    width: int,
    dist: wp.array2d(dtype=float),
):
    """Horizontal distance (pixels) from each local pixel to the nearest pixel of ``layer`` in its row.

    The pass from the left leaves 0 exactly at the layer's pixels (and at least 1 elsewhere), so the pass from the
    right finds them there without reading ``slice_id`` again."""
    y = wp.tid()
    big = float(1.0e9)
    last = float(-1.0e9)
    for x in range(width):
        if slice_id[y + y0, x + x0] == layer:
            last = float(x)
        dist[y, x] = wp.min(float(x) - last, big)
    last = float(1.0e9)
    for i in range(width):
        x = width - 1 - i
        d = dist[y, x]
        if d == 0.0:
            last = float(x)
        dist[y, x] = wp.min(d, last - float(x))


@wp.kernel
def column_distance_kernel(dist: wp.array2d(dtype=float), height: int, band: int):
    """Second pass of the city-block (L1) distance transform, in place, per band of ``band`` columns.

    Each thread sweeps its band row by row (contiguous memory on the CPU);
    on a GPU use ``band = 1`` (one thread per column).
    """
    b = wp.tid()
    xa = b * band
    xb = wp.min(xa + band, dist.shape[1])
    for y in range(1, height):
        for x in range(xa, xb):
            dist[y, x] = wp.min(dist[y, x], dist[y - 1, x] + 1.0)
    for i in range(1, height):
        y = height - 1 - i
        for x in range(xa, xb):
            dist[y, x] = wp.min(dist[y, x], dist[y + 1, x] + 1.0)
