"""Overlapping tiles for bounded-memory inference, blended back with raised-cosine weights."""

from __future__ import annotations

import math

import numpy as np

from bokehray.errors import InputError

__all__ = ["blend_tiles", "raised_cosine_ramp", "refine_boxes", "tile_grid"]

Box = tuple[int, int, int, int]  # y0, y1, x0, x1


def _starts(size: int, tile: int, overlap: int) -> list[int]:
    if size <= tile:
        return [0]
    step = tile - overlap
    n = math.ceil((size - tile) / step) + 1
    return sorted({min(i * step, size - tile) for i in range(n)})


def tile_grid(shape: tuple[int, int], tile: int, overlap: int, multiple: int = 1) -> list[tuple[Box, tuple[int, int]]]:
    """Tiles covering an ``h x w`` image: ``((y0, y1, x0, x1), (pad_h, pad_w))`` each.

    Neighbouring tiles overlap by at least ``overlap`` pixels; ``pad_h, pad_w`` bring a
    tile up to a multiple of ``multiple`` (a model's size constraint).
    """
    if tile < multiple or tile % multiple or not 0 <= overlap < tile:
        raise InputError(f"tile {tile} must be a positive multiple of {multiple} larger than the overlap {overlap}")
    h, w = shape
    out = []
    for y0 in _starts(h, tile, overlap):
        for x0 in _starts(w, tile, overlap):
            y1, x1 = min(y0 + tile, h), min(x0 + tile, w)
            out.append(((y0, y1, x0, x1), (-(y1 - y0) % multiple, -(x1 - x0) % multiple)))
    return out


def raised_cosine_ramp(n: int, overlap: int, lo_edge: bool = False, hi_edge: bool = False) -> np.ndarray:
    """Weights over ``n`` pixels: 1 inside, a raised cosine rising over ``overlap`` pixels at each end that is not
    an image edge (``lo_edge`` / ``hi_edge``)."""
    r = np.ones(n)
    k = min(overlap, n // 2)
    if k > 0:
        up = 0.5 - 0.5 * np.cos(np.pi * (np.arange(k) + 0.5) / k)
        if not lo_edge:
            r[:k] = up
        if not hi_edge:
            r[n - k:] = up[::-1]
    return r


def blend_tiles(tiles: list[np.ndarray], boxes: list[Box], shape: tuple[int, int], overlap: int) -> np.ndarray:
    """Blend ``h' x w' x c`` tile outputs into one image: weights fall off as raised cosines across overlaps."""
    h, w = shape
    acc = np.zeros((h, w, tiles[0].shape[2]))
    total = np.zeros((h, w, 1))
    for t, (y0, y1, x0, x1) in zip(tiles, boxes):
        wy = raised_cosine_ramp(y1 - y0, overlap, y0 == 0, y1 == h)
        wx = raised_cosine_ramp(x1 - x0, overlap, x0 == 0, x1 == w)
        wt = (wy[:, None] * wx[None, :])[..., None]
        acc[y0:y1, x0:x1] += wt * t
        total[y0:y1, x0:x1] += wt
    return (acc / total).astype(np.float32)


def refine_boxes(need: np.ndarray, tile: int, halo: int) -> list[tuple[tuple[int, int, int, int], list]]:
    """Boxes of tiles (``(ty0, ty1, tx0, tx1)`` on the tile grid, each with the tiles it stands for) that cover
    every tile of ``need`` once, each run with one halo around it.

    Greedy: every tile starts as its own box; the two boxes whose bounding box (with its halo) has the most less
    area than the two apart merge, until no merge saves area. The network's cost grows with the area it runs on,
    and one halo around neighbouring tiles costs less than one around each.
    """
    ys, xs = np.nonzero(need)
    boxes = np.stack([ys, ys + 1, xs, xs + 1], 1).astype(np.int64)
    members = [[(int(y), int(x))] for y, x in zip(ys, xs)]

    def area(b):
        return ((b[..., 1] - b[..., 0]) * tile + 2 * halo) * ((b[..., 3] - b[..., 2]) * tile + 2 * halo)

    while len(boxes) > 1:
        a = area(boxes)
        union = np.stack([np.minimum(boxes[:, None, 0], boxes[None, :, 0]), np.maximum(boxes[:, None, 1], boxes[None, :, 1]),
                          np.minimum(boxes[:, None, 2], boxes[None, :, 2]), np.maximum(boxes[:, None, 3], boxes[None, :, 3])],
                         -1)
        saving = a[:, None] + a[None, :] - area(union)
        np.fill_diagonal(saving, -1)
        k = int(np.argmax(saving))
        i, j = divmod(k, len(boxes))
        if saving[i, j] <= 0:
            break
        boxes[i] = union[i, j]
        members[i] += members[j]
        boxes = np.delete(boxes, j, 0)
        del members[j]
    return [(tuple(int(v) for v in b), sorted(m)) for b, m in zip(boxes, members)]
