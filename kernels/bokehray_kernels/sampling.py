"""Bilinear sampling taps shared by the scatter, fill and ray-tracing kernels."""

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.struct
class Taps:
    """The four texels around a point and the blend weights: ``(x0, y0)``, ``(x1, y1)``, ``tx``, ``ty``."""

    x0: int
    y0: int
    x1: int
    y1: int
    tx: float
    ty: float


@wp.func
def bilinear_taps(fx: float, fy: float, h: int, w: int) -> Taps:
    """Taps of texel-centre coordinates ``(fx, fy)`` on an ``h x w`` grid, clamped to its edge."""
    fx = wp.clamp(fx, 0.0, float(w - 1))
    fy = wp.clamp(fy, 0.0, float(h - 1))
    t = Taps()
    t.x0 = int(wp.floor(fx))
    t.y0 = int(wp.floor(fy))
    t.x1 = wp.min(t.x0 + 1, w - 1)
    t.y1 = wp.min(t.y0 + 1, h - 1)
    t.tx = fx - float(t.x0)
    t.ty = fy - float(t.y0)
    return t
