"""Slow, obvious NumPy references for the soft scene (``bokehray.scene.split_scene``, ``bokehray_kernels.soft``),
and a two-plane scene whose exact split is known.

Written from docs/renderer.md ("Soft edges"): a split pixel's far part replaces it (colour B, CoC ``far_coc``);
its near part, ``(alpha F, alpha)`` at ``near_coc``, is a source of the layer ``near_coc`` falls in, at the
pixel's place, where that layer has no source of its own.
"""

from __future__ import annotations

import math

import numpy as np


def near_sources(src: np.ndarray, coc: np.ndarray, parts: dict, layer: int, y0: int, x0: int) -> None:
    """Write the near parts of ``layer`` (``parts``: y, x, value, coc, layer, in window coordinates) into the
    sources of the box at ``(y0, x0)`` (``src`` h x w x 4, ``coc`` h x w), in place. Loops, one part at a time."""
    h, w = coc.shape
    for i in range(len(parts["y"])):
        if parts["layer"][i] != layer:
            continue
        y, x = int(parts["y"][i]) - y0, int(parts["x"][i]) - x0
        if 0 <= y < h and 0 <= x < w:
            src[y, x] = parts["value"][i]
            coc[y, x] = parts["coc"][i]


# --------------------------------------------------------------------------- the two-plane scene


def _coverage(inside, h: int, w: int, ss: int = 8) -> np.ndarray:
    """Pixel coverage of the region ``inside(y, x)`` (float64 pixel coordinates, centres at i + 0.5), by
    ``ss`` x ``ss`` supersampling."""
    o = (np.arange(ss) + 0.5) / ss
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    cov = np.zeros((h, w))
    for dy in o:
        for dx in o:
            cov += inside(yy + dy, xx + dx)
    return cov / (ss * ss)


def two_plane_scene(h: int = 160, w: int = 224, background: str = "smooth") -> dict:
    """A sharp far plane and a near plane (an antialiased cut-out disc and thin strands 0.5 - 2.5 px wide).

    Returns the straight-alpha near RGBA, the far RGB, the disc's centre and radius, the strands' pixels, and
    the flattened photo ``alpha F + (1 - alpha) B``. ``background``: "smooth" (low-frequency colour), "flat"
    (one colour: the fill behind the disc is exact) or "texture" (adds fine detail the fill cannot guess).
    """
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64) + 0.5
    far = np.stack([0.25 + 0.12 * np.sin(xx / 23.0) + 0.05 * np.cos(yy / 31.0),
                    0.35 + 0.10 * np.cos(xx / 29.0 + yy / 41.0),
                    0.45 + 0.12 * np.sin(yy / 19.0)], axis=-1)
    if background == "flat":
        far = np.broadcast_to(np.array([0.3, 0.4, 0.5]), far.shape).copy()
    elif background == "texture":
        far = far + 0.08 * np.sign(np.sin(xx / 2.3) * np.sin(yy / 3.1))[..., None]
    near_rgb = np.stack([0.95 + 0.05 * np.sin(yy / 17.0), 0.55 + 0.1 * np.cos(xx / 13.0),
                         0.15 + 0.05 * np.sin((xx + yy) / 11.0)], axis=-1)
    cy, cx, radius = h * 0.5, w * 0.28, min(h, w) * 0.25
    disc = _coverage(lambda y, x: (y - cy) ** 2 + (x - cx) ** 2 <= radius * radius, h, w)
    strands = np.zeros((h, w))
    widths = [0.5, 0.8, 1.2, 1.7, 2.5]
    for k, width in enumerate(widths):  # near-vertical lines, slightly slanted (every sub-pixel phase)
        x_top = w * 0.58 + k * w * 0.08
        slope = 0.08 + 0.03 * k

        def line(y, x, x_top=x_top, slope=slope, width=width):
            d = np.abs(x - (x_top + slope * y)) / math.sqrt(1.0 + slope * slope)
            return (d <= width / 2) & (y > h * 0.1) & (y < h * 0.9)

        strands = np.maximum(strands, _coverage(line, h, w))
    alpha = np.clip(disc + strands, 0.0, 1.0)
    photo = alpha[..., None] * near_rgb + (1.0 - alpha[..., None]) * far
    return {"alpha": alpha.astype(np.float32), "near_rgb": near_rgb.astype(np.float32),
            "far_rgb": far.astype(np.float32), "photo": photo.astype(np.float32), "disc": (cy, cx, radius),
            "strands": strands > 0}


def silhouette_ring(h: int, w: int, disc: tuple[float, float, float], width: float = 1.5) -> np.ndarray:
    """Pixels whose centre lies within ``width`` px of the disc's outline."""
    cy, cx, radius = disc
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64) + 0.5
    return np.abs(np.hypot(yy - cy, xx - cx) - radius) <= width


def exact_split(scene: dict, near_coc: float, far_coc: float):
    """The perfect split of the photo's mixed pixels (0 < alpha < 1) as SoftEdges fields (index, alpha, F, B,
    near CoC, far CoC)."""
    a = scene["alpha"].ravel()
    idx = np.flatnonzero((a > 0) & (a < 1)).astype(np.int64)
    n = len(idx)
    return dict(index=idx, alpha=a[idx].astype(np.float32),
                foreground=scene["near_rgb"].reshape(-1, 3)[idx].astype(np.float32),
                background=scene["far_rgb"].reshape(-1, 3)[idx].astype(np.float32),
                near_coc=np.full(n, near_coc, np.float32), far_coc=np.full(n, far_coc, np.float32))


def psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> float:
    """PSNR (dB, peak 1) of linear RGB over ``mask`` (all pixels when None)."""
    d = (np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2
    if mask is not None:
        d = d[mask]
    mse = float(d.mean())
    return math.inf if mse == 0 else 10.0 * math.log10(1.0 / mse)
