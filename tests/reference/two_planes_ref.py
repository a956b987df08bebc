"""Float64 exact thin-lens render of two fronto-parallel planes with analytic textures: a textured disc at
disparity 1 over a textured background at disparity 0 (the soft-map seam test, docs/soft-scene.md).

Every ray through the lens meets the near plane where the disc covers it, else the far plane; a pixel's value is
the mean over its area (``sub`` x ``sub`` points) and the aperture (``n_aperture`` points of a Fibonacci spiral,
uniform over the disc). The all-in-focus photo is the same mean at CoC 0 (``sub_photo`` x ``sub_photo`` points)."""

from __future__ import annotations

import numpy as np

GOLDEN = np.pi * (3.0 - np.sqrt(5.0))


def near_colour(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    t = np.sin(2 * np.pi * x / 23.0) * np.cos(2 * np.pi * y / 17.0)
    return np.stack([0.60 * (1 + 0.3 * t), 0.35 * (1 - 0.3 * t), 0.20 * (1 + 0.2 * t)], -1)


def far_colour(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    t = np.cos(2 * np.pi * x / 19.0 + 1.0) * np.sin(2 * np.pi * y / 29.0)
    return np.stack([0.15 * (1 + 0.3 * t), 0.30 * (1 + 0.2 * t), 0.55 * (1 - 0.3 * t)], -1)


class TwoPlanes:
    """The scene on an ``n`` x ``n`` frame: the disc of ``radius`` px about the frame's centre."""

    def __init__(self, n: int = 96, radius: float = 26.0):
        self.n, self.radius = n, radius
        self.c = n / 2.0

    def inside(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return (x - self.c) ** 2 + (y - self.c) ** 2 <= self.radius ** 2

    def _mean(self, offsets: list[tuple[float, float, float, float]]) -> np.ndarray:
        """Mean over (dx, dy, near_scale, far_scale) samples: pixel (i, j) at (j + 0.5 + dx, i + 0.5 + dy), the
        near plane read at ``near_scale`` (the aperture point times the near CoC), the far likewise."""
        yy, xx = np.mgrid[0 : self.n, 0 : self.n].astype(np.float64) + 0.5
        acc = np.zeros((self.n, self.n, 3))
        for dx, dy, ux, uy, ns, fs in offsets:
            px, py = xx + dx, yy + dy
            nx, ny = px + ns * ux, py + ns * uy
            hit = self.inside(nx, ny)[..., None]
            acc += np.where(hit, near_colour(nx, ny), far_colour(px + fs * ux, py + fs * uy))
        return acc / len(offsets)

    def photo(self, sub: int = 8) -> np.ndarray:
        g = (np.arange(sub) + 0.5) / sub - 0.5
        return self._mean([(dx, dy, 0.0, 0.0, 0.0, 0.0) for dy in g for dx in g])

    def hard_map(self) -> np.ndarray:
        """Disparity 1 where the pixel's centre is in the disc, else 0."""
        yy, xx = np.mgrid[0 : self.n, 0 : self.n].astype(np.float64) + 0.5
        return self.inside(xx, yy).astype(np.float64)

    def bokeh(self, k: float, focus: float, sub: int = 2, n_aperture: int = 256) -> np.ndarray:
        """The exact render at CoC radius ``k |d - focus|`` (the near plane's signed CoC ``k (1 - focus)``)."""
        g = (np.arange(sub) + 0.5) / sub - 0.5
        i = np.arange(n_aperture)
        r = np.sqrt((i + 0.5) / n_aperture)
        samples = []
        for s_i, (dy, dx) in enumerate((a, b) for a in g for b in g):
            th = i * GOLDEN + s_i * 0.7  # each pixel sample turns the spiral: the estimates decorrelate
            for ux, uy in zip(r * np.cos(th), r * np.sin(th)):
                samples.append((dx, dy, ux, uy, k * (1.0 - focus), k * (0.0 - focus)))
        return self._mean(samples)
