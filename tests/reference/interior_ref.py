"""Float64 oracle of ``bokehray_kernels.interior``: the pixels whose cone meets no farther surface."""

from __future__ import annotations

import numpy as np


def opaque_pixels(ids: np.ndarray, split: np.ndarray, coc: np.ndarray, jump: float = 1.0) -> np.ndarray:
    """True where every pixel within city-block distance ``sqrt(2) (|coc| + 1)`` (the disc of radius ``|coc| + 1``
    inside it) is no boundary pixel, by brute force: a boundary pixel is copied (``ids < 0``), split, or has a
    4-neighbour whose signed CoC is lower (farther) by more than ``jump`` (the frame's outside being none)."""
    ids = np.asarray(ids)
    c = np.asarray(coc, np.float64)
    h, w = ids.shape
    edge = (ids < 0) | np.asarray(split, bool)
    edge[:, 1:] |= c[:, :-1] < c[:, 1:] - jump
    edge[:, :-1] |= c[:, 1:] < c[:, :-1] - jump
    edge[1:] |= c[:-1] < c[1:] - jump
    edge[:-1] |= c[1:] < c[:-1] - jump
    dist = np.full((h, w), np.inf)
    yy, xx = np.mgrid[0:h, 0:w]
    for y, x in zip(*np.nonzero(edge)):
        np.minimum(dist, np.abs(yy - y) + np.abs(xx - x), out=dist)
    return dist > np.sqrt(2.0) * (np.abs(c) + 1.0)
