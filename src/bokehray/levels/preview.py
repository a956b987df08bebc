"""The preview level: layered, occlusion-aware row-span scatter (docs/renderer.md).

Pipeline (all heavy work in ``bokehray_kernels``):

0. The frame is extended by its edge pixels (colour and signed CoC) as far as its border's CoC reaches
   (:func:`border_pad`: the clamped border), rendered, and cropped.
1. Tiles whose pixels, and every pixel within CoC reach of them, have ``|s| < 0.5`` are *copied*: never
   scattered, never composited (``bokehray.scene.copy_tiles``).
2. The rest is the layered scene (``bokehray.scene.split_scene``): layers by ``s``, ids growing towards the
   camera, each with its box, radius bound and fill reach; mixed pixels at depth edges split into a near part
   (a source of the near layer) and a far part (the pixel) when the render was given soft edges.
3. Each layer, independently (one worker thread per CPU core): its sources (its own pixels and the fill of what
   nearer layers hide, ``bokehray.scene.build_layer_sources``) are scattered with their own exact radius on
   the radius pyramid, the excess light of the salient ones (:func:`route_salient`) at full resolution.
4. Layers are composited back to front with "over" (opacity = scattered coverage clipped to 1, colour
   normalised by coverage), and the result is divided by the total opacity.

Large renders go tile by tile through ``bokehray.tiling`` with exact halos (``bokehray.scene.scatter_halo``).
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import itertools
import math
import os
import threading
import time
from concurrent.futures import FIRST_COMPLETED, Future, ThreadPoolExecutor, wait
from dataclasses import dataclass

import bokehray_kernels as bk
import numpy as np
import warp as wp

from .. import scene as sc
from .. import tiling
from .._memory import bound_heap
from ..edge_estimate import MattingRule, on_threads
from ..errors import ResourceError
from ..lens import Aperture, aperture_area
from ..options import PreviewOptions
from ..stats import PreviewStats
from .base import Progress, RenderContext
from .buffers import is_lazy, lazy_for, lazy_zeros, release_cached, reuse_buffers

__all__ = ["aperture_shape", "border_pad", "no_routing", "prefix_rows", "pyramid_buffers", "render_preview",
           "render_signed_coc", "route_salient", "scatter_merged"]

# Bytes per pixel, from the arrays each stage allocates (float32 = 4 bytes), calibrated on measured peaks (the
# growth of the process during renders of 1.5 to 24 MP, within 15 %: docs/renderer.md, "The memory model");
# benchmarks/photo/bench_memory.py prints the estimate beside the peak (docs/robustness.md).
WHOLE_IMAGE_B = 24
"""Whole-image arrays kept through the layers: the scene's colour (its split pixels hold their far part, 12), its
signed CoC (4), layer ids (4), tile masks; the plan's transients (sort keys) are gone by then, and so are the
context's pixels when it is disposable (``RenderContext.release_pixels``). 32 while the context's signed CoC stayed
(recalibrated on the measured peaks: docs/renderer.md, "the command line's arrays handed over")."""
KEPT_CONTEXT_B = 4
"""The context's signed CoC, kept through the layers when the context is not disposable (an RGBA input's alpha or
the refiner reads it after the level)."""
REGION_B = 17
"""Per pixel of the rendered region: the accumulator (16; the image, CoC and layer ids are read in place on the CPU;
the accumulator's pages are taken from the first composite on, ``buffers.lazy_zeros``, so a lazily zeroed one
counts from the back layer's composite on, ``ACC_B``) and the map of the pixels their own layer covers whole (1, :func:`opaque_pixels`; its float distances, 4, are gone
before the first layer)."""
ACC_B = 16
"""Of ``REGION_B``, the accumulator's (vec4): a lazily zeroed one takes its pages from the first composite on (the back
layer's), so it is counted beside the layers from then on (:func:`_region_bytes`)."""
LIT_B = 30
"""Per pixel of a layer's lit area (its box's pixels in its support's tiles, :func:`_lit_area`) while it is in work
on the CPU: its sources (16) and signed CoC (4), lazily zeroed, take pages where its sources and then its result
lie, and the routing's planes and flags where the support is; calibrated on measured peaks (6 to 24 MP, two
workers: docs/renderer.md, "pages only where a layer's light lies"). The pull-push fill's buffers and the coarse
pyramid levels span the box but are a few bytes a box pixel and do not coincide with the peak (one fill at a time)."""
LEVEL0_B = 16
"""More per lit pixel for a layer whose first pyramid level is 0: its level-0 difference plane (a layer starting
on a coarser level holds only routed light there, within ``LIT_B``)."""
DENSE_LAYER_B = 48
"""Per pixel of a layer's box in work on a GPU, where every array is dense (``buffers.lazy_zeros`` allocates
whole): sources (16 + 4), the radius pyramid's difference buffers (16 x 4/3) and the routing's arrays (as the CPU
model was calibrated before its pages followed the support; not measured on a GPU)."""
SMALL_BOX_B = 58
"""Per pixel of the box of a layer whose arrays are zeroed at once on the CPU (a box below ``buffers.LAZY_MIN_BYTES``
of vec4): its sources, level 0, the routing's planes and flags, dense; calibrated on measured growth at 1.5 MP
(the demo, exact, Gaussian 4 px and all-edges maps, two workers: 1.01-1.04 of the growth; 70 while the routing kept
a dense plane of its clusters' light and shape a pyramid level; docs/design/memory-model.md)."""
TILED_B = 12
"""Per pixel of the frame in a tiled render: the output the tiles' cores are copied into (``_render_tiled``); 12 more
where the frame is not padded, for the photo it keeps for the copied tiles (padded, that photo is the scene's colour,
``split_scene`` writing into it)."""
SOFT_B = 76
"""Per split pixel (``SoftEdges``, 44, and its near part in the scene, ``NearParts``, 32), through the layers."""
SPLIT_PLAN_B = 170
"""Per split pixel of the (padded) frame while its scene is planned (``scene.split_scene``): the split pixels (44)
held while their near parts (32) are made, with the split's int64 indices, layer ids and F and B kept in range.
Measured on a 20 000 x 2 strip with a 1-px checkerboard map, whose clamped border replicates its split pixels 10.8
million times: the plan peaked at 2448 MB over 690 MB of frame arrays, where the layers held 1511 MB
(docs/design/memory-model.md)."""
RESULT_B = 16
"""Per pixel of a finished layer's lit area (its box's on a GPU) waiting to be composited (premultiplied RGB and
coverage): while the next layer to composite is in work, at most ``threads - 1`` others' results wait beside the
other workers' layers (``_render_window`` starts no more once ``threads`` wait)."""
HELD_B = 20
"""Per pixel of a lazily zeroed layer's lit area, what it holds from its start to its end: its sources (16, written
over its support as it starts, then its result) and its CoC (4). Its level 0 and routing planes take their pages as
its light is deposited, at the end of its scatter: beside the largest layer at its peak, the other workers' layers
count this much (a dense box, zeroed whole as it starts, counts whole). Counted at their full rate, two workers'
layers made the estimate 1.34 of the growth on a 6 MP all-edges map (one worker: 1.03; docs/design/memory-model.md)."""

ROUTING_B = 9
"""More per lit pixel a routed layer (exact highlights, pyramid levels above 0) holds from its routing to the end of
its scatter, beside another layer's peak: the routing's flags (1) and its cells' neighbourhood sums and pixel counts
(20 B a level-``l`` cell, 7-8 B a pixel in 4 KB pages; ``route_salient``). On a 20 000 x 2 noise strip, a light or
a cluster in nearly every cell, two routed full-frame layers were at their peak at once (docs/design/memory-model.md)."""

Footprint = tuple[int, int, int]
"""(pixels a layer's arrays take pages on, bytes per such pixel at its peak, bytes per such pixel it holds while in
work beside another layer's peak)."""


def _plan_bytes(frame_px: int, n_split: int) -> int:
    """The peak while the scene of a frame of ``frame_px`` pixels with ``n_split`` split pixels is planned."""
    return WHOLE_IMAGE_B * frame_px + SPLIT_PLAN_B * n_split


def _least_bytes(frame_px: int, n_split: int) -> int:
    """The least any render of such a frame holds, tiles or not: its plan, and its layers' whole-image arrays with
    a tiled render's output."""
    return max(_plan_bytes(frame_px, n_split), (WHOLE_IMAGE_B + TILED_B) * frame_px + SOFT_B * n_split)


def _clamped_border(s: np.ndarray, soft: sc.SoftEdges | None, grid: int, clamp: bool,
                    memory) -> tuple[int, int, int, int]:
    """The clamped border's pads (:func:`border_pad`: a split pixel's near part reaches as far as its CoC), or none
    where the least any render of the padded frame holds (its split pixels' replicas counted before they are made)
    does not fit the budget. Raises ResourceError where the frame's own split pixels cannot be planned within it
    (before anything is padded or split)."""
    h0, w0 = s.shape
    pads = _pads_of_rims(sc.rim_radii(s, soft), s.shape, grid) if clamp and s.size else (0, 0, 0, 0)
    n_own = 0 if soft is None else len(soft)
    budget = tiling.budget_bytes(memory)
    if any(pads):
        h, w = h0 + pads[0] + pads[1], w0 + pads[2] + pads[3]
        n_soft = n_own + (sc.soft_replicas(soft, (h0, w0), pads) if n_own else 0)
        if _least_bytes(h * w, n_soft) > budget:
            pads = (0, 0, 0, 0)  # the clamped border does not fit: the frame alone
    if n_own and _plan_bytes(h0 * w0, n_own) > budget:
        raise ResourceError(f"soft edges of the {w0} x {h0} px image: its {n_own} split pixels need about "
                            f"{_plan_bytes(h0 * w0, n_own) / tiling.MB:,.0f} MB to plan, over the memory budget of "
                            f"{budget / tiling.MB:,.0f} MB (a map that is edges everywhere; give more memory, or "
                            "LayerOptions(soft_edges=False))")
    return pads


def _layer_footprint(layer: sc.LayerRecord, level_radius_px: float, on_cpu: bool, routed: bool = True) -> Footprint:
    """A layer's :data:`Footprint`: dense arrays (a GPU's, a small box's) are taken whole as the layer starts.
    ``routed``: exact highlights on (the layer's sources above level 0 are routed, :func:`route_salient`)."""
    if not on_cpu:
        return _area(layer.bbox), DENSE_LAYER_B, DENSE_LAYER_B
    if not lazy_for(layer.bbox[1] - layer.bbox[0], layer.bbox[3] - layer.bbox[2]):  # a small box: dense arrays
        return _area(layer.bbox), SMALL_BOX_B, SMALL_BOX_B
    dense_level0 = sc.lowest_level(layer, level_radius_px) == 0
    routing = ROUTING_B if routed and sc.pyramid_levels(layer.max_radius, level_radius_px) > 1 else 0
    return _lit_area(layer), LIT_B + (LEVEL0_B if dense_level0 else 0), HELD_B + routing


@dataclass(frozen=True, slots=True)
class _Scatter:
    """What every layer's scatter reads: the aperture on the device (its blades, vertical extent and area at unit
    circumradius, the spans' normalisation) and the pyramid step."""

    shape: bk.Shape
    level_radius_px: float
    exact_highlights: bool
    merge_sources: bool
    threads: int
    device: str
    fill_gate: threading.Lock = dataclasses.field(default_factory=threading.Lock)
    """Held while a layer fills what nearer layers hide: one pull-push fill at a time (see :func:`render_layer`)."""


def aperture_shape(aperture: Aperture, blade_rows: np.ndarray, device: str) -> bk.Shape:
    """The aperture as the kernels take it: its blades (``blade_rows``: ``Aperture.blade_discs()``), their count,
    its vertical extent and its area at unit circumradius."""
    shape = bk.Shape()
    shape.blades = wp.array(blade_rows if len(blade_rows) else np.zeros((1, 4), np.float32), dtype=wp.vec4,
                            device=device)
    shape.n_blades = len(blade_rows)
    shape.extent = wp.vec2(*aperture.vertical_extent())
    shape.area = aperture_area(aperture)
    return shape


def pyramid_buffers(bufs: list[wp.array]) -> bk.Levels:
    """The radius pyramid's difference buffers (levels 0 .. MAX_LEVELS - 1) as the kernels take them."""
    levels = bk.Levels()
    levels.l0, levels.l1, levels.l2, levels.l3, levels.l4, levels.l5 = bufs
    return levels


def _region_bytes(window_px: int, layers: list[Footprint], threads: int, lazy_acc: bool = False) -> int:
    """The peak beyond the whole-image arrays of rendering a region of ``window_px`` pixels whose layers take
    ``layers`` (:func:`_layer_footprint`, back to front) on ``threads`` workers. ``lazy_acc``: the accumulator is
    lazily zeroed (a CPU window of ``buffers.LAZY_MIN_BYTES`` or more), so it takes its pages at the first composite,
    the back layer's: the larger of the layers before it (the accumulator not yet there), the back layer's result
    composited beside the accumulator and the other workers' layers, and the layers after it beside the accumulator.
    Otherwise (a dense accumulator) it is there all along."""
    if not lazy_acc or not layers:
        return REGION_B * window_px + _layers_bytes(layers, threads)
    acc, rest = ACC_B * window_px, layers[1:]
    held = sorted((p * h for p, _, h in rest), reverse=True)
    results = sorted((px for px, _, _ in rest), reverse=True)
    back_composited = RESULT_B * layers[0][0] + sum(held[: threads - 1]) + RESULT_B * sum(results[threads - 1 : 2 * threads - 2])
    return (REGION_B - ACC_B) * window_px + max(_layers_bytes(layers, threads),
                                                acc + max(back_composited, _layers_bytes(rest, threads)))


def _layers_bytes(layers: list[Footprint], threads: int) -> int:
    """Layers in work: one at its peak and each other worker's at what it holds while in work (the choice that makes
    the sum largest), and threads - 1 others finished, waiting to be composited behind a slower one (the next
    largest)."""
    work = 0
    for i, (px, rate, _) in enumerate(layers):
        held = sorted((p * h for j, (p, _, h) in enumerate(layers) if j != i), reverse=True)
        work = max(work, px * rate + sum(held[: threads - 1]))
    results = sorted((px for px, _, _ in layers), reverse=True)
    return work + RESULT_B * sum(results[threads : 2 * threads - 1])


SALIENT_VISIBLE = 0.002
"""A source's disc outline counts as visible when its plateau exceeds 0.2 % of its surroundings."""
SALIENT_FLOOR = 1e-6
"""Darkest surroundings (linear radiance) the visibility test compares with: on black every light shows."""


@dataclass(frozen=True, slots=True)
class Routing:
    """What :func:`route_salient` decided for one layer's sources (see ``bk.scatter_kernel``)."""

    exact: wp.array  # uint8 per source: 1 routed alone, 2 in its cell's cluster, 0 on the pyramid
    cell_total: wp.array  # per level-l cell: its 3 x 3 cells' sum of sources (the routed sources' local colour)
    cell_pixels: wp.array  # and how many pixels they hold

    def struct(self) -> bk.Routing:
        """The routing as the kernels take it."""
        r = bk.Routing()
        r.exact, r.cell_total, r.cell_pixels = self.exact, self.cell_total, self.cell_pixels
        return r


def no_routing(device: str) -> Routing:
    """``bk.scatter_kernel``'s routing when nothing is routed: 1-element placeholders it does not read."""
    return Routing(wp.zeros((1, 1), dtype=wp.uint8, device=device), wp.zeros((1, 1, 1), dtype=wp.vec4, device=device),
                   wp.zeros((1, 1, 1), dtype=float, device=device))


def route_salient(src: wp.array, coc: wp.array, n_levels: int, r0: float, device: str, shape: bk.Shape,
                  buf0: wp.array, support: sc.LayerSupport | None = None, first: int = 1,
                  lazy: bool = True) -> Routing:
    """Which pyramid-level sources send their excess light to level 0: alone, or as their cell's cluster.

    A source on pyramid level ``l`` gets its outline blurred by about ``2^l`` px. That is
    invisible where many similar discs overlap (smooth content), not where one source stands
    out: ``bk.route_cells_kernel`` scores each source's excess radiance over its coverage of the
    layer's local colour (the 3 x 3 level-``l`` cells of a radiance pyramid around it) against
    ``SALIENT_VISIBLE * pi r^2 * max(mean, SALIENT_FLOOR)`` and keeps, in each level-``l`` cell,
    the ``max(1, 2^(l-1))`` best-scored of them, so the level-0 work stays below half of the
    pyramid work whatever the radius (flat cost in R). In the same pass it gathers the rest of each cell's
    excess light into one source a block when together it is visible (an extended light: each of its pixels
    is too faint alone) and scatters those into ``buf0``, level 0's difference plane, with the aperture
    ``shape``: the clusters hold no memory of their own. Every decision depends only on pyramid-aligned cells of
    the layer's box, so tiled renders route the same sources. Cells outside the layer's ``support`` (None: everywhere) are skipped,
    and so are the levels below ``first``, which hold no source (``bokehray.scene.lowest_level``).
    """
    h, w = src.shape
    where = (support or sc.LayerSupport.everywhere(device)).struct()
    # the routing's arrays are mostly zero (level k writes 1 / 4^k of its plane): pages taken where written. Only the
    # flags and level 1 of the means are read where nothing wrote them (zero): the counts and the levels present are
    # written everywhere, the coarser means wherever they are read, the neighbourhoods wherever a source is routed
    exact = lazy_zeros((h, w), wp.uint8, device, lazy)
    n_means = n_levels - 1  # radiance pyramid levels 1 .. n_levels - 1
    h1, w1 = (h + 1) // 2, (w + 1) // 2
    means = _written((n_means, h1, w1), wp.vec4, device, lazy)
    if not is_lazy(means):
        means[0].zero_()
    counts = _written((n_means, h1, w1), float, device, lazy)
    present = _written((n_means, h1, w1), wp.uint8, device, lazy)
    n, span = sc.row_span(device, w1)
    wp.launch(bk.radiance_mean_kernel, dim=(h1, n), inputs=[span, src, coc, where, float(r0), n_levels],
              outputs=[means, counts, present], device=device)
    fh, fw = h1, w1
    for k in range(1, n_means):
        ch, cw = (fh + 1) // 2, (fw + 1) // 2
        wp.launch(bk.halve_mean_kernel, dim=(ch, cw), inputs=[means, counts, present, k, fh, fw], device=device)
        fh, fw = ch, cw
    cell_total = _written((n_means, h1, w1), wp.vec4, device, lazy)
    cell_pixels = _written((n_means, h1, w1), float, device, lazy)
    routing = Routing(exact, cell_total, cell_pixels)
    for lev in range(max(1, first), n_levels):
        side = 1 << lev
        salience = bk.Salience()
        salience.per_cell, salience.visible, salience.floor = max(1, side // 2), SALIENT_VISIBLE, SALIENT_FLOOR
        wp.launch(bk.route_cells_kernel, dim=((h + side - 1) // side, (w + side - 1) // side),
                  inputs=[src, coc, means, counts, present, float(r0), n_levels, lev, salience, where],
                  outputs=[routing.struct(), shape, buf0], device=device)
    return routing


def _written(shape: tuple[int, ...], dtype, device: str, lazy: bool) -> wp.array:
    """An array whose every element that is read is written first: lazily zeroed pages where ``lazy`` (taken only
    where written, as the other planes of a large box), else uninitialised (a small box's planes were cleared whole,
    0.01-0.05 CPU-s a layer, for elements nothing reads)."""
    return lazy_zeros(shape, dtype, device) if lazy else wp.empty(shape, dtype=dtype, device=device)


def border_pad(signed_coc: np.ndarray, tile_px: int) -> tuple[int, int, int, int]:
    """Widths [px] (top, bottom, left, right) of the clamped border the preview renders around the frame.

    What lies beyond the frame is unknown; the preview takes it to be the frame's edge pixels
    continued outwards (edge-replicated colour and signed CoC, as the ray tracer clamps its
    textures), so light near the border is neither invented nor dropped (docs/renderer.md).
    Only pixels within the CoC of a border pixel can scatter into the frame: each side's pad is
    the largest radius found on that side (corners included) plus one pixel, 0 when it is below
    half a pixel, rounded up to whole skip tiles (``tile_px``) so that the frame's tiles are
    tiles of the padded render.

    A border CoC beyond half the frame's longer side (blur wider than the picture) is not
    clamped: continuing a border that far would let a few edge pixels dominate the whole
    render; there the old rule holds (the render is divided by the coverage it got, i.e. the
    unknown outside is taken as the frame's own neighbourhood average).
    """
    if signed_coc.size == 0:
        return 0, 0, 0, 0
    return _pads_of_rims(sc.rim_radii(signed_coc, None), signed_coc.shape, tile_px)


def _pads_of_rims(rims: tuple[np.ndarray, ...], shape: tuple[int, int], tile_px: int) -> tuple[int, int, int, int]:
    """:func:`border_pad` of the frame of ``shape`` whose rims' radii (top, bottom, left, right: ``scene.rim_radii``)
    are ``rims``."""
    limit = 0.5 * max(shape)
    radii = [float(rim.max()) for rim in rims]
    if max(radii) > limit:
        return 0, 0, 0, 0
    return tuple(-(-(int(math.ceil(r)) + 1) // tile_px) * tile_px if r >= 0.5 else 0 for r in radii)


def _border_reach(signed_coc: np.ndarray, soft: sc.SoftEdges | None) -> float:
    """The largest CoC radius [px] on the frame's rim (a split pixel's parts included): 0 for an empty frame."""
    if signed_coc.size == 0:
        return 0.0
    return max(float(rim.max()) for rim in sc.rim_radii(signed_coc, soft))


def _area(box: tiling.Box) -> int:
    return (box[1] - box[0]) * (box[3] - box[2])


def _lit_area(layer: sc.LayerRecord) -> int:
    """The pixels of a layer's box in its support's tiles (the whole box where it has none): on the CPU its
    sources, level 0 and result take pages there only (:func:`render_layer`)."""
    if layer.support is None:
        return _area(layer.bbox)
    t, (oy, ox) = layer.tile_px, layer.origin
    y0, y1, x0, x1 = layer.bbox

    def overlaps(lo: int, hi: int, n: int) -> np.ndarray:  # pixels of [lo, hi) in each of n tiles
        edges = np.arange(n + 1) * t
        return np.clip(np.minimum(edges[1:], hi) - np.maximum(edges[:-1], lo), 0, None)

    rows = overlaps(y0 + oy, y1 + oy, layer.support.shape[0])
    cols = overlaps(x0 + ox, x1 + ox, layer.support.shape[1])
    return int(rows @ layer.support.astype(np.int64) @ cols)


def layer_cost(layer: sc.LayerRecord) -> int:
    """A layer's render time, roughly (measured on the demo: about 0.1 s per megapixel of its box, and 0.4 s more
    per megapixel of its own pixels): only the order the workers take layers in depends on it."""
    return _area(layer.bbox) + 4 * min(layer.pixels, _area(layer.bbox))


def render_preview(ctx: RenderContext) -> tuple[np.ndarray, PreviewStats]:
    """Render ``ctx.image`` (RGB) with its signed CoC map."""
    options: PreviewOptions = ctx.options
    t_start = time.perf_counter()
    image, s = ctx.image, ctx.signed_coc
    h0, w0 = s.shape
    stats = PreviewStats(quality="preview", shape=(h0, w0), device=ctx.device)
    tiling.check_whole_image(h0, w0, WHOLE_IMAGE_B, ctx.memory)  # before allocating anything large
    stats.max_coc_px = max(float(s.max()), -float(s.min())) if s.size else 0.0

    grid = ctx.layers.tile_px
    soft = ctx.soft if ctx.soft is not None and len(ctx.soft) else None
    pt, pb, pl, pr = _clamped_border(s, soft, grid, options.clamp_border, ctx.memory)
    h, w = h0 + pt + pb, w0 + pl + pr
    # merged sources put a textured cell's light apart from its coverage, which only the coverage a clamped border
    # completes keeps out of the colours (an unclamped border's coverage is cut, and divided out: docs/renderer.md)
    merge = options.merge_sources and ((h, w) != (h0, w0) or _border_reach(s, soft) < 0.5)
    cores = 1 if wp.get_device(ctx.device).is_cuda else max(1, options.threads or os.cpu_count() or 1)
    image, s, soft, copy, photo_range = _padded_frame(image, s, soft, (pt, pb, pl, pr), grid, cores)
    frame = (pt, pt + h0, pl, pl + w0)

    check = (lambda: ctx.progress(0, 1)) if ctx.progress is not None else (lambda: None)  # a stop, before a layer
    check()
    frame_tiles = copy[pt // grid : pt // grid + -(-h0 // grid), pl // grid : pl // grid + -(-w0 // grid)]
    stats.tiles_total, stats.tiles_copied = int(frame_tiles.size), int(frame_tiles.sum())  # the frame's tiles
    active = ~sc.grid_to_pixels(copy, grid, (h, w))
    if not active.any():
        stats.stage_seconds["plan"] = time.perf_counter() - t_start
        stats.stage_seconds["total"] = stats.stage_seconds["plan"]
        return ctx.image.copy(), stats

    photo = image
    # padded, the image and CoC are this function's copies: the split pixels' far parts are written into them (the
    # tiled path reads ``photo`` on copied tiles only, where no pixel is split)
    image, s, scene = sc.split_scene(image, s, soft, active, ctx.layers, options.level_radius_px,
                                     overwrite=(h, w) != (h0, w0), photo_range=photo_range)
    n_split = 0 if soft is None else len(soft)
    del active, soft
    check()
    ctx.release_pixels()  # the scene holds what the layers read (a disposable context's pixels are freed here)
    bound_heap()  # the soft scene's and the plan's freed transients handed back before the layers
    stats.layers = len(scene.layers)
    stats.sources_scattered = sum(lyr.pixels for lyr in scene.layers)  # the layered pixels and the near parts
    stats.pyramid_levels = max(sc.pyramid_levels(lyr.max_radius, options.level_radius_px) for lyr in scene.layers)
    threads = cores

    whole = (WHOLE_IMAGE_B + (0 if ctx.disposable else KEPT_CONTEXT_B)) * h * w + SOFT_B * n_split
    # a layer's arrays take pages where its light lies on the CPU (lazily zeroed), its whole box on a GPU
    on_cpu = wp.get_device(ctx.device).is_cpu
    footprints = [_layer_footprint(lyr, options.level_radius_px, on_cpu, options.exact_highlights)
                  for lyr in scene.layers]
    lazy_acc = on_cpu and lazy_for(h, w)  # the accumulator's pages taken from the first composite on
    if ctx.memory.tile_size is None:
        # fewer layers in flight before tiles: where the budget does not hold a layer a worker but holds the frame
        # with fewer workers, those render it untiled (the same values, the layers' CPU time the same, less
        # parallel), where tiles would repeat every window's halo work or be refused
        budget = tiling.budget_bytes(ctx.memory)
        threads = next((k for k in range(threads, 0, -1)
                        if whole + _region_bytes(h * w, footprints, k, lazy_acc) <= budget), threads)
    stats.threads = threads
    margin = 2 * max(sum(sc.scatter_halo(lyr, options.level_radius_px)) for lyr in scene.layers)
    tiled = (TILED_B if (h, w) != (h0, w0) else 2 * TILED_B) * h * w
    tile, need = tiling.choose_tile(
        h, w, ctx.memory, untiled_bytes=whole + _region_bytes(h * w, footprints, threads, lazy_acc), margin=margin,
        window_bytes=lambda hy, wx: whole + tiled + _region_bytes(
            hy * wx, [(min(px, hy * wx), rate, held) for px, rate, held in footprints], threads, on_cpu and lazy_for(hy, wx)),
        what=f"preview render at a largest CoC of {stats.max_coc_px:.0f} px", frame=(h0, w0),
    )
    stats.memory_estimate_mb = max(need, _plan_bytes(h * w, n_split)) / tiling.MB  # the plan's peak is past
    if tile is None:
        photo = None  # the padded input is read by tiled renders only
    blade_rows = ctx.aperture.blade_discs()
    scatter = _Scatter(aperture_shape(ctx.aperture, blade_rows, ctx.device), float(options.level_radius_px),
                       bool(options.exact_highlights), merge, threads, ctx.device)
    t_plan = time.perf_counter()
    stats.stage_seconds["plan"] = t_plan - t_start

    with reuse_buffers(ctx.device):  # the layers' buffers: allocated once, reused by the next layers (buffers.py)
        if tile is None:
            out, n_filled = _render_window(image, s, scene.ids, scene.layers, scene.n_slots, scatter, ctx.progress,
                                           scene.near, frame)
        else:
            out, n_filled, stats.image_tiles = _render_tiled(photo, image, s, scene, scatter, tile, frame,
                                                             ctx.progress)
            out = np.ascontiguousarray(out[frame[0] : frame[1], frame[2] : frame[3]])
    stats.sources_filled = n_filled
    stats.sources_scattered += n_filled
    stats.stage_seconds["layers"] = time.perf_counter() - t_plan
    stats.stage_seconds["total"] = time.perf_counter() - t_start
    return out, stats


def _padded_frame(image: np.ndarray, s: np.ndarray, soft: sc.SoftEdges | None, pads: tuple[int, int, int, int],
                  grid: int, threads: int):
    """The frame with its clamped border ``pads`` (top, bottom, left, right: the image and the CoC edge-replicated,
    the split pixels replicated; as given where there is none) and its tiles to copy (``scene.copy_tiles``): (image,
    CoC, split pixels, copy grid, the image's per-channel range for the split or None without split pixels). With
    more than one of ``threads``, the image is padded and its range found on another thread while the CoC is padded
    and its tiles reduced (on the cores, ``scene.radius_tile_max``)."""
    pt, pb, pl, pr = pads
    h0, w0 = s.shape
    padded = any(pads)

    def photo() -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray] | None]:
        out = np.pad(image, ((pt, pb), (pl, pr), (0, 0)), mode="edge") if padded else image
        if soft is None:
            return out, None
        rgb = np.asarray(image[..., :3], np.float32)  # the split's colours (the padded border repeats the frame's)
        return out, (rgb.min(axis=0).min(axis=0), rgb.max(axis=0).max(axis=0))  # per axis: far faster than (0, 1)

    with ThreadPoolExecutor(max_workers=1) if threads > 1 else contextlib.nullcontext() as helper:
        job = _soon(photo, helper)
        if padded:
            s = np.pad(s, ((pt, pb), (pl, pr)), mode="edge")
            if soft is not None:  # the split pixels in the padded frame
                soft = sc.pad_soft_edges(soft, (h0, w0), pads)
        copy = sc.copy_tiles_of(sc.radius_tile_max(s, soft, grid), grid)
        out, photo_range = job.result()
    return out, s, soft, copy, photo_range


def _tile_layers(scene: sc.LayeredScene, core: tiling.Box) -> tuple[tiling.Box, list[sc.LayerRecord]]:
    """The window a tile needs and its layers (boxes relative to the window); layers that cannot reach the core
    drop out."""
    cy0, cy1, cx0, cx1 = core
    boxes = []
    for lyr in scene.layers:
        gy0, gy1, gx0, gx1 = lyr.bbox
        if gy1 <= cy0 or gy0 >= cy1 or gx1 <= cx0 or gx0 >= cx1:
            continue  # a layer's box holds all its light: nothing of it lands in this core
        halo, align = sc.scatter_halo(lyr, scene.level_radius_px)
        boxes.append((lyr, tiling.window(lyr.bbox, core, halo, align)))
    wy0 = min([cy0] + [b[0] for _, b in boxes])
    wy1 = max([cy1] + [b[1] for _, b in boxes])
    wx0 = min([cx0] + [b[2] for _, b in boxes])
    wx1 = max([cx1] + [b[3] for _, b in boxes])
    local = [lyr.moved((y0 - wy0, y1 - wy0, x0 - wx0, x1 - wx0), (wy0, wx0)) for lyr, (y0, y1, x0, x1) in boxes]
    return (wy0, wy1, wx0, wx1), local


def _render_tiled(photo: np.ndarray, image: np.ndarray, s: np.ndarray, scene: sc.LayeredScene, scatter: _Scatter,
                  tile: int, frame: tiling.Box, progress: Progress | None) -> tuple[np.ndarray, int, int]:
    """Render tile by tile, each tile on its window (halo included), its core copied out; the tiles cover the
    ``frame`` (the rest is the clamped border around it). ``image`` is the scene's colour (split pixels hold
    their far part), ``photo`` the input."""
    out = photo.copy()  # pixels no layer reaches (copied tiles) keep the input, as finalize does
    fy0, fy1, fx0, fx1 = frame
    plans = {(a + fy0, b + fy0, c + fx0, d + fx0): None
             for a, b, c, d in tiling.cores(fy1 - fy0, fx1 - fx0, tile)}
    plans = {core: _tile_layers(scene, core) for core in plans}
    total = sum(len(local) for _, local in plans.values())
    done, n_filled = 0, 0

    def report(i: int, _n: int) -> None:
        if progress is not None:
            progress(done + i, total)

    def render_core(core: tiling.Box) -> np.ndarray | None:
        nonlocal done, n_filled
        (wy0, wy1, wx0, wx1), local = plans[core]
        if not local:
            return None
        cy0, cy1, cx0, cx1 = core
        part, filled = _render_window(image[wy0:wy1, wx0:wx1], s[wy0:wy1, wx0:wx1], scene.ids[wy0:wy1, wx0:wx1],
                                      local, scene.n_slots, scatter, report, scene.near.window((wy0, wy1, wx0, wx1)),
                                      (cy0 - wy0, cy1 - wy0, cx0 - wx0, cx1 - wx0))
        done += len(local)
        n_filled += filled
        return part

    n_tiles = tiling.render_tiles(out, tile, render_core, frame)
    return out, n_filled, n_tiles


@dataclass(frozen=True, slots=True)
class _Kept:
    """Where a layer's light is kept (the frame without its clamped border, a tile's core; :func:`_kept`): its support
    cut to the tiles that meet it, and the rows ``[start, stop)`` of the layer's box those tiles span."""

    support: sc.LayerSupport
    rows: tuple[int, int]


def _kept(layer: sc.LayerRecord, acc_box: tiling.Box, keep: tiling.Box, device: str) -> _Kept:
    """A layer's :class:`_Kept` for the pixels ``keep`` of its window, whose accumulator spans ``acc_box`` (the
    tiles that meet ``keep``; the whole window where the layers have no support)."""
    y0, y1 = layer.bbox[:2]
    return _Kept(sc.LayerSupport.within(layer, keep, device),
                 (min(max(acc_box[0] - y0, 0), y1 - y0), min(max(acc_box[1] - y0, 0), y1 - y0)))


def render_layer(layer: sc.LayerRecord, arrays: sc.LayerSources, scatter: _Scatter, kept: _Kept | None = None
                 ) -> wp.array:
    """Scatter one layer's sources on the radius pyramid and resolve it: (premultiplied RGB, coverage) on its box,
    at the pixels of ``kept.support`` (None: the layer's support); elsewhere the array holds what it held (zero
    outside the layer's support, its sources elsewhere) and is not to be read. The clamped border's light is output
    nowhere: there the level-0 sums are not stored and nothing is resolved."""
    device = scatter.device
    y0, y1, x0, x1 = layer.bbox
    h, w = y1 - y0, x1 - x0
    support = sc.LayerSupport.of(layer, device)
    kept = kept or _Kept(support, (0, h))
    lazy = lazy_for(h, w)  # a small box's arrays are zeroed at once (buffers.LAZY_MIN_BYTES)

    def sources_zeros(shape, dtype, device):
        """Lazily zeroed on a large box (``lazy``): pages taken where written. The sources' plane, read over the
        support (routing, scatter) and written there at last (the result), takes the support's pages by a first
        write: one fault a page where a first read would map the shared zero page and the write fault again to copy
        it (12 MP: 0.14 M faults
        fewer, 3 s of CPU on this machine; doing the same to level 0 saves 0.03 M more and raises the peak 0.1 GB)."""
        a = lazy_zeros(shape, dtype, device, lazy)
        if dtype is wp.vec4 and is_lazy(a):  # (``wp.zeros`` wrote every page already)
            n, span = sc.row_span(device, w)
            wp.launch(bk.clear_support_kernel, dim=(h, n), inputs=[span, support.struct(), w], outputs=[a],
                      device=device)
        return a

    # One worker fills at a time (the pull-push levels above level 0 and the distance map, on the whole box), so two
    # workers' fills never overlap; the layer's own sources are written before, outside the lock (a worker waiting
    # for it holds only those). Nothing else is shared: values do not depend on it.
    src, coc = sc.build_layer_sources(layer, arrays, zeros=sources_zeros, fill_gate=scatter.fill_gate)
    if lazy:  # a large box: its fill's buffers and transients handed back, not kept beside the layers' peak
        _hand_back(device)
    n_levels = sc.pyramid_levels(layer.max_radius, scatter.level_radius_px)
    first = sc.lowest_level(layer, scatter.level_radius_px)  # levels 1 .. first - 1 stay empty
    bufs = []
    for lv in range(bk.MAX_LEVELS):
        if lv < n_levels and (lv == 0 or lv >= first):
            shape = ((h + (1 << lv) - 1) >> lv, ((w + (1 << lv) - 1) >> lv) + 2)
            # level 0's pages are taken only within the support, where light is deposited and read (the prefix
            # sums store nothing before a row's first deposit nor outside the support); above a first level of 1
            # or more it holds only the routed light and sub-pixel sources, sparse
            bufs.append(lazy_zeros(shape, wp.vec4, device, lazy) if lv == 0 else wp.zeros(shape, wp.vec4, device))
        else:
            bufs.append(bufs[0] if lv > 0 else None)
    routed = scatter.exact_highlights and n_levels > 1
    routing = (route_salient(src, coc, n_levels, scatter.level_radius_px, device, scatter.shape, bufs[0], support,
                             first, lazy) if routed else no_routing(device))
    levels = pyramid_buffers(bufs)
    _scatter_sources(src, coc, support, routing, scatter, n_levels, first, levels)
    del routing, coc  # scattered: their pages go before the prefix sums and the resolve (a layer's last stages)
    # level 0 is read at the kept pixels only (its sums stored there, on the rows that hold them), the coarser levels
    # everywhere
    prefix_rows(bufs[0], device, support, w, kept.support, kept.rows)
    for lv in range(max(1, first), n_levels):
        prefix_rows(bufs[lv], device)
    out = src  # the sources are scattered: reuse their memory for the result at the kept pixels
    n, span = sc.row_span(device, w)
    wp.launch(bk.resolve_levels_kernel, dim=(h, n), inputs=[span, n_levels, first, levels, kept.support.struct()],
              outputs=[out], device=device)
    if lazy:
        bound_heap()  # the layer's freed transients (the C heap's pages of its threads) before its result waits
    return out


def _hand_back(device: str) -> None:
    """After a large layer's fill: the cache's blocks (its fill buffers, reused by the next fill only) and the C heap's
    freed pages go back to the system, so that they do not lie beside the peak of the layers in work (12 MP, a soft
    map: a peak of 1.72 GB without, docs/design/memory-model.md). Nothing changes a value."""
    release_cached(device)
    bound_heap()


def _scatter_sources(src: wp.array, coc: wp.array, support: sc.LayerSupport, routing: Routing, scatter: _Scatter,
                     n_levels: int, first: int, levels: bk.Levels) -> None:
    """Scatter a layer's sources (``bk.scatter_kernel``), those of the pyramid levels ``first`` (at least 1) and up
    merged per cell (:func:`scatter_merged`) unless ``scatter.merge_sources`` is off."""
    h, w = src.shape
    n, span = sc.row_span(scatter.device, w)
    wp.launch(bk.scatter_kernel, dim=(h, n),
              inputs=[span, src, coc, support.struct(), routing.struct(), scatter.shape, scatter.level_radius_px, n_levels,
                      levels, int(scatter.merge_sources)],
              device=scatter.device)
    if scatter.merge_sources:
        for lev in range(max(1, first), n_levels):
            scatter_merged(src, coc, support, routing, scatter, n_levels, lev, levels)


MERGE_COC_CELLS = 0.5
"""Sources of one pyramid cell merge when their signed CoCs differ by less than this many of the level's pixels
(``bk.scatter_merged_kernel``): the level's sharp spans and the upsampling blur their outlines by about one."""


def scatter_merged(src: wp.array, coc: wp.array, support: sc.LayerSupport, routing: Routing, scatter: _Scatter,
                   n_levels: int, lev: int, levels: bk.Levels) -> None:
    """Scatter a layer's sources of pyramid level ``lev`` >= 1 merged per cell (``bk.scatter_merged_kernel``)."""
    h, w = src.shape
    side = 1 << lev
    wp.launch(bk.scatter_merged_kernel, dim=((h + side - 1) // side, (w + side - 1) // side),
              inputs=[src, coc, support.struct(), routing.struct(), scatter.shape, scatter.level_radius_px, n_levels,
                      lev, MERGE_COC_CELLS * side, levels], device=scatter.device)


def prefix_rows(buf: wp.array, device: str, support: sc.LayerSupport | None = None, width: int | None = None,
                store: sc.LayerSupport | None = None, rows: tuple[int, int] | None = None) -> None:
    """The running sums of a difference buffer's rows, in place (``prefix_rows_kernel``), read within ``support``,
    stored within it and ``store`` (None: everywhere), in the first ``width`` columns (None: all) of the rows
    ``rows`` (start, stop; None: all) only."""
    everywhere = sc.LayerSupport.everywhere(device) if support is None or store is None else None
    inside, keep = support or everywhere, store or everywhere
    r0, r1 = rows or (0, buf.shape[0])
    if r1 <= r0:
        return
    if (r0, r1) != (0, buf.shape[0]):
        buf, inside, keep = buf[r0:r1], inside.down(r0), keep.down(r0)
    wp.launch(bk.prefix_rows_kernel, dim=buf.shape[0],
              inputs=[buf, inside.struct(), keep.struct(), buf.shape[1] if width is None else width], device=device)


def _acc_box(layers, keep: tiling.Box, shape: tuple[int, int]) -> tiling.Box:
    """The window's pixels the accumulator spans: the tiles that meet ``keep`` (the layers' supports cut to them,
    :meth:`bokehray.scene.LayerSupport.within`), within the window; the whole window where the layers have no
    support (they composite their whole box)."""
    if not layers or layers[0].support is None:
        return 0, shape[0], 0, shape[1]
    t, (oy, ox) = layers[0].tile_px, layers[0].origin
    y0, y1, x0, x1 = keep
    return (max(0, (y0 + oy) // t * t - oy), min(shape[0], -(-(y1 + oy) // t) * t - oy),
            max(0, (x0 + ox) // t * t - ox), min(shape[1], -(-(x1 + ox) // t) * t - ox))


def _render_window(image: np.ndarray, s: np.ndarray, ids: np.ndarray, layers, n_slots: int, scatter: _Scatter,
                   progress: Progress | None, near: sc.NearParts | None = None, keep: tiling.Box | None = None
                   ) -> tuple[np.ndarray, int]:
    """Scatter and composite ``layers`` (boxes in the window's coordinates), then finalise the pixels ``keep`` of
    the window (None: all; the frame without its clamped border, a tile's core): the layers resolve and composite
    no more than the tiles that meet it. ``near``: the near parts of split pixels, in the window's coordinates.

    Returns the rendered RGB of ``keep`` and the number of filled sources.
    """
    device = scatter.device
    h, w = s.shape
    keep = keep or (0, h, 0, w)
    arrays = sc.LayerSources.upload(image, s, ids, n_slots, device, near)
    ay0, ay1, ax0, ax1 = box = _acc_box(layers, keep, (h, w))
    kept = [_kept(lyr, box, keep, device) for lyr in layers]

    # Layers render independently (Warp CPU launches release the GIL) on ``threads`` workers and are composited
    # strictly back to front as they complete (:class:`_Starter` says which layer a free worker takes).
    pool = ThreadPoolExecutor(max_workers=scatter.threads)
    # the composite and the final division in bands of rows, one on this thread and one on each other core: the
    # layers still in work share the cores with them, and after the last one no core idles while they run
    bands = ThreadPoolExecutor(max_workers=scatter.threads - 1) if scatter.threads > 1 else None
    whole = _soon(functools.partial(_whole, arrays, box, device), bands)  # while the first layers render
    # the accumulator too (zeroed at once below 2 MP; when lazy, its pages are taken at the first composite)
    acc_job = _soon(functools.partial(lazy_zeros, (ay1 - ay0, ax1 - ax0), wp.vec4, device,
                                      lazy_for(ay1 - ay0, ax1 - ax0)), bands)
    starter = _Starter(lambda layer, k: render_layer(layer, arrays, scatter, k), layers, kept, pool,
                       scatter.threads)
    try:
        while (head := starter.head) < len(layers):
            starter.top_up()
            fut = starter.get(head)  # None: every worker busy with layers further front
            if fut is None or not fut.done():
                wait([fut] if fut is not None else starter.running(), return_when=FIRST_COMPLETED)
                continue
            out = fut.result()
            starter.composited(head)
            _composite(out, layers[head], kept[head], box, acc_job.result(), whole.result(), device, bands,
                       scatter.threads)
            del out
            if progress is not None:
                progress(head + 1, len(layers))
    except BaseException:
        # Ctrl-C, or a progress callback that abandons the render: return at once, not after the layers in
        # flight (their results are dropped; the command line then exits without waiting for them)
        starter.stop()
        pool.shutdown(wait=False, cancel_futures=True)
        if bands is not None:
            bands.shutdown(wait=False)  # (its bands are waited for where they are started)
        raise
    pool.shutdown(wait=True)
    acc = acc_job.result()

    ky0, ky1, kx0, kx1 = keep
    result = wp.empty((ky1 - ky0, kx1 - kx0), dtype=wp.vec3, device=device)

    def finalize(a: int, b: int) -> None:  # rows [a, b) of the kept pixels
        wp.launch(bk.finalize_kernel, dim=(b - a, kx1 - kx0),
                  inputs=[acc[ky0 + a - ay0 : ky0 + b - ay0, kx0 - ax0 : kx1 - ax0], arrays.image[ky0 + a : ky0 + b, kx0:kx1],
                          arrays.ids[ky0 + a : ky0 + b, kx0:kx1]], outputs=[result[a:b]], device=device)

    in_bands(finalize, 0, ky1 - ky0, bands, scatter.threads)
    if bands is not None:
        bands.shutdown(wait=True)
    return result.numpy(), arrays.filled_count()


class _Starter:
    """Which layers are in work on the pool's ``threads`` workers, and the next to composite (:attr:`head`): a free
    worker takes the next layer to composite if it has not started, else the costliest one left
    (:func:`layer_cost`), so that a slow layer does not start last while the other workers idle. A finished layer
    waiting to be composited holds only its result (16 B/px); while as many results wait as there are workers, only
    the next layer to composite starts (:func:`_region_bytes` counts one working layer a thread and that many
    results). :meth:`top_up` runs on the compositing thread and on each worker as its layer finishes, so a worker
    freed while the composite runs takes its next layer at once."""

    def __init__(self, render, layers, kept, pool: ThreadPoolExecutor, threads: int) -> None:
        self.render, self.layers, self.kept, self.pool, self.threads = render, layers, kept, pool, threads
        self.order = sorted(range(len(layers)), key=lambda k: -layer_cost(layers[k]) if threads > 1 else k)
        self.lock = threading.Lock()
        self.started: dict[int, Future] = {}  # started and not yet composited
        self.head = 0
        self.stopped = False

    def top_up(self, _finished: Future | None = None) -> None:
        """Start layers while a worker is free and a layer may start (a future's done callback)."""
        new = []
        with self.lock:
            # (a layer's callback may run after the compositing thread has taken its result and moved the head past
            # the last layer: a future's waiters are woken before its callbacks run)
            while not self.stopped and self.head < len(self.layers):
                running = sum(not f.done() for f in self.started.values())
                waiting = len(self.started) - running  # finished, waiting for the layers behind them
                if running >= self.threads:
                    break
                # the next to composite always; another only while fewer results than workers wait (each holds
                # 16 B a box pixel: workers far ahead of a slow back layer would stack them up)
                pick = self.head if self.head not in self.started else next(
                    (k for k in self.order if k > self.head and k not in self.started and waiting < self.threads),
                    None)
                if pick is None:
                    break
                self.started[pick] = fut = self.pool.submit(self.render, self.layers[pick], self.kept[pick])
                new.append(fut)
        for fut in new:  # outside the lock: a future already done calls back at once, on this thread
            fut.add_done_callback(self.top_up)

    def get(self, k: int) -> Future | None:
        with self.lock:
            return self.started.get(k)

    def running(self) -> list[Future]:
        with self.lock:
            return [f for f in self.started.values() if not f.done()]

    def composited(self, k: int) -> None:
        """Layer ``k``, the head, leaves the workers' count: the next one is the head."""
        with self.lock:
            del self.started[k]
            self.head = k + 1

    def stop(self) -> None:
        """Start nothing more (the render is abandoned)."""
        with self.lock:
            self.stopped = True


BAND_MIN_ROWS = 64
"""Rows below which a per-pixel pass over a region runs in one band (:func:`in_bands`): handing a band to another
thread costs about as much as a few thousand pixels."""


def in_bands(launch, r0: int, r1: int, helper: ThreadPoolExecutor | None, threads: int) -> None:
    """``launch(a, b)`` over the rows ``[r0, r1)`` cut into up to ``threads`` bands: the first on this thread, the
    others on ``helper``'s ``threads - 1`` threads (None: one band here). Returns when every band is done; for passes
    whose rows are independent (each band's values are those of one launch over all rows)."""
    n = 1 if helper is None else min(threads, max(1, (r1 - r0) // BAND_MIN_ROWS))
    cuts = [r0 + (r1 - r0) * i // n for i in range(n + 1)]
    on_threads([functools.partial(launch, a, b) for a, b in itertools.pairwise(cuts) if b > a], helper)


def _composite(out: wp.array, layer: sc.LayerRecord, kept: _Kept, acc_box: tiling.Box, acc: wp.array,
               whole: tuple[wp.array, wp.array], device: str, helper: ThreadPoolExecutor | None = None,
               threads: int = 1) -> None:
    """Composite a resolved layer (``render_layer``'s ``out`` on its box) over the accumulator (on ``acc_box``) at
    its kept pixels, in bands of rows on this thread and ``helper``'s (:func:`in_bands`). ``whole``: the pixels
    their own layer covers whole (:func:`opaque_pixels`) and the layers' ids, on the accumulator's pixels."""
    y0, _, x0, x1 = layer.bbox
    n, span = sc.row_span(device, x1 - x0)

    def launch(a: int, b: int) -> None:
        wp.launch(bk.composite_kernel, dim=(b - a, n),
                  inputs=[span, out[a:b], kept.support.down(a).struct(), x0 - acc_box[2], y0 + a - acc_box[0],
                          whole[0], whole[1], layer.index], outputs=[acc], device=device)

    in_bands(launch, *kept.rows, helper, threads)


def _whole(arrays: sc.LayerSources, box: tiling.Box, device: str) -> tuple[wp.array, wp.array]:
    """The pixels their own layer covers whole (:func:`opaque_pixels`) and the layers' ids, on the accumulator's
    ``box``."""
    y0, y1, x0, x1 = box
    return opaque_pixels(arrays, device)[y0:y1, x0:x1], arrays.ids[y0:y1, x0:x1]


def _soon(fn, executor: ThreadPoolExecutor | None) -> Future:
    """``fn()`` on ``executor`` (None: here, now), as a future."""
    if executor is not None:
        return executor.submit(fn)
    f: Future = Future()
    f.set_result(fn())
    return f


def opaque_pixels(arrays: sc.LayerSources, device: str) -> wp.array:
    """The window's pixels whose cone, of their CoC radius plus one, meets no farther surface, no split and no copied
    pixel (``bokehray_kernels.interior``; a farther surface is one beyond the matting's depth-edge jump,
    ``MattingRule.jump_px``): 1 there, 0 elsewhere. The composite takes their own layer's coverage as
    1 there, where the footprints of sources of unequal radii need not sum to 1."""
    h, w = arrays.ids.shape
    dist = wp.empty((h, w), dtype=float, device=device)
    n, span = sc.row_span(device, w)
    wp.launch(bk.boundary_kernel, dim=(h, n), inputs=[span, arrays.ids, arrays.signed_coc, MattingRule().jump_px],
              outputs=[dist], device=device)
    if arrays.near is not None:
        wp.launch(bk.mark_split_kernel, dim=arrays.near[0].shape[0], inputs=[arrays.near[0], arrays.near[1]],
                  outputs=[dist], device=device)
    wp.launch(bk.row_sweep_kernel, dim=h, inputs=[dist], device=device)
    band = w if wp.get_device(device).is_cpu else 1
    wp.launch(bk.column_distance_kernel, dim=-(-w // band), inputs=[dist, h, band], device=device)
    flag = wp.empty((h, w), dtype=wp.uint8, device=device)
    wp.launch(bk.opaque_flag_kernel, dim=(h, n), inputs=[span, dist, arrays.signed_coc], outputs=[flag],
              device=device)
    return flag


def render_signed_coc(image: np.ndarray, signed_coc: np.ndarray, aperture, *, layers=None, memory=None,
                      options: PreviewOptions | None = None, device: str = "cpu",
                      progress: Progress | None = None) -> tuple[np.ndarray, PreviewStats]:
    """The preview of an RGB float32 image (validated by the caller) with a given signed CoC map instead of a
    disparity and ``BlurParams``: the seam the kernel tests and stress cases render through."""
    from ..options import LayerOptions, MemoryOptions

    memory = memory or MemoryOptions()
    tiling.check_whole_image(*signed_coc.shape, WHOLE_IMAGE_B, memory)  # from the shape, before reading a value
    ctx = RenderContext(image, None, sc.cap_coc(signed_coc), None, aperture, layers or LayerOptions(), memory,
                        options or PreviewOptions(), device, progress)
    out, stats = render_preview(ctx)
    stats.max_coc_px = max(float(signed_coc.max()), -float(signed_coc.min())) if signed_coc.size else 0.0
    return out, stats
