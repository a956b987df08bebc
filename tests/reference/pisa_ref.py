"""Float64 NumPy oracle of the PISA masks (eq. 5-8): dense ``N x N`` matrices, rows = queries, columns = keys.

Written pair by pair from the paper's definitions, sharing no code with the
Warp kernels. Only for small images (N = h * w up to a few hundred).
"""

from __future__ import annotations

import math

import numpy as np

from .raytrace_ref import bilinear

GOLDEN_ANGLE = 2.399963229728653


def soft(x: np.ndarray, slope: float) -> np.ndarray:
    return 0.5 * (1.0 + np.tanh(0.5 * slope * x))  # = sigmoid(slope * x), overflow-free


def source_offsets(n: int, sigma: float) -> np.ndarray:
    """(x, y) offsets: the key itself for odd n, then mirrored pairs +-p_m; their mean is exactly 0."""
    out = [np.zeros(2)] if n % 2 else []
    pairs = n // 2
    for m in range(pairs):
        u = (m + 0.5) / pairs
        rad = sigma * math.sqrt(-2.0 * math.log(1.0 - u))
        p = np.array([rad * math.cos(m * GOLDEN_ANGLE), rad * math.sin(m * GOLDEN_ANGLE)])
        out += [p, -p]
    return np.array(out) if out else np.zeros((1, 2))


def coc_dense(d: np.ndarray, d_f: float, k_lat: float, slope: float, c: float = 1.0) -> np.ndarray:
    h, w = d.shape
    ys, xs = np.mgrid[0:h, 0:w]
    p = np.stack([xs.ravel(), ys.ravel()], axis=1).astype(np.float64)
    dist = np.linalg.norm(p[:, None, :] - p[None, :, :], axis=2)  # [q, k]
    r = k_lat * np.abs(d.ravel().astype(np.float64) - d_f)  # per key
    return soft(r[None, :] - c * dist, slope)


def collinear(q, ps, ds, dt, d_f, k_lat, model, eps):
    g = ps - q
    if model == "paper":
        ds_c = min(ds, 1 - eps)
        dt_c = max(dt, eps)
        return q + (1 - dt_c) * ds_c / ((1 - ds_c) * dt_c) * g
    den = k_lat * (ds - d_f)
    if abs(den) > eps:
        u = g / den
    elif np.linalg.norm(g) > 0:
        u = g / np.linalg.norm(g)
    else:
        u = np.zeros(2)
    if np.linalg.norm(u) > 1:
        u = u / np.linalg.norm(u)
    return q + k_lat * (dt - d_f) * u


def visibility_dense(d: np.ndarray, d_f: float, k_lat: float, n_sources: int = 5, sigma: float = 0.5,
                     n_steps: int = 8, margin_px: float = 0.5, model: str = "thin_lens",
                     eps: float = 1e-3) -> np.ndarray:
    h, w = d.shape
    d = d.astype(np.float64)
    margin = margin_px / k_lat if k_lat > 0 else 2.0
    offs = source_offsets(n_sources, sigma)
    n = h * w
    vis = np.zeros((n, n))
    for ki in range(n):
        ky, kx = divmod(ki, w)
        for qi in range(n):
            qy, qx = divmod(qi, w)
            q = np.array([qx, qy], np.float64)
            acc = 0.0
            for off in offs:
                ps = np.array([kx, ky], np.float64) + off
                ds = float(bilinear(d, ps[0] + 0.5, ps[1] + 0.5))  # texel centres at +0.5 there
                visible = True
                for i in range(n_steps):
                    dt = ds + (1 - ds) * (i + 0.5) / n_steps
                    p = collinear(q, ps, ds, dt, d_f, k_lat, model, eps)
                    ix, iy = int(math.floor(p[0] + 0.5)), int(math.floor(p[1] + 0.5))
                    if 0 <= ix < w and 0 <= iy < h and d[iy, ix] > dt + margin:
                        visible = False
                        break
                acc += visible
            vis[qi, ki] = acc / len(offs)
    return vis


def window_to_dense(win: np.ndarray, window: int) -> np.ndarray:
    """Scatter a key-centric window ``h x w x (2w+1)^2`` into a dense ``[q, k]`` matrix."""
    h, w, n_off = win.shape
    n = 2 * window + 1
    out = np.zeros((h * w, h * w), win.dtype)
    for ky in range(h):
        for kx in range(w):
            for o in range(n_off):
                qy, qx = ky + o // n - window, kx + o % n - window
                if 0 <= qy < h and 0 <= qx < w:
                    out[qy * w + qx, ky * w + kx] = win[ky, kx, o]
    return out
