"""Layered thin-lens ray tracer: a deterministic aperture quadrature, composited front to back.

Thin lens in image space (docs/raytracer.md): the ray from output pixel
centre ``x`` through the aperture point ``u`` (unit disc: circumradius 1)
meets the surface of disparity ``d`` at pinhole-image position

    p(d) = x + K (d - d_f) u,

so a point at disparity ``d`` spreads into the aperture shape of radius
``K |d - d_f|`` around its pinhole position: the CoC convention of the whole
project. A layer is an RGBA texture (premultiplied, scene-linear) with its
disparity either a plane ``d(p) = a p_x + b p_y + c`` or a per-pixel map.

The aperture is not point-sampled: it is cut into box cells (host side:
``bokehray.quadrature``), each with a centre ``u_c``, half sizes ``h`` and a
weight (its share of the aperture's area). One ray per cell goes through
``u_c``; where it meets a layer at disparity ``d`` the cell's footprint on the
layer is the box of half sizes ``K |d - d_f| h`` around the hit, and the
layer's texture is averaged over that box exactly, from a float64 summed-area
table of the texture read as constant over each pixel. Along the ray the
layers are composited nearest first with the cell means,
``C += T * rgb``, ``T *= 1 - a``. The footprints of a layer's cells tile the
aperture's footprint, so a fronto-parallel layer is integrated exactly over the
(polygonised) aperture: the estimator has no noise, and its bias is the
outline's polygonisation plus, between layers, treating the nearer layer's
coverage and the farther layer's colour as uncorrelated inside one cell.

Textures continue their border rows and columns outwards (clamp-to-edge) for
rays that leave the layer's extent. The single-ray level (``hx = hy = 0``:
everything within half a pixel of focus) reads a 1 px box, i.e. the texture
interpolated bilinearly between pixel centres.
"""

import warp as wp

from .sampling import bilinear_taps

wp.set_module_options({"enable_backward": False})


@wp.func
def sat_inside(sat: wp.array3d(dtype=wp.vec4d), layer: int, x: wp.float64, y: wp.float64) -> wp.vec4d:
    """The table at a point of ``[0, W] x [0, H]``: bilinear between its corners (exact for box texels)."""
    w = sat.shape[2] - 1
    h = sat.shape[1] - 1
    i0 = wp.min(int(wp.floor(x)), w - 1)
    j0 = wp.min(int(wp.floor(y)), h - 1)
    fx = x - wp.float64(i0)
    fy = y - wp.float64(j0)
    one = wp.float64(1.0)
    top = sat[layer, j0, i0] * (one - fx) + sat[layer, j0, i0 + 1] * fx
    bot = sat[layer, j0 + 1, i0] * (one - fx) + sat[layer, j0 + 1, i0 + 1] * fx
    return top * (one - fy) + bot * fy


@wp.func
def sat_at(sat: wp.array3d(dtype=wp.vec4d), layer: int, x: wp.float64, y: wp.float64) -> wp.vec4d:
    """Integral of the clamp-to-edge texture over ``[0, x] x [0, y]`` (signed), for any ``x, y``.

    Outside the extent the border column / row / corner texel continues:
    ``S(x, y) = S(xc, yc) + ex * col(yc) + ey * row(xc) + ex * ey * corner``.
    """
    w = wp.float64(sat.shape[2] - 1)
    h = wp.float64(sat.shape[1] - 1)
    zero = wp.float64(0.0)
    one = wp.float64(1.0)
    xc = wp.clamp(x, zero, w)
    yc = wp.clamp(y, zero, h)
    ex = x - xc
    ey = y - yc
    v = sat_inside(sat, layer, xc, yc)
    ecol = zero
    if ex > zero:
        ecol = w - one
    erow = zero
    if ey > zero:
        erow = h - one
    if ex != zero:
        v = v + (sat_inside(sat, layer, ecol + one, yc) - sat_inside(sat, layer, ecol, yc)) * ex
    if ey != zero:
        v = v + (sat_inside(sat, layer, xc, erow + one) - sat_inside(sat, layer, xc, erow)) * ey
    if ex != zero and ey != zero:
        ci = int(ecol)
        cj = int(erow)
        corner = sat[layer, cj + 1, ci + 1] - sat[layer, cj, ci + 1] - sat[layer, cj + 1, ci] + sat[layer, cj, ci]
        v = v + corner * (ex * ey)
    return v


@wp.func
def box_mean(sat: wp.array3d(dtype=wp.vec4d), layer: int, p: wp.vec2, hx: float, hy: float) -> wp.vec4:
    """Mean of the texture over the box of half sizes ``(hx, hy)`` > 0 centred at ``p`` (pixel units)."""
    cx = wp.float64(p[0])
    cy = wp.float64(p[1])
    ax = wp.float64(hx)
    ay = wp.float64(hy)
    i0 = int(wp.floor(cx - ax))
    j0 = int(wp.floor(cy - ay))
    if (i0 == int(wp.floor(cx + ax)) and j0 == int(wp.floor(cy + ay)) and i0 >= 0 and j0 >= 0
            and i0 < sat.shape[2] - 1 and j0 < sat.shape[1] - 1):
        # the box lies inside one texel (a layer near focus): its value
        t = sat[layer, j0 + 1, i0 + 1] - sat[layer, j0, i0 + 1] - sat[layer, j0 + 1, i0] + sat[layer, j0, i0]
        return wp.vec4(float(t[0]), float(t[1]), float(t[2]), float(t[3]))
    s = (sat_at(sat, layer, cx + ax, cy + ay) - sat_at(sat, layer, cx - ax, cy + ay)
         - sat_at(sat, layer, cx + ax, cy - ay) + sat_at(sat, layer, cx - ax, cy - ay))
    m = s / (wp.float64(4.0) * ax * ay)
    return wp.vec4(float(m[0]), float(m[1]), float(m[2]), float(m[3]))


@wp.func
def sample_layer_disp(disp: wp.array3d(dtype=float), layer: int, p: wp.vec2) -> float:
    t = bilinear_taps(p[0] - 0.5, p[1] - 0.5, disp.shape[1], disp.shape[2])
    top = disp[layer, t.y0, t.x0] * (1.0 - t.tx) + disp[layer, t.y0, t.x1] * t.tx
    bot = disp[layer, t.y1, t.x0] * (1.0 - t.tx) + disp[layer, t.y1, t.x1] * t.tx
    return top * (1.0 - t.ty) + bot * t.ty


@wp.func
def point_alpha(sat: wp.array3d(dtype=wp.vec4d), layer: int, p: wp.vec2) -> float:
    return box_mean(sat, layer, p, 0.5, 0.5)[3]


@wp.func
def intersect_layer(
    sat: wp.array3d(dtype=wp.vec4d),
    disp: wp.array3d(dtype=float),
    layer: int,
    plane: wp.vec4,
    drange: wp.vec2,
    x: wp.vec2,
    su: wp.vec2,
    d_f: float,
) -> wp.vec4:
    """First visible hit of the ray ``p(d) = x + (d - d_f) su`` (``su = K u``): ``(p_x, p_y, d, hit)``.

    A map layer is marched from its nearest to its farthest disparity in
    half-pixel steps of ``p``; a crossing where the layer is transparent
    (alpha < 1e-4: outside the layer's content) does not stop the march.
    """
    if plane[3] != 0.0:
        # plane d = g.p + c: solve p = q + su (g.p) with q = x + (c - d_f) su (Sherman-Morrison)
        g = wp.vec2(plane[0], plane[1])
        q = x + su * (plane[2] - d_f)
        den = 1.0 - wp.dot(g, su)
        if wp.abs(den) < 1.0e-6:
            return wp.vec4(0.0, 0.0, 0.0, 0.0)  # ray grazes the plane: no hit
        p = q + su * (wp.dot(g, q) / den)
        return wp.vec4(p[0], p[1], wp.dot(g, p) + plane[2], 1.0)
    # per-pixel map: march d from near to far in half-pixel steps of p, then refine the crossing
    lo = drange[0]
    hi = drange[1]
    step_px = wp.length(su)
    if step_px < 1.0e-6:
        return wp.vec4(x[0], x[1], sample_layer_disp(disp, layer, x), 1.0)  # in focus: the pinhole position
    n = int(wp.ceil((hi - lo) * step_px / 0.5)) + 1
    dd = (hi - lo) / float(n)
    d_prev = hi
    p0 = x + su * (hi - d_f)
    f_prev = sample_layer_disp(disp, layer, p0) - hi
    if f_prev >= 0.0 and point_alpha(sat, layer, p0) >= 1.0e-4:
        return wp.vec4(p0[0], p0[1], hi, 1.0)
    for i in range(1, n + 1):
        d = hi - dd * float(i)
        f = sample_layer_disp(disp, layer, x + su * (d - d_f)) - d
        if f >= 0.0 and f_prev < 0.0:
            t = f_prev / (f_prev - f)  # linear crossing between the two samples
            dh = d_prev + (d - d_prev) * t
            p = x + su * (dh - d_f)
            if point_alpha(sat, layer, p) >= 1.0e-4:
                return wp.vec4(p[0], p[1], dh, 1.0)
        d_prev = d
        f_prev = f
    return wp.vec4(0.0, 0.0, 0.0, 0.0)


@wp.func
def trace_cell(
    sat: wp.array3d(dtype=wp.vec4d),
    disp: wp.array3d(dtype=float),
    planes: wp.array(dtype=wp.vec4),
    dranges: wp.array(dtype=wp.vec2),
    n_layers: int,
    k_px: float,
    d_f: float,
    centre: wp.vec2,
    cell: wp.vec4,
) -> wp.vec4:
    """One cell's ray through the layers, nearest first: ``(premultiplied RGB, 1 - transmittance)``."""
    u = wp.vec2(cell[0], cell[1])
    su = u * k_px
    colour = wp.vec3()
    trans = float(1.0)
    for layer in range(n_layers):
        hit = intersect_layer(sat, disp, layer, planes[layer], dranges[layer], centre, su, d_f)
        if hit[3] > 0.0:
            rad = wp.abs(k_px * (hit[2] - d_f))
            hx = float(0.5)
            hy = float(0.5)
            if cell[2] > 0.0:
                hx = wp.max(rad * cell[2], 1.0e-3)
                hy = wp.max(rad * cell[3], 1.0e-3)
            s = box_mean(sat, layer, wp.vec2(hit[0], hit[1]), hx, hy)
            colour = colour + wp.vec3(s[0], s[1], s[2]) * trans
            trans = trans * (1.0 - wp.clamp(s[3], 0.0, 1.0))
            if trans < 1.0e-6:
                break
    return wp.vec4(colour[0], colour[1], colour[2], 1.0 - trans)


@wp.kernel
def raytrace_kernel(
    sat: wp.array3d(dtype=wp.vec4d),
    disp: wp.array3d(dtype=float),
    planes: wp.array(dtype=wp.vec4),
    dranges: wp.array(dtype=wp.vec2),
    n_layers: int,
    k_px: float,
    d_f: float,
    cells: wp.array(dtype=wp.vec4),
    weights: wp.array(dtype=float),
    offsets: wp.array(dtype=wp.int32),
    level: wp.array2d(dtype=wp.int32),
    row0: int,
    tex_x0: int,
    tex_y0: int,
    out: wp.array2d(dtype=wp.vec4),
):
    """Weighted sum over the cells of level ``level[y, x]``; ``out`` = (RGB, 1 - transmittance).

    Launched over a band of rows: thread ``(y, x)`` is output pixel ``(y + row0, x)``,
    texture pixel ``(y + row0 + tex_y0, x + tex_x0)`` (a tile's core inside its window).
    """
    yb, x = wp.tid()
    y = yb + row0
    lv = level[y, x]
    centre = wp.vec2(float(x + tex_x0) + 0.5, float(y + tex_y0) + 0.5)
    acc = wp.vec4()
    for c in range(offsets[lv], offsets[lv + 1]):
        acc = acc + trace_cell(sat, disp, planes, dranges, n_layers, k_px, d_f, centre, cells[c]) * weights[c]
    out[y, x] = acc
