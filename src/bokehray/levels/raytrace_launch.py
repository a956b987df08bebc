"""Launching the layered ray tracer: summed-area tables, cells per pixel, and row bands.

Used by ``bokehray.levels.raytrace`` (layer stacks and photo mode). The trace runs in
bands of rows (on the CPU two or more bands at a time, one per thread: Warp's
CPU launches release the GIL), so a progress callback is called between bands
and Ctrl-C (KeyboardInterrupt) is honoured within one band's time, about
0.05 s of work; no partial result is returned.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait

import bokehray_kernels as bk
import numpy as np
import warp as wp

from ..lens import Aperture
from .quadrature import OUTLINE, CellTable, cell_table, strips_for_radius

__all__ = ["BAND_CELL_LAYERS", "choose_levels", "strip_cap", "summed_area", "tables", "trace_bands"]

BAND_CELL_LAYERS = 400_000
"""Work per band (cell rays x layers, a map layer counted 4 times): about 0.05 s on one CPU core."""


def summed_area(rgba: np.ndarray) -> np.ndarray:
    """``(n, H, W, 4)`` textures -> ``(n, H + 1, W + 1, 4)`` float64 tables, ``S[l, j, i] = sum(rgba[l, :j, :i])``."""
    n, h, w, c = rgba.shape
    sat = np.zeros((n, h + 1, w + 1, c), np.float64)
    for i in range(n):  # layer by layer: short steps (Ctrl-C is seen between them)
        np.cumsum(rgba[i], axis=0, dtype=np.float64, out=sat[i, 1:, 1:])
        np.cumsum(sat[i, 1:, 1:], axis=1, out=sat[i, 1:, 1:])
    return sat


def choose_levels(r_px: np.ndarray, aperture: Aperture, samples_per_px2: float, strip_range: tuple[int, int],
                  max_cells: int | None = None) -> tuple[np.ndarray, CellTable, np.ndarray]:
    """Per pixel, the index of its cell partition; the table; and the strips per pixel.

    A pixel whose visible CoC ``r`` is below half a pixel takes the centre ray (level 0)
    unless ``strip_range[0] > 0``. Otherwise it takes ``ceil(2 r sqrt(samples_per_px2))``
    strips (within ``strip_range``) and an outline resolved to ``max(OUTLINE, 0.25 px / r)``,
    with ``r`` rounded up to a half octave; the choice depends on the pixel alone (a tiled
    render traces the same cells). Where that partition has more than ``max_cells`` cells,
    ``_fit`` trades strips and outline down to the cap.
    """
    g_min, g_max = strip_range
    r = np.asarray(r_px, np.float64)
    g = np.clip(strips_for_radius(r, samples_per_px2), max(g_min, 1), g_max)
    g = np.where(r < 0.5, g_min, g)
    b = np.ceil(2.0 * np.log2(np.maximum(r, 0.5))).astype(np.int64)
    key = np.where(g > 0, g * 64 + (b + 2), 0)
    levels = np.zeros(r.shape, np.int32)
    parts = []
    for i, kv in enumerate(int(v) for v in np.unique(key) if v > 0):
        gv, bv = divmod(kv, 64)
        outline = max(OUTLINE, 0.25 / 2.0 ** ((bv - 2) / 2.0))
        parts.append(_fit(aperture, gv, outline, max_cells))
        levels[key == kv] = i + 1
    table = tables(aperture, tuple(parts))
    return levels, table, g


def _count(aperture: Aperture, g: int, outline: float) -> int:
    return int(tables(aperture, ((g, outline),)).count(1))


def _fit(aperture: Aperture, g: int, outline: float, max_cells: int | None) -> tuple[int, float]:
    """(strips, outline) with at most ``max_cells`` cells: first fewer strips (down to 4), then a coarser
    outline (to 0.1), then fewer strips (to 2), a coarser outline (to 0.5), and at last one cell.
    The outline goes first because it is the shape of every bokeh ball; the strips only refine
    occlusion between layers."""
    if max_cells is None:
        return g, outline
    while _count(aperture, g, outline) > max_cells:
        if g > 4:
            g -= 1
        elif outline < 0.1:
            outline = min(0.1, outline * 1.25)
        elif g > 2:
            g -= 1
        elif outline < 0.5:
            outline = min(0.5, outline * 1.25)
        else:
            return 1, outline
    return g, outline


_TABLE_CACHE: dict = {}


def tables(aperture: Aperture, parts: tuple[tuple[int, float], ...]) -> CellTable:
    """Cell tables for ``(strips, outline)`` pairs, cached per aperture (outline rounded up to 1/16 octave)."""
    key_parts = tuple((g, 2.0 ** (math.ceil(16 * math.log2(ol)) / 16)) for g, ol in parts)
    key = (aperture, key_parts)
    if key not in _TABLE_CACHE:
        if len(_TABLE_CACHE) > 64:
            _TABLE_CACHE.clear()
        tables = [cell_table(aperture, [g], outline=ol) for g, ol in key_parts]
        boxes = [np.zeros((1, 4), np.float32)] + [t.boxes[1:] for t in tables]
        weights = [np.ones(1, np.float32)] + [t.weights[1:] for t in tables]
        offsets = np.cumsum([0] + [len(b) for b in boxes]).astype(np.int32)
        _TABLE_CACHE[key] = CellTable(strips=(0, *[g for g, _ in key_parts]), boxes=np.concatenate(boxes),
                                      weights=np.concatenate(weights), offsets=offsets, parts=key_parts)
    return _TABLE_CACHE[key]


def strip_cap(max_cells: int) -> int:
    """The most strips whose full cells, about ``(pi / 4) g^2``, number at most ``max_cells`` (>= 1)."""
    return max(1, int(math.floor(math.sqrt(4.0 * max_cells / math.pi) + 1e-9)))


def strip_range(options) -> tuple[int, int]:
    """(fewest, most) strips across the aperture for :class:`~bokehray.RaytraceOptions` (0 fewest: in-focus pixels
    take the centre ray)."""
    g_max = strip_cap(options.max_spp)
    g_min = 0 if options.min_spp <= 1 else min(g_max, int(math.ceil(math.sqrt(4.0 * options.min_spp / math.pi) - 1e-9)))
    return g_min, g_max


def trace_bands(  # noqa: C901
    sat: np.ndarray,
    disp: np.ndarray,
    planes: np.ndarray,
    ranges: np.ndarray,
    k_px: float,
    d_f: float,
    table: CellTable,
    levels: np.ndarray,
    core_origin: tuple[int, int],
    device: str,
    *,
    progress: Callable[[int, int], None] | None = None,
    threads: int | None = None,
) -> np.ndarray:
    """Trace ``levels.shape`` output pixels in bands of rows; returns ``(h, w, 4)`` float32.

    ``core_origin`` = (y, x) of output pixel (0, 0) inside the textures.
    """
    n = disp.shape[0]
    h, w = levels.shape
    dev = wp.get_device(device)
    args = [
        # on the CPU the kernel reads the host arrays in place (no second copy of the tables)
        wp.array(sat, dtype=wp.vec4d, device=device, copy=not dev.is_cpu),
        wp.array(np.ascontiguousarray(disp, np.float32), dtype=float, device=device, copy=not dev.is_cpu),
        wp.array(np.ascontiguousarray(planes, np.float32), dtype=wp.vec4, device=device),
        wp.array(np.ascontiguousarray(ranges, np.float32), dtype=wp.vec2, device=device),
        int(n),
        float(k_px),
        float(d_f),
        wp.array(table.boxes, dtype=wp.vec4, device=device),
        wp.array(table.weights, dtype=float, device=device),
        wp.array(table.offsets, dtype=wp.int32, device=device),
        wp.array(np.ascontiguousarray(levels, np.int32), dtype=wp.int32, device=device),
    ]
    out = wp.zeros((h, w), dtype=wp.vec4, device=device)
    # bands of about BAND_CELL_LAYERS work each (cells x layers per row)
    # a map layer's march costs about 4 plane hits
    row_work = table.count(levels).sum(axis=1).astype(np.float64) * float(np.where(planes[:, 3] != 0, 1, 4).sum())
    budget = BAND_CELL_LAYERS * (8 if dev.is_cuda else 1)
    bands, y0, acc = [], 0, 0.0
    for y in range(h):
        acc += row_work[y]
        if acc >= budget or y == h - 1:
            bands.append((y0, y + 1))
            y0, acc = y + 1, 0.0
    total = int(row_work.sum())

    def run(band: tuple[int, int]) -> int:
        b0, b1 = band
        wp.launch(bk.raytrace_kernel, dim=(b1 - b0, w),
                  inputs=[*args, int(b0), int(core_origin[1]), int(core_origin[0])], outputs=[out], device=device)
        if dev.is_cuda:
            wp.synchronize_device(device)
        return int(row_work[b0:b1].sum())

    done = 0
    if dev.is_cuda:
        for band in bands:
            done += run(band)
            if progress is not None:
                progress(done, total)
    else:
        workers = max(1, min(threads or os.cpu_count() or 1, len(bands)))
        pool = ThreadPoolExecutor(max_workers=workers)
        try:
            queue = list(reversed(bands))
            running = set()
            while queue or running:
                while queue and len(running) < workers:
                    running.add(pool.submit(run, queue.pop()))
                finished, running = wait(running, timeout=0.05, return_when=FIRST_COMPLETED)
                for f in finished:
                    done += f.result()
                    if progress is not None:
                        progress(done, total)
        except BaseException:
            queue.clear()
            for f in running:
                f.cancel()
            raise
        finally:
            pool.shutdown(wait=True)
    return out.numpy()

