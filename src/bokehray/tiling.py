"""Memory budget and tiled rendering: a generic driver, bounded peak memory at any image size.

A quality level plans its layered scene on the whole image (cheap: a few bytes per pixel), then either renders
every layer on its bounding box (the normal path) or, when that would not fit the memory budget or a tile size
is forced, renders square *tiles* independently and stitches their cores. This module knows nothing of any
renderer: a caller gives

- the image size and the bytes its render needs untiled and on a window of a given size (:func:`choose_tile`),
- the reach of a pixel on its inputs (halo) and the cell its pyramids are anchored to (alignment), from which
  :func:`window` cuts each tile's window,
- a function that renders one tile's window and returns the tile's core (:func:`render_tiles`).

A tile is exact when everything that couples distant pixels is decided once for the whole image (the levels do
this: ``bokehray.scene`` plans the layers, their radius bounds, fill reach and pyramid depths once) and the
window holds everything the core depends on; a pyramid anchored at a box corner must also start a whole number of
cells after it (:func:`span`), so every coarse cell inside the window sums the same pixels as untiled.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ._memory import available_bytes
from .errors import ResourceError
from .options import MemoryOptions

__all__ = ["MB", "TILE_CANDIDATES", "Box", "available_bytes", "budget_bytes", "check_whole_image", "choose_tile",
           "cores", "render_tiles", "span", "window"]

MB = 1 << 20
TILE_CANDIDATES = (8192, 4096, 3072, 2048, 1536, 1024, 768, 512, 384, 256, 128, 64)

Box = tuple[int, int, int, int]
"""(y0, y1, x0, x1), half-open."""


def budget_bytes(memory: MemoryOptions) -> int:
    """The memory one render may use: ``memory.memory_limit_mb``, else 80 % of what is available now."""
    if memory.memory_limit_mb is not None:
        return int(memory.memory_limit_mb * MB)
    return int(0.8 * available_bytes())


def _refuse(what: str, need: float, budget: float, hint: str) -> ResourceError:
    return ResourceError(f"{what}: needs about {need / MB:,.0f} MB, but the memory budget is {budget / MB:,.0f} MB "
                         f"({hint})")


def check_whole_image(h: int, w: int, per_px: int, memory: MemoryOptions) -> None:
    """Refuse early (before anything large is allocated) when the whole-image arrays alone cannot fit."""
    need, budget = per_px * h * w, budget_bytes(memory)
    if need > budget:
        raise _refuse(f"render of {w} x {h} px", need, budget,
                      "the whole-image arrays alone do not fit, tiles or not; render a smaller image or free memory")


def choose_tile(h: int, w: int, memory: MemoryOptions, *, untiled_bytes: int, margin: int,
                window_bytes: Callable[[int, int], int], what: str,
                frame: tuple[int, int] | None = None) -> tuple[int | None, int]:
    """(tile side, or None to render untiled; estimated peak bytes) under the memory budget.

    ``margin``: how much larger than its tile a window can be, in all (both halos and the alignment slack);
    ``window_bytes(hy, wx)``: the peak of a render on a window of that size; ``frame``: the image's own ``(h, w)``
    where ``h x w`` is it padded by the blur's reach beyond its borders (a refusal names both). Raises ResourceError
    if nothing fits.
    """
    budget = budget_bytes(memory)
    if memory.tile_size is None and untiled_bytes <= budget:
        return None, untiled_bytes
    for tile in ([memory.tile_size] if memory.tile_size is not None else TILE_CANDIDATES):
        need = window_bytes(min(h, tile + margin), min(w, tile + margin))
        if need <= budget:
            return tile, need
        if memory.tile_size is not None:
            raise _refuse(f"{what} in {tile} px tiles", need, budget,
                          "choose a smaller tile_size or leave it to the automatic choice")
    size = f"{w} x {h} px" if frame is None or frame == (h, w) else \
        f"the {frame[1]} x {frame[0]} px image ({w} x {h} px with the blur's reach beyond its borders)"
    raise _refuse(f"{what} of {size}", untiled_bytes, budget,
                  f"even {TILE_CANDIDATES[-1]} px tiles do not fit; lower the blur or the image size")


def cores(h: int, w: int, tile: int) -> list[Box]:
    """Tile cores covering an ``h x w`` image, row by row."""
    return [(y, min(h, y + tile), x, min(w, x + tile)) for y in range(0, h, tile) for x in range(0, w, tile)]


def span(g0: int, g1: int, c0: int, c1: int, halo: int, align: int) -> tuple[int, int]:
    """An extent [g0, g1) cut to a core's [c0, c1) plus ``halo``, its start aligned to ``g0 + k align``."""
    lo = g0 + max(0, c0 - halo - g0) // align * align
    return lo, min(g1, c1 + halo)


def window(extent: Box, core: Box, halo: int, align: int) -> Box:
    """The part of ``extent`` a core depends on: the core plus ``halo``, aligned to ``extent``'s corner."""
    gy0, gy1, gx0, gx1 = extent
    cy0, cy1, cx0, cx1 = core
    return (*span(gy0, gy1, cy0, cy1, halo, align), *span(gx0, gx1, cx0, cx1, halo, align))


def render_tiles(out: np.ndarray, tile: int, render_core: Callable[[Box], np.ndarray | None],
                 region: Box | None = None) -> int:
    """Fill ``out`` (H x W x C) tile by tile: ``render_core(core)`` returns the core's pixels, or None to keep what
    ``out`` holds there. The tiles cover ``region`` (default: all of ``out``). Returns the number of tiles."""
    y0, y1, x0, x1 = (0, out.shape[0], 0, out.shape[1]) if region is None else region
    all_cores = [(a + y0, b + y0, c + x0, d + x0) for a, b, c, d in cores(y1 - y0, x1 - x0, tile)]
    for core in all_cores:
        part = render_core(core)
        if part is not None:
            cy0, cy1, cx0, cx1 = core
            out[cy0:cy1, cx0:cx1] = part
    return len(all_cores)
