"""Layered thin-lens ray tracer: rays through the aperture, composited front to back.

Thin lens in image space (docs/raytracer.md): the ray from output pixel
centre ``x`` through the aperture point ``u`` (unit disc: circumradius 1)
meets the surface of disparity ``d`` at pinhole-image position

    p(d) = x + K (d - d_f) u,

so a point at disparity ``d`` spreads into the aperture shape of radius
``K |d - d_f|`` around its pinhole position: the CoC convention of the whole
project. A layer is an RGBA texture (premultiplied, scene-linear) with its
disparity either a plane ``d(p) = a p_x + b p_y + c`` or a per-pixel map. The
ray takes each layer's first intersection, in the given (front-to-back)
order, and composites ``C += T * rgba.rgb``, ``T *= 1 - rgba.a``. Textures are
sampled bilinearly with clamp-to-edge, so a ray leaving the layer's extent sees
the layer's border continued outwards (as the path-traced dev set does).
"""

import warp as wp

from .aperture import chord
from .sampling import bilinear_taps

wp.set_module_options({"enable_backward": False})

GOLDEN_ANGLE = 2.399963229728653


@wp.func
def hash_angle(x: int, y: int, seed: int) -> float:
    """Deterministic per-pixel rotation in [0, 2 pi) of the sample pattern (decorrelates neighbours)."""
    # three integer mixes (multipliers kept below 2^31 so they are valid Warp int literals)
    h = wp.uint32(x) * wp.uint32(1973) + wp.uint32(y) * wp.uint32(9277) + wp.uint32(seed) * wp.uint32(26699)
    h = h ^ (h >> wp.uint32(16))
    h = h * wp.uint32(0x7FEB352D)
    h = h ^ (h >> wp.uint32(15))
    h = h * wp.uint32(0x68E31DA4)
    h = h ^ (h >> wp.uint32(16))
    return float(h & wp.uint32(0xFFFFFF)) / 16777216.0 * 6.283185307179586


@wp.func
def aperture_sample(i: int, n: int, rotation: float) -> wp.vec2:
    """The i-th of n points of a rotated Vogel (golden-angle) spiral: area-uniform on the unit disc."""
    r = wp.sqrt((float(i) + 0.5) / float(n))
    t = float(i) * GOLDEN_ANGLE + rotation
    return wp.vec2(r * wp.cos(t), r * wp.sin(t))


@wp.func
def sample_layer_rgba(tex: wp.array3d(dtype=wp.vec4), layer: int, p: wp.vec2) -> wp.vec4:
    t = bilinear_taps(p[0] - 0.5, p[1] - 0.5, tex.shape[1], tex.shape[2])
    top = tex[layer, t.y0, t.x0] * (1.0 - t.tx) + tex[layer, t.y0, t.x1] * t.tx
    bot = tex[layer, t.y1, t.x0] * (1.0 - t.tx) + tex[layer, t.y1, t.x1] * t.tx
    return top * (1.0 - t.ty) + bot * t.ty


@wp.func
def sample_layer_disp(disp: wp.array3d(dtype=float), layer: int, p: wp.vec2) -> float:
    t = bilinear_taps(p[0] - 0.5, p[1] - 0.5, disp.shape[1], disp.shape[2])
    top = disp[layer, t.y0, t.x0] * (1.0 - t.tx) + disp[layer, t.y0, t.x1] * t.tx
    bot = disp[layer, t.y1, t.x0] * (1.0 - t.tx) + disp[layer, t.y1, t.x1] * t.tx
    return top * (1.0 - t.ty) + bot * t.ty


@wp.func
def intersect_layer(
    rgba: wp.array3d(dtype=wp.vec4),
    disp: wp.array3d(dtype=float),
    layer: int,
    plane: wp.vec4,
    drange: wp.vec2,
    x: wp.vec2,
    su: wp.vec2,
    d_f: float,
) -> wp.vec3:
    """First visible hit of the ray ``p(d) = x + (d - d_f) su`` (``su = K u``) with a layer: ``(p_x, p_y, hit)``.

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
            return wp.vec3(0.0, 0.0, 0.0)  # ray grazes the plane: no hit
        p = q + su * (wp.dot(g, q) / den)
        return wp.vec3(p[0], p[1], 1.0)
    # per-pixel map: march d from near to far in half-pixel steps of p, then refine the crossing
    lo = drange[0]
    hi = drange[1]
    step_px = wp.length(su)
    if step_px < 1.0e-6:
        return wp.vec3(x[0], x[1], 1.0)  # in focus: the ray sees the pinhole position
    n = int(wp.ceil((hi - lo) * step_px / 0.5)) + 1
    dd = (hi - lo) / float(n)
    d_prev = hi
    p0 = x + su * (hi - d_f)
    f_prev = sample_layer_disp(disp, layer, p0) - hi
    if f_prev >= 0.0 and sample_layer_rgba(rgba, layer, p0)[3] >= 1.0e-4:
        return wp.vec3(p0[0], p0[1], 1.0)
    for i in range(1, n + 1):
        d = hi - dd * float(i)
        f = sample_layer_disp(disp, layer, x + su * (d - d_f)) - d
        if f >= 0.0 and f_prev < 0.0:
            t = f_prev / (f_prev - f)  # linear crossing between the two samples
            dh = d_prev + (d - d_prev) * t
            p = x + su * (dh - d_f)
            if sample_layer_rgba(rgba, layer, p)[3] >= 1.0e-4:
                return wp.vec3(p[0], p[1], 1.0)
        d_prev = d
        f_prev = f
    return wp.vec3(0.0, 0.0, 0.0)


@wp.kernel
def raytrace_kernel(
    rgba: wp.array3d(dtype=wp.vec4),
    disp: wp.array3d(dtype=float),
    planes: wp.array(dtype=wp.vec4),
    dranges: wp.array(dtype=wp.vec2),
    n_layers: int,
    k_px: float,
    d_f: float,
    blades: wp.array(dtype=wp.vec4),
    n_blades: int,
    spp: wp.array2d(dtype=wp.int32),
    seed: int,
    tex_x0: int,
    tex_y0: int,
    img_x0: int,
    img_y0: int,
    out: wp.array2d(dtype=wp.vec4),
):
    """Average of ``spp[y, x]`` aperture rays per pixel; ``out`` = (RGB, 1 - transmittance).

    Output pixel ``(y, x)`` is texture pixel ``(y + tex_y0, x + tex_x0)``, and the
    textures start at pixel ``(img_y0, img_x0)`` of the whole image (a tile of a
    larger render): the sample pattern's rotation hashes the whole-image position,
    so a tiled render traces the same rays as an untiled one.
    """
    y, x = wp.tid()
    n = spp[y, x]
    tx = x + tex_x0
    ty = y + tex_y0
    rot = hash_angle(tx + img_x0, ty + img_y0, seed)
    centre = wp.vec2(float(tx) + 0.5, float(ty) + 0.5)
    acc = wp.vec4()
    used = int(0)
    for i in range(n):
        u = aperture_sample(i, n, rot)
        if n_blades > 0:
            c = chord(u[1], 1.0, blades, n_blades)
            if u[0] < c[0] or u[0] > c[1]:
                continue
        used += 1
        su = u * k_px
        colour = wp.vec3()
        trans = float(1.0)
        for layer in range(n_layers):
            hit = intersect_layer(rgba, disp, layer, planes[layer], dranges[layer], centre, su, d_f)
            if hit[2] > 0.0:
                s = sample_layer_rgba(rgba, layer, wp.vec2(hit[0], hit[1]))
                colour = colour + wp.vec3(s[0], s[1], s[2]) * trans
                trans = trans * (1.0 - wp.clamp(s[3], 0.0, 1.0))
                if trans < 1.0e-5:
                    break
        acc = acc + wp.vec4(colour[0], colour[1], colour[2], 1.0 - trans)
    if used == 0:
        # no sample fell inside a narrow aperture: use its centre ray
        colour = wp.vec3()
        trans = float(1.0)
        for layer in range(n_layers):
            hit = intersect_layer(rgba, disp, layer, planes[layer], dranges[layer], centre, wp.vec2(), d_f)
            if hit[2] > 0.0:
                s = sample_layer_rgba(rgba, layer, wp.vec2(hit[0], hit[1]))
                colour = colour + wp.vec3(s[0], s[1], s[2]) * trans
                trans = trans * (1.0 - wp.clamp(s[3], 0.0, 1.0))
        out[y, x] = wp.vec4(colour[0], colour[1], colour[2], 1.0 - trans)
    else:
        out[y, x] = acc / float(used)
