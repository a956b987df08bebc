"""The layered ray tracer: exact thin-lens renders of layer stacks, and the ``raytrace`` quality level.

The aperture is cut into box cells (``levels.quadrature``), one ray per cell, intersected with every layer and
composited front to back, each layer's texture averaged exactly over the cell's footprint (kernel:
``bokehray_kernels.raytrace``; launches in interruptible row bands: ``levels.raytrace_launch``). For a stack of
RGBA layers this is the thin-lens image up to the stated bias (:func:`raytrace_layers`); for a photo, the layered
scene is the preview's (``bokehray.scene``: the same depth slices, hidden regions filled), ray traced instead of
scattered (:func:`render_raytrace`). See docs/raytracer.md.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .. import scene as sc
from .. import tiling
from ..edge_estimate import dilate
from ..errors import InputError
from ..lens import Aperture, BlurParams
from ..options import RaytraceOptions
from ..stats import RaytraceStats
from ..validate import check_finite, check_radiance, check_type
from .base import Progress, RenderContext
from .raytrace_launch import choose_levels, strip_range, summed_area, trace_bands

__all__ = ["Layer", "raytrace_layers", "render_raytrace"]

# Bytes per pixel (float32 = 4 bytes), checked against measured peaks by benchmarks/photo/bench_memory.py.
WHOLE_IMAGE_B = 48
"""Whole-image arrays: signed CoC, layer ids, the plan's sort keys, output."""
LAYER_B = 56
"""Per pixel of the traced region and per layer: the packed texture (16 + 4) on the host and its float64
summed-area table (32; read in place on the CPU, copied to a GPU)."""
REGION_B = 150
"""Per pixel of the traced region: image, CoC, layer ids on the device, a layer's sources and fill pyramid while
it is built, ray counts, result and normalised result."""


CONTENT_ALPHA = 1e-4
"""A texel of a map layer with less coverage is outside the layer's content (``bk.raytrace_kernel``'s march)."""


@dataclass(frozen=True)
class Layer:
    """One layer of a scene: an RGBA texture and its disparity.

    Args:
        rgba: ``H x W x 4`` float32, scene-linear colour with straight (not
            premultiplied) alpha; alpha 0 is empty space.
        disparity: ``H x W`` disparity map in [0, 1], or None for a plane.
        plane: ``(a, b, c)`` with ``d = a * x + b * y + c`` at pinhole-image
            position ``(x, y)`` in pixels (pixel centres at ``i + 0.5``).
    """

    rgba: np.ndarray
    disparity: np.ndarray | None = None
    plane: tuple[float, float, float] | None = None


@dataclass(frozen=True, slots=True, eq=False)
class _Stack:
    """Packed layers, nearest first: premultiplied RGB and coverage (n, H, W, 4), the disparity of every layer at
    every pixel (n, H, W) and ``(a, b, c, 1)`` for plane layers, else 0 (n, 4)."""

    rgba: np.ndarray
    disp: np.ndarray
    planes: np.ndarray

    @property
    def n(self) -> int:
        return self.disp.shape[0]


@dataclass(frozen=True, slots=True, eq=False)
class _Part:
    """What a tile of a larger trace takes from the whole image: each layer's disparity range (the march
    bounds, n x 2), the visible CoC of the traced pixels (the ray counts), and the traced pixels ``core`` (y0, y1,
    x0, x1) inside the textures."""

    ranges: np.ndarray
    r_px: np.ndarray
    core: tiling.Box


def _validate_layers(layers: list[Layer]) -> tuple[int, int]:  # noqa: C901
    if isinstance(layers, Layer) or not isinstance(layers, (list, tuple)):
        raise InputError(f"layers: expected a list of bokehray.Layer, got {type(layers).__name__}")
    if not layers:
        raise InputError("layers: expected at least one layer")
    shape = None
    for i, lyr in enumerate(layers):
        check_type(lyr, Layer, f"layer {i}", "a bokehray.Layer")
        rgba = np.asarray(lyr.rgba)
        if rgba.ndim != 3 or rgba.shape[2] != 4:
            raise InputError(f"layer {i}: expected an H x W x 4 RGBA texture (with alpha), got shape {rgba.shape}")
        if shape is None:
            shape = rgba.shape[:2]
        elif rgba.shape[:2] != shape:
            raise InputError(f"layer {i}: expected size {shape} like layer 0, got {rgba.shape[:2]}")
        check_finite(rgba, f"layer {i} RGBA", "(y, x, c)")
        check_radiance(rgba[..., :3], f"layer {i} RGBA")
        if (lyr.disparity is None) == (lyr.plane is None):
            raise InputError(f"layer {i}: give exactly one of a disparity map or a plane (a, b, c)")
        if lyr.disparity is not None:
            d = np.asarray(lyr.disparity)
            if d.shape != shape:
                raise InputError(f"layer {i}: disparity shape {d.shape} differs from the texture's {shape}")
            check_finite(d, f"layer {i} disparity")
        elif not all(math.isfinite(float(v)) for v in lyr.plane):
            raise InputError(f"layer {i}: plane coefficients must be finite, got {lyr.plane}")
    return shape


def _layer_disparity_at_pixels(lyr: Layer, h: int, w: int) -> np.ndarray:
    if lyr.disparity is not None:
        return np.asarray(lyr.disparity, np.float32)
    a, b, c = lyr.plane
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32) + 0.5
    return (a * xx + b * yy + c).astype(np.float32)


def _visible_coc(coc: np.ndarray, content: np.ndarray, grid: int) -> np.ndarray:
    """A layer's CoC where its content can reach (tiles with content, dilated by the CoC), else 0.

    A layer whose disparity is defined everywhere but whose alpha is zero far from a pixel cannot send that
    pixel any light: it must not inflate the pixel's ray count.
    """
    reach = dilate(sc.tile_max(content, grid), int(np.ceil(float(coc.max()) / grid)) + 1)
    return np.where(sc.grid_to_pixels(reach, grid, coc.shape), coc, 0.0).astype(np.float32)


def raytrace_layers(
    layers: list[Layer],
    blur: BlurParams,
    aperture: Aperture | None = None,
    *,
    options: RaytraceOptions | None = None,
    device: str = "cpu",
    progress: Callable[[int, int], None] | None = None,
) -> tuple[np.ndarray, RaytraceStats]:
    """Ray trace a front-to-back stack of layers through a thin lens.

    Args:
        layers: nearest first. Layers are composited in this order along every
            ray, so they must not interpenetrate.
        blur: ``K`` and ``d_f``: a point at disparity ``d`` spreads into the
            aperture of radius ``K |d - d_f|`` px.
        aperture: disc (default) or bladed polygon.
        options: aperture sampling (:class:`~bokehray.RaytraceOptions`).
        progress: called as ``progress(done, total)`` (units of work) between bands of rows;
            an exception it raises (or Ctrl-C) stops the trace within one band.

    Returns:
        ``(H x W x 4, stats)``: premultiplied RGB and the coverage (1 minus the
        transmittance left after the last layer), both averaged over the rays.
    """
    t0 = time.perf_counter()
    check_type(blur, BlurParams, "blur", "a bokehray.BlurParams")
    aperture = Aperture() if aperture is None else aperture
    check_type(aperture, Aperture, "aperture", "a bokehray.Aperture")
    options = RaytraceOptions() if options is None else options
    check_type(options, RaytraceOptions, "options", "a bokehray.RaytraceOptions")
    h, w = _validate_layers(layers)
    n = len(layers)
    rgba = np.empty((n, h, w, 4), np.float32)
    disp = np.empty((n, h, w), np.float32)
    planes = np.zeros((n, 4), np.float32)
    for i, lyr in enumerate(layers):
        tex = np.asarray(lyr.rgba, np.float32)
        rgba[i, ..., :3] = tex[..., :3] * tex[..., 3:4]
        rgba[i, ..., 3] = tex[..., 3]
        disp[i] = _layer_disparity_at_pixels(lyr, h, w)
        if lyr.plane is not None:
            planes[i] = (*lyr.plane, 1.0)
    out, stats = _trace(_Stack(rgba, disp, planes), blur, aperture, options, device, t0, progress=progress)
    stats.shape, stats.device = (h, w), device
    return out, stats


def _whole_part(stack: _Stack, blur: BlurParams, grid: int) -> _Part:
    """The :class:`_Part` of an untiled trace: ranges and visible CoC from the whole layers."""
    n, h, w = stack.disp.shape
    ranges = np.stack([stack.disp.min(axis=(1, 2)), stack.disp.max(axis=(1, 2))], axis=1).astype(np.float32)
    r_px = np.zeros((h, w), np.float32)
    for i in range(n):
        np.maximum(r_px, _visible_coc(blur.coc_radius(stack.disp[i]), stack.rgba[i, ..., 3] > 0, grid), out=r_px)
    return _Part(ranges, r_px, (0, h, 0, w))


def _trace(stack: _Stack, blur: BlurParams, aperture: Aperture, options: RaytraceOptions, device: str, t0: float,
           part: _Part | None = None, grid: int = 16, progress: Progress | None = None
           ) -> tuple[np.ndarray, RaytraceStats]:
    """Trace packed layers in row bands (``levels.raytrace_launch``); returns the traced pixels (``part.core``) only."""
    part = _whole_part(stack, blur, grid) if part is None else part
    core = part.core
    levels, table, _ = choose_levels(part.r_px, aperture, options.samples_per_px2, strip_range(options),
                                     options.max_spp)
    sat = summed_area(stack.rgba)
    t1 = time.perf_counter()
    result = trace_bands(sat, stack.disp, stack.planes, part.ranges, float(blur.k_px), float(blur.focus_disparity),
                         table, levels, (core[0], core[2]), device, progress=progress)
    rays = table.count(levels)
    stats = RaytraceStats(quality="raytrace", layers=stack.n, samples_total=int(rays.sum()),
                          spp_mean=float(rays.mean()), spp_max=int(rays.max()),
                          partitions=[[int(g), float(ol)] for g, ol in table.parts])
    stats.stage_seconds = {"setup": t1 - t0, "trace": time.perf_counter() - t1, "total": time.perf_counter() - t0}
    return result, stats


def _photo_stack(scene: sc.LayeredScene, image: np.ndarray, s: np.ndarray, ids: np.ndarray, blur: BlurParams,
                 device: str, near: sc.NearParts | None = None) -> _Stack:
    """The map layers of photo mode on the given arrays (the whole image, or a tile's window; ``near``: the near
    parts of split pixels in its coordinates), nearest first."""
    h, w = s.shape
    arrays = sc.LayerSources.upload(image, s, ids, scene.n_slots, device, near)
    n = len(scene.layers)
    rgba = np.empty((n, h, w, 4), np.float32)
    disp = np.empty((n, h, w), np.float32)
    for i, layer in enumerate(reversed(scene.layers)):  # nearest first
        src, coc = sc.build_layer_sources(layer.moved((0, h, 0, w)), arrays)
        rgba[i] = src.numpy()  # premultiplied RGB and coverage already: what the kernel takes
        # the layer's own CoC where it has content (coverage of at least the march's 1e-4: a split pixel's near
        # part may hold less), its mid-range elsewhere (transparent: never hit)
        coc_np = np.where(rgba[i, ..., 3] >= CONTENT_ALPHA, np.clip(coc.numpy(), layer.s_lo, layer.s_hi),
                          0.5 * (layer.s_lo + layer.s_hi))
        disp[i] = np.clip(coc_np / blur.k_px + blur.focus_disparity, 0.0, 1.0)
    np.clip(rgba[..., 3], 0.0, 1.0, out=rgba[..., 3])
    return _Stack(rgba, disp, np.zeros((n, 4), np.float32))


def _halo(scene: sc.LayeredScene, grid: int) -> tuple[int, int]:
    """(halo, alignment) of photo-mode tiles: every layer is filled on the whole image (its box at 0, 0); the
    alignment keeps the cores on the grid of the visible-CoC tiles."""
    reach = int(math.ceil(scene.max_coc)) + 4
    halo, align = reach, 1
    for lyr in scene.layers:
        f_halo, f_align = sc.fill_halo(lyr)
        if lyr.filled:
            halo = max(halo, reach + f_halo)
        align = max(align, f_align)
    return halo, max(align, grid)


def render_raytrace(ctx: RenderContext) -> tuple[np.ndarray, RaytraceStats]:
    """Photo mode: ray trace the layered scene built from one RGB image and its disparity.

    Each layer becomes a map layer whose disparity is its pixels' own where it has content. Rays that end on no
    opaque layer are renormalised by the coverage they found, as in the preview. Large renders go tile by tile
    (``bokehray.tiling``), with the same result.
    """
    options: RaytraceOptions = ctx.options
    image, blur, s = ctx.image, ctx.blur, ctx.signed_coc
    h, w = s.shape
    if blur.k_px == 0.0:  # a pinhole: the input itself
        return image[..., :3].copy(), RaytraceStats(quality="raytrace", shape=(h, w), device=ctx.device,
                                                    stage_seconds={"total": 0.0})
    tiling.check_whole_image(h, w, WHOLE_IMAGE_B, ctx.memory)
    # the layers' disparity is s / K + d_f: s is capped (bokehray.scene.cap_coc), the disparity alike
    # the scene's colour and CoC hold the far parts of split pixels (ctx.soft), the scene their near parts
    split_image, split_s, scene = sc.split_scene(image, s, ctx.soft, np.ones((h, w), bool), ctx.layers)
    grid = ctx.layers.tile_px
    n = len(scene.layers)
    halo, align = _halo(scene, grid)
    per_px = REGION_B + LAYER_B * n
    tile, need = tiling.choose_tile(
        h, w, ctx.memory, untiled_bytes=(WHOLE_IMAGE_B + per_px) * h * w, margin=2 * halo + align,
        window_bytes=lambda hy, wx: WHOLE_IMAGE_B * h * w + per_px * hy * wx,
        what=f"ray traced render with {n} layers")
    t0 = time.perf_counter()
    if tile is None:
        stack = _photo_stack(scene, split_image, split_s, scene.ids, blur, ctx.device, scene.near)
        t_layers = time.perf_counter()
        part = _whole_part(stack, blur, grid)
        out, stats = _trace(stack, blur, ctx.aperture, options, ctx.device, t_layers, part, grid, ctx.progress)
        stats.stage_seconds = {"layers": t_layers - t0, **stats.stage_seconds,
                               "total": stats.stage_seconds["total"] + t_layers - t0}
        del stack
    else:
        out, stats = _trace_tiles(ctx, scene, split_image, split_s, -(-tile // grid) * grid, halo, align, t0)
    stats.shape, stats.device = (h, w), ctx.device
    stats.memory_estimate_mb = need / tiling.MB
    cov = out[..., 3:4]
    rgb = np.where(cov > 1e-4, out[..., :3] / np.maximum(cov, 1e-12), image[..., :3])
    return rgb.astype(np.float32), stats


def _trace_tiles(ctx: RenderContext, scene: sc.LayeredScene, image: np.ndarray, s: np.ndarray, tile: int, halo: int,
                 align: int, t0: float) -> tuple[np.ndarray, RaytraceStats]:
    """Photo mode tile by tile, equal to the untiled trace.

    Pass 1 builds each tile's layers on its window and gathers what the untiled trace takes from whole layers:
    their disparity ranges (the march bounds), their largest CoC and their content tiles (the ray counts).
    Pass 2 builds them again and traces each tile's core.
    """
    blur = ctx.blur
    h, w = s.shape
    n, grid = len(scene.layers), ctx.layers.tile_px
    ranges = np.tile(np.array([[np.inf, -np.inf]], np.float32), (n, 1))
    coc_max = np.zeros(n, np.float32)
    content = np.zeros((n, -(-h // grid), -(-w // grid)), bool)

    def window_stack(core: tiling.Box) -> tuple[tiling.Box, tiling.Box, _Stack]:
        wy0, wy1, wx0, wx1 = tiling.window((0, h, 0, w), core, halo, align)
        stack = _photo_stack(scene, image[wy0:wy1, wx0:wx1], s[wy0:wy1, wx0:wx1], scene.ids[wy0:wy1, wx0:wx1],
                             blur, ctx.device, scene.near.window((wy0, wy1, wx0, wx1)))
        cy0, cy1, cx0, cx1 = core
        return (wy0, wy1, wx0, wx1), (cy0 - wy0, cy1 - wy0, cx0 - wx0, cx1 - wx0), stack

    for core in tiling.cores(h, w, tile):
        _, (y0, y1, x0, x1), stack = window_stack(core)
        d = stack.disp[:, y0:y1, x0:x1]
        np.minimum(ranges[:, 0], d.min(axis=(1, 2)), out=ranges[:, 0])
        np.maximum(ranges[:, 1], d.max(axis=(1, 2)), out=ranges[:, 1])
        for i in range(n):
            coc_max[i] = max(coc_max[i], float(blur.coc_radius(d[i]).max()))
            ty, tx = core[0] // grid, core[2] // grid
            t = sc.tile_max(stack.rgba[i, y0:y1, x0:x1, 3] > 0, grid)
            content[i, ty : ty + t.shape[0], tx : tx + t.shape[1]] |= t
    reach = [dilate(content[i], int(np.ceil(float(coc_max[i]) / grid)) + 1) for i in range(n)]

    stats = RaytraceStats(quality="raytrace", layers=n)
    all_cores = tiling.cores(h, w, tile)
    traced = 0.0

    def trace_core(core: tiling.Box) -> np.ndarray:
        nonlocal traced
        _, (y0, y1, x0, x1), stack = window_stack(core)
        cy0, cy1, cx0, cx1 = core
        r_px = np.zeros((cy1 - cy0, cx1 - cx0), np.float32)
        for i in range(n):
            sub = reach[i][cy0 // grid : -(-cy1 // grid), cx0 // grid : -(-cx1 // grid)]  # cores start on the grid
            mask = sc.grid_to_pixels(sub, grid, (cy1 - cy0, cx1 - cx0))
            np.maximum(r_px, np.where(mask, blur.coc_radius(stack.disp[i, y0:y1, x0:x1]), 0.0).astype(np.float32),
                       out=r_px)
        k = all_cores.index(core)
        tile_progress = None if ctx.progress is None else (
            lambda done, total: ctx.progress(k * 1000 + int(1000 * done / max(total, 1)), 1000 * len(all_cores)))
        part, st = _trace(stack, blur, ctx.aperture, ctx.options, ctx.device, time.perf_counter(),
                          _Part(ranges, r_px, (y0, y1, x0, x1)), grid, tile_progress)
        stats.samples_total += st.samples_total
        stats.spp_max = max(stats.spp_max, st.spp_max)
        stats.partitions += [p for p in st.partitions if p not in stats.partitions]
        traced += st.stage_seconds["total"]
        return part

    out = np.empty((h, w, 4), np.float32)
    stats.image_tiles = tiling.render_tiles(out, tile, trace_core)
    stats.spp_mean = stats.samples_total / float(h * w)
    total = time.perf_counter() - t0
    stats.stage_seconds = {"layers (both passes)": total - traced, "trace": traced, "total": total}
    return out, stats
