"""Slow, obvious float64 NumPy layered thin-lens ray tracer (loops over pixels, rays and layers).

Same sample pattern as the Warp kernel (rotated Vogel spiral, integer-hash
rotation) so the two agree to rounding; convergence to the exact image is
tested separately with many rays.
"""

from __future__ import annotations

import math

import numpy as np

GOLDEN = 2.399963229728653
M32 = 0xFFFFFFFF


def hash_angle(x: int, y: int, seed: int) -> float:
    h = (x * 1973 + y * 9277 + seed * 26699) & M32
    h ^= h >> 16
    h = (h * 0x7FEB352D) & M32
    h ^= h >> 15
    h = (h * 0x68E31DA4) & M32
    h ^= h >> 16
    return (h & 0xFFFFFF) / 16777216.0 * 2.0 * math.pi


def bilinear(tex: np.ndarray, px: float, py: float) -> np.ndarray:
    h, w = tex.shape[:2]
    fx = min(max(px - 0.5, 0.0), w - 1.0)
    fy = min(max(py - 0.5, 0.0), h - 1.0)
    x0, y0 = int(math.floor(fx)), int(math.floor(fy))
    x1, y1 = min(x0 + 1, w - 1), min(y0 + 1, h - 1)
    tx, ty = fx - x0, fy - y0
    top = tex[y0, x0] * (1 - tx) + tex[y0, x1] * tx
    bot = tex[y1, x0] * (1 - tx) + tex[y1, x1] * tx
    return top * (1 - ty) + bot * ty


def trace(layers: list[tuple[np.ndarray, tuple[float, float, float]]], k: float, d_f: float,
          spp: int, seed: int = 0) -> np.ndarray:
    """Plane layers only, nearest first: ``(rgba straight-alpha H x W x 4, (a, b, c))``.

    For a ray from pixel centre ``x`` through aperture point ``u`` the hit on
    the plane ``d = g.p + c`` solves ``p = x + k (g.p + c - d_f) u`` (2 x 2 linear system).
    """
    h, w = layers[0][0].shape[:2]
    # interpolate premultiplied colour: a straight-alpha texel of alpha 0 has no colour to lend
    layers = [(np.concatenate([t[..., :3] * t[..., 3:], t[..., 3:]], axis=2), p) for t, p in layers]
    out = np.zeros((h, w, 4))
    for y in range(h):
        for x in range(w):
            rot = hash_angle(x, y, seed)
            acc = np.zeros(4)
            for i in range(spp):
                r, t = math.sqrt((i + 0.5) / spp), i * GOLDEN + rot
                u = np.array([r * math.cos(t), r * math.sin(t)])
                colour, trans = np.zeros(3), 1.0
                for tex, (a, b, c) in layers:
                    g = np.array([a, b])
                    # (I - k u g^T) p = x + k (c - d_f) u
                    m = np.eye(2) - k * np.outer(u, g)
                    p = np.linalg.solve(m, np.array([x + 0.5, y + 0.5]) + k * (c - d_f) * u)
                    s = bilinear(tex, p[0], p[1])
                    colour += trans * s[:3]
                    trans *= 1.0 - s[3]
                acc += np.concatenate([colour, [1.0 - trans]])
            out[y, x] = acc / spp
    return out
