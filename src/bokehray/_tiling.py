"""Memory budget and tiled rendering: bounded peak memory at any image size (docs/robustness.md).

Both quality levels plan their depth layers on the whole image (cheap: a few
bytes per pixel), then either render every layer on its bounding box (the
normal path) or, when that would not fit the memory budget or a tile size is
forced, render square *tiles* independently and stitch their cores.

A tile is exact, not an approximation: every decision that couples distant
pixels is taken once for the whole image (the tiles to copy, the layer edges,
each layer's radius bound, fill reach and pyramid depths), and each tile is
rendered on a *window* around it that holds everything its pixels depend on:

- the scatter reach of the layer: its largest radius plus two cells of its
  coarsest radius-pyramid level;
- the pull-push fill: a pixel's filled value depends on the pyramid cells up to
  ``3 * 2^n`` px away (``n`` pull levels; each push reads the coarser level's
  neighbours), and the window's cut cells reach ``2^n`` px in; the fill's
  distance gate (``sqrt(2) r + 1``) lies inside that;
- alignment: a layer's pyramids (scatter levels and pull-push) are anchored at
  its bounding box corner, so a tile's box of that layer starts a multiple of
  ``2^levels`` px after it; then every coarse cell inside the window sums the
  same pixels as in the untiled render.

The stitched image therefore equals the untiled render up to float32
rounding (row prefix sums start at another column; tested in
tests/test_stress_tiling.py). The price is the halo: at a largest CoC of 64 px
and filled layers it is about 1100 px, so tiles pay off only on large images.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import numpy as np

from ._memory import available_bytes
from ._scatter import PreviewOptions, RenderStats, _Layer, _levels_for, _pull_levels, _render_region
from .errors import ResourceError
from .lens import Aperture

__all__ = ["available_bytes", "budget_bytes", "preview_tile_size", "raytrace_tile_size"]

MB = 1 << 20

# Bytes per pixel, from the arrays each stage allocates (float32 = 4 bytes); checked against
# measured peaks by benchmarks/bench_memory.py (docs/robustness.md).
# Whole-image arrays of a preview render, kept or transient: signed CoC and radius, tile masks,
# the layer plan's sort keys (int64 search result), slice ids, output.
PREVIEW_WHOLE_IMAGE_B = 48
# Per pixel of the rendered region: image, CoC, slice ids on the device, accumulator, result.
PREVIEW_REGION_B = 60
# Per pixel of a layer's box in flight: sources (16 + 4), pull-push pyramid (24 x 4/3),
# distance map (4), radius-pyramid difference buffers (16 x 4/3 and 2 spare columns).
PREVIEW_LAYER_B = 80
# Ray tracer, per pixel of the traced region and per layer: the packed texture (16 + 4) on the
# host and its device copy.
RAYTRACE_LAYER_B = 40
# Ray tracer, per pixel of the traced region: image, CoC, slice ids on the device, a layer's
# sources and fill pyramid while it is built, ray counts, result and normalised result.
RAYTRACE_REGION_B = 150
RAYTRACE_WHOLE_IMAGE_B = 48
TILE_CANDIDATES = (8192, 4096, 3072, 2048, 1536, 1024, 768, 512, 384, 256, 128, 64)


def budget_bytes(options: PreviewOptions) -> int:
    """The memory one render may use: ``options.memory_limit_mb``, else 80 % of what is available now."""
    if options.memory_limit_mb is not None:
        return int(options.memory_limit_mb * MB)
    return int(0.8 * available_bytes())


def _refuse(what: str, need: float, budget: float, hint: str) -> ResourceError:
    return ResourceError(f"{what}: needs about {need / MB:,.0f} MB, but the memory budget is {budget / MB:,.0f} MB "
                         f"({hint})")


# --------------------------------------------------------------------------- halos and windows


def _layer_halo(lyr: _Layer, options: PreviewOptions) -> tuple[int, int]:
    """(halo, alignment) of one layer: how far a tile's pixel depends on the layer, and its pyramids' cell."""
    n_lv = _levels_for(lyr.max_radius, options.level_radius_px)
    coarse = 1 << n_lv
    halo = int(math.ceil(lyr.max_radius)) + 2 + 2 * coarse
    align = 1 << (n_lv - 1)
    if lyr.fill_reach >= 0.5:
        n_pp = _pull_levels(lyr.fill_reach)
        halo += 4 * (1 << n_pp) + 4
        align = max(align, 1 << n_pp)
    return halo, align


def _span(g0: int, g1: int, c0: int, c1: int, halo: int, align: int) -> tuple[int, int]:
    """A layer's extent [g0, g1) cut to a tile's core [c0, c1) plus ``halo``, its start aligned to g0 + k align."""
    lo = g0 + max(0, c0 - halo - g0) // align * align
    return lo, min(g1, c1 + halo)


def _tile_layers(layers: list[_Layer], core: tuple[int, int, int, int], options: PreviewOptions
                 ) -> tuple[tuple[int, int, int, int], list[_Layer]]:
    """The window a tile needs and its layers (boxes relative to the window); layers that cannot reach the core drop out."""
    cy0, cy1, cx0, cx1 = core
    boxes = []
    for lyr in layers:
        gy0, gy1, gx0, gx1 = lyr.bbox
        if gy1 <= cy0 or gy0 >= cy1 or gx1 <= cx0 or gx0 >= cx1:
            continue  # a layer's box holds all its light: nothing of it lands in this core
        halo, align = _layer_halo(lyr, options)
        boxes.append((lyr, (*_span(gy0, gy1, cy0, cy1, halo, align), *_span(gx0, gx1, cx0, cx1, halo, align))))
    wy0 = min([cy0] + [b[0] for _, b in boxes])
    wy1 = max([cy1] + [b[1] for _, b in boxes])
    wx0 = min([cx0] + [b[2] for _, b in boxes])
    wx1 = max([cx1] + [b[3] for _, b in boxes])
    local = [dataclasses.replace(lyr, bbox=(y0 - wy0, y1 - wy0, x0 - wx0, x1 - wx0)) for lyr, (y0, y1, x0, x1) in boxes]
    return (wy0, wy1, wx0, wx1), local


def _cores(h: int, w: int, tile: int) -> list[tuple[int, int, int, int]]:
    return [(y, min(h, y + tile), x, min(w, x + tile)) for y in range(0, h, tile) for x in range(0, w, tile)]


def _area(box: tuple[int, int, int, int]) -> int:
    return (box[1] - box[0]) * (box[3] - box[2])


# --------------------------------------------------------------------------- preview


def _preview_region_bytes(window_px: int, layer_areas: list[int], threads: int) -> int:
    in_flight = sorted(layer_areas, reverse=True)[: threads + 1]
    return PREVIEW_REGION_B * window_px + PREVIEW_LAYER_B * sum(in_flight)


def check_whole_image(h: int, w: int, per_px: int, options: PreviewOptions) -> None:
    """Refuse early (before the plan allocates anything) when the whole-image arrays alone cannot fit."""
    need, budget = per_px * h * w, budget_bytes(options)
    if need > budget:
        raise _refuse(f"render of {w} x {h} px", need, budget,
                      "the whole-image arrays alone do not fit, tiles or not; render a smaller image or free memory")


def preview_tile_size(h: int, w: int, layers: list[_Layer], options: PreviewOptions, threads: int,
                      stats: RenderStats) -> int | None:
    """Tile side for a preview render, or None to render untiled. Raises ResourceError if nothing fits."""
    budget = budget_bytes(options)
    whole = PREVIEW_WHOLE_IMAGE_B * h * w
    untiled = whole + _preview_region_bytes(h * w, [_area(lyr.bbox) for lyr in layers], threads)
    if options.tile_size is None and untiled <= budget:
        stats.memory_estimate_mb = untiled / MB
        return None
    reach = max(sum(_layer_halo(lyr, options)) for lyr in layers)  # halo plus alignment slack
    for tile in ([options.tile_size] if options.tile_size is not None else TILE_CANDIDATES):
        window = min(h, tile + 2 * reach) * min(w, tile + 2 * reach)  # the largest window of this tile size
        need = whole + _preview_region_bytes(window, [min(_area(lyr.bbox), window) for lyr in layers], threads)
        if need <= budget:
            stats.memory_estimate_mb = need / MB
            return tile
        if options.tile_size is not None:
            raise _refuse(f"preview render in {tile} px tiles", need, budget,
                          "choose a smaller tile_size or leave it to the automatic choice")
    raise _refuse(f"preview render of {w} x {h} px at a largest CoC of {stats.max_coc_px:.0f} px", untiled,
                  budget, f"even {TILE_CANDIDATES[-1]} px tiles do not fit; lower the blur or the image size")


def render_preview_tiles(
    image: np.ndarray,
    signed_coc: np.ndarray,
    sid: np.ndarray,
    layers: list[_Layer],
    aperture: Aperture,
    options: PreviewOptions,
    device: str,
    threads: int,
    tile: int,
    progress: Callable[[int, int], None] | None,
    stats: RenderStats,
    frame: tuple[int, int, int, int] | None = None,
) -> tuple[np.ndarray, int]:
    """Render the preview tile by tile; each tile on its window (halo included), its core copied out.

    ``frame`` (y0, y1, x0, x1): only this part of the arrays is wanted (the rest is the clamped
    border around the frame, ``_scatter.border_pad``); the tiles cover it, the rest keeps the input.
    """
    h, w = signed_coc.shape
    out = image.copy()  # pixels no layer reaches (copied tiles) keep the input, as finalize does
    fy0, fy1, fx0, fx1 = frame if frame is not None else (0, h, 0, w)
    cores = [(y0 + fy0, y1 + fy0, x0 + fx0, x1 + fx0) for y0, y1, x0, x1 in _cores(fy1 - fy0, fx1 - fx0, tile)]
    stats.image_tiles = len(cores)
    plans = [(core, *_tile_layers(layers, core, options)) for core in cores]
    total = sum(len(lyrs) for _, _, lyrs in plans)
    done, n_filled = 0, 0

    def report(i: int, _n: int) -> None:
        if progress is not None:
            progress(done + i, total)

    for (cy0, cy1, cx0, cx1), (wy0, wy1, wx0, wx1), local in plans:
        if not local:
            continue
        part, filled = _render_region(image[wy0:wy1, wx0:wx1], signed_coc[wy0:wy1, wx0:wx1],
                                      sid[wy0:wy1, wx0:wx1], local, aperture, options, device, threads, report)
        out[cy0:cy1, cx0:cx1] = part[cy0 - wy0 : cy1 - wy0, cx0 - wx0 : cx1 - wx0]
        done += len(local)
        n_filled += filled
    return out, n_filled


# --------------------------------------------------------------------------- ray tracer


def raytrace_halo(layers: list[_Layer], max_coc: float) -> tuple[int, int]:
    """(halo, alignment) for photo-mode ray tracing: every layer is filled on the whole image (box at 0, 0)."""
    halo, align = int(math.ceil(max_coc)) + 4, 1
    for lyr in layers:
        if lyr.fill_reach >= 0.5:
            n_pp = _pull_levels(lyr.fill_reach)
            halo = max(halo, int(math.ceil(max_coc)) + 4 + 4 * (1 << n_pp) + 4)
            align = max(align, 1 << n_pp)
    return halo, max(align, 16)  # 16: the visible-CoC tile grid of the ray counts


def raytrace_window(h: int, w: int, core: tuple[int, int, int, int], halo: int, align: int
                    ) -> tuple[int, int, int, int]:
    cy0, cy1, cx0, cx1 = core
    return (*_span(0, h, cy0, cy1, halo, align), *_span(0, w, cx0, cx1, halo, align))


def raytrace_tile_size(h: int, w: int, layers: list[_Layer], max_coc: float, options: PreviewOptions
                       ) -> tuple[int | None, float]:
    """(tile side or None to trace untiled, estimated bytes) for a photo-mode ray trace.

    Raises ResourceError if nothing fits.
    """
    budget = budget_bytes(options)
    n = len(layers)
    whole = RAYTRACE_WHOLE_IMAGE_B * h * w
    untiled = whole + (RAYTRACE_REGION_B + RAYTRACE_LAYER_B * n) * h * w
    if options.tile_size is None and untiled <= budget:
        return None, untiled
    halo, align = raytrace_halo(layers, max_coc)
    for tile in ([options.tile_size] if options.tile_size is not None else TILE_CANDIDATES):
        side_y, side_x = min(h, tile + 2 * halo + align), min(w, tile + 2 * halo + align)
        need = whole + (RAYTRACE_REGION_B + RAYTRACE_LAYER_B * n) * side_y * side_x
        if need <= budget:
            return tile, need
        if options.tile_size is not None:
            raise _refuse(f"ray traced render in {tile} px tiles", need, budget,
                          "choose a smaller tile_size or leave it to the automatic choice")
    raise _refuse(f"ray traced render of {w} x {h} px with {n} layers", untiled, budget,
                  f"even {TILE_CANDIDATES[-1]} px tiles do not fit; lower the blur or the image size")


def cores(h: int, w: int, tile: int) -> list[tuple[int, int, int, int]]:
    """Tile cores (y0, y1, x0, x1) covering an ``h x w`` image."""
    return _cores(h, w, tile)
