"""The layered ray tracer: exact thin-lens renders of layer stacks, and the ``raytrace`` quality level.

Rays through sampled points of the aperture are intersected with every layer
and composited front to back (kernel: ``bokehray_kernels.raytrace``). For a
stack of planar RGBA layers this converges to the exact thin-lens image as the
samples grow; for a photo, the layers are built from the image and its
disparity exactly as the preview builds them (depth slices, hidden regions
filled), then ray traced instead of scattered. See docs/raytracer.md.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import warp as wp

from ._scatter import PreviewOptions, _box_max_tiles, _dilate, _layer_sources, cap_coc, plan_layers
from .errors import InputError
from .lens import Aperture, BlurParams

MAX_RADIANCE = 1e36
"""Largest radiance photo-mode ray tracing accepts: sums of 128 rays of it stay within float32 (3.4e38)."""

__all__ = ["Layer", "RaytraceOptions", "RaytraceStats", "raytrace_layers", "render_raytrace"]


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


@dataclass(frozen=True)
class RaytraceOptions:
    """The aperture quadrature (``bokehray.quadrature``; docs/raytracer.md).

    Args:
        samples_per_px2: cells per square pixel of the largest CoC a pixel can
            see: the aperture is cut into ``g = ceil(2 r sqrt(samples_per_px2))``
            strips of square-ish cells (about ``(pi / 4) g^2`` of them) plus thin
            cells along its outline. Each cell is one ray whose texture lookups
            average the cell's footprint, so this sets how finely occlusion between
            layers is resolved, not the noise (there is none).
        max_spp: most rays (cells) per pixel: the strips are capped at ``sqrt(4 max_spp / pi)``
            and, where the full cells and the thin cells along the outline exceed it, the outline
            is coarsened, then strips dropped (``bokehray.raytrace_launch.choose_levels``).
            1 is a single box cell of the aperture's area.
        min_spp: the fewest rays per pixel; 1 lets in-focus pixels (CoC below half a
            pixel) take the single centre ray.
    """

    samples_per_px2: float = 0.5
    max_spp: int = 128
    min_spp: int = 1

    def __post_init__(self) -> None:
        if not (math.isfinite(self.samples_per_px2) and self.samples_per_px2 > 0):
            raise InputError(f"samples_per_px2: expected a finite value > 0, got {self.samples_per_px2!r}")
        if not 1 <= self.min_spp <= self.max_spp <= 65536:
            raise InputError(f"rays per pixel: expected 1 <= min_spp <= max_spp <= 65536, "
                             f"got {self.min_spp}, {self.max_spp}")

    def strip_range(self) -> tuple[int, int]:
        """(fewest, most) strips across the aperture (0 fewest: in-focus pixels take the centre ray)."""
        from .raytrace_launch import strip_cap  # noqa: PLC0415

        g_max = strip_cap(self.max_spp)
        g_min = 0 if self.min_spp <= 1 else min(g_max, int(math.ceil(math.sqrt(4.0 * self.min_spp / math.pi) - 1e-9)))
        return g_min, g_max


@dataclass
class RaytraceStats:
    """Samples used and time taken."""

    layers: int = 0
    samples_total: int = 0
    spp_mean: float = 0.0
    spp_max: int = 0
    image_tiles: int = 1
    memory_estimate_mb: float = 0.0
    stage_seconds: dict[str, float] = field(default_factory=dict)
    partitions: list = field(default_factory=list)  #: (strips, outline) of each aperture partition used
    refine: dict | None = None  #: what ``refine=`` did (tiles refined, share, seconds), None without it

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


def _validate_layers(layers: list[Layer]) -> tuple[int, int]:
    if not layers:
        raise InputError("layers: expected at least one layer")
    shape = None
    for i, lyr in enumerate(layers):
        rgba = np.asarray(lyr.rgba)
        if rgba.ndim != 3 or rgba.shape[2] != 4:
            raise InputError(f"layer {i}: expected an H x W x 4 RGBA texture (with alpha), got shape {rgba.shape}")
        if shape is None:
            shape = rgba.shape[:2]
        elif rgba.shape[:2] != shape:
            raise InputError(f"layer {i}: expected size {shape} like layer 0, got {rgba.shape[:2]}")
        if not np.isfinite(rgba).all():
            raise InputError(f"layer {i}: RGBA contains NaN/Inf")
        if (lyr.disparity is None) == (lyr.plane is None):
            raise InputError(f"layer {i}: give exactly one of a disparity map or a plane (a, b, c)")
        if lyr.disparity is not None:
            d = np.asarray(lyr.disparity)
            if d.shape != shape:
                raise InputError(f"layer {i}: disparity shape {d.shape} differs from the texture's {shape}")
            if not np.isfinite(d).all():
                raise InputError(f"layer {i}: disparity contains NaN/Inf")
        elif not all(math.isfinite(float(v)) for v in lyr.plane):
            raise InputError(f"layer {i}: plane coefficients must be finite, got {lyr.plane}")
    return shape


def _layer_disparity_at_pixels(lyr: Layer, h: int, w: int) -> np.ndarray:
    if lyr.disparity is not None:
        return np.asarray(lyr.disparity, np.float32)
    a, b, c = lyr.plane
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32) + 0.5
    return (a * xx + b * yy + c).astype(np.float32)


def _visible_coc(coc: np.ndarray, content: np.ndarray, tile: int = 16) -> np.ndarray:
    """A layer's CoC where its content can reach (tiles with content, dilated by the CoC), else 0.

    A layer whose disparity is defined everywhere but whose alpha is zero far
    from a pixel cannot send that pixel any light: it must not inflate the
    pixel's ray count.
    """
    h, w = coc.shape
    reach = _dilate(_box_max_tiles(content, tile), int(np.ceil(float(coc.max()) / tile)) + 1)
    mask = np.repeat(np.repeat(reach, tile, 0), tile, 1)[:h, :w]
    return np.where(mask, coc, 0.0).astype(np.float32)


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
        progress: called as ``progress(done, total)`` (units of work) between bands of rows;
            an exception it raises (or Ctrl-C) stops the trace within one band.

    Returns:
        ``(H x W x 4, stats)``: premultiplied RGB and the coverage (1 minus the
        transmittance left after the last layer), both averaged over the rays.
    """
    t0 = time.perf_counter()
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
    return _trace(rgba, disp, planes, blur, aperture or Aperture(), options or RaytraceOptions(), device, t0,
                  progress=progress)


def _trace(
    rgba: np.ndarray,
    disp: np.ndarray,
    planes: np.ndarray,
    blur: BlurParams,
    aperture: Aperture,
    options: RaytraceOptions,
    device: str,
    t0: float,
    *,
    ranges: np.ndarray | None = None,
    r_px: np.ndarray | None = None,
    core: tuple[int, int, int, int] | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> tuple[np.ndarray, RaytraceStats]:
    """Launch the kernel on packed layers: ``rgba`` (n, H, W, 4) premultiplied, ``disp`` (n, H, W) the
    disparity of every layer at every pixel, ``planes`` (n, 4) ``(a, b, c, 1)`` for plane layers, else 0.

    A tile of a larger render passes what depends on the whole image: each layer's disparity
    range (``ranges``, n x 2), the visible CoC of the traced pixels (``r_px``), the traced
    pixels ``core`` = (y0, y1, x0, x1) inside the textures. Returns the traced pixels only.
    ``progress(done, total)`` is called between bands of rows (``bokehray.raytrace_launch``).
    """
    from .raytrace_launch import choose_levels, summed_area, trace_bands  # noqa: PLC0415

    n, h, w = disp.shape
    core = (0, h, 0, w) if core is None else core
    if ranges is None:
        ranges = np.stack([disp.min(axis=(1, 2)), disp.max(axis=(1, 2))], axis=1).astype(np.float32)
    if r_px is None:
        r_px = np.zeros((h, w), np.float32)
        for i in range(n):
            np.maximum(r_px, _visible_coc(blur.coc_radius(disp[i]), rgba[i, ..., 3] > 0), out=r_px)
        r_px = r_px[core[0] : core[1], core[2] : core[3]]
    levels, table, _ = choose_levels(r_px, aperture, options.samples_per_px2, options.strip_range(),
                                           options.max_spp)
    sat = summed_area(rgba)
    t1 = time.perf_counter()
    result = trace_bands(sat, disp, planes, ranges, float(blur.k_px), float(blur.focus_disparity), table, levels,
                         (core[0], core[2]), device, progress=progress)
    rays = table.count(levels)
    stats = RaytraceStats(layers=n, samples_total=int(rays.sum()), spp_mean=float(rays.mean()), spp_max=int(rays.max()),
                          partitions=[[int(g), float(ol)] for g, ol in table.parts])
    stats.stage_seconds = {"setup": t1 - t0, "trace": time.perf_counter() - t1, "total": time.perf_counter() - t0}
    return result, stats


def _photo_textures(plans: list, image: np.ndarray, s: np.ndarray, sid: np.ndarray, blur: BlurParams,
                    device: str) -> tuple[np.ndarray, np.ndarray]:
    """The map layers of photo mode on the given arrays (the whole image, or a tile's window), nearest first:
    premultiplied RGB and coverage (n, H, W, 4), and disparity (n, H, W)."""
    h, w = s.shape
    img_wp = wp.array(np.ascontiguousarray(image[..., :3], np.float32), dtype=wp.vec3, device=device)
    s_wp = wp.array(np.ascontiguousarray(s, np.float32), dtype=float, device=device)
    sid_wp = wp.array(np.ascontiguousarray(sid), dtype=wp.int32, device=device)
    n = len(plans)
    rgba = np.empty((n, h, w, 4), np.float32)
    disp = np.empty((n, h, w), np.float32)
    filled = wp.zeros(max(plan.index for plan in plans) + 1, dtype=wp.int32, device=device)
    for i, plan in enumerate(reversed(plans)):  # nearest first
        full = dataclasses.replace(plan, bbox=(0, h, 0, w))
        src, coc = _layer_sources(full, img_wp, s_wp, sid_wp, filled, device)
        rgba[i] = src.numpy()  # premultiplied RGB and coverage already: what the kernel takes
        # the layer's own CoC where it has content, its mid-range elsewhere (transparent: never hit)
        coc_np = np.where(rgba[i, ..., 3] > 0, np.clip(coc.numpy(), plan.s_lo, plan.s_hi), 0.5 * (plan.s_lo + plan.s_hi))
        disp[i] = np.clip(coc_np / blur.k_px + blur.focus_disparity, 0.0, 1.0)
    np.clip(rgba[..., 3], 0.0, 1.0, out=rgba[..., 3])
    return rgba, disp


def render_raytrace(
    image: np.ndarray,
    disparity: np.ndarray,
    blur: BlurParams,
    aperture: Aperture,
    *,
    preview_options: PreviewOptions | None = None,
    options: RaytraceOptions | None = None,
    device: str = "cpu",
    progress: Callable[[int, int], None] | None = None,
) -> tuple[np.ndarray, RaytraceStats]:
    """Photo mode: build layers from one RGB image and its disparity, then ray trace them.

    The layers are the preview's (the same depth slices, hidden regions filled
    by pull-push at the layer's density); each becomes a map layer whose
    disparity is its pixels' own where it has content. Rays that end on no
    opaque layer are renormalised by the coverage they found, as in the preview.
    Large renders go tile by tile (``bokehray._tiling``), with the same result.
    """
    from . import _tiling  # noqa: PLC0415 - _tiling imports bokehray._scatter

    preview_options = preview_options or PreviewOptions()
    options = options or RaytraceOptions()
    h, w = disparity.shape
    if blur.k_px == 0.0:  # a pinhole: the input itself
        return image[..., :3].copy(), RaytraceStats(stage_seconds={"total": 0.0})
    _tiling.check_whole_image(h, w, _tiling.RAYTRACE_WHOLE_IMAGE_B, preview_options)
    peak = float(np.abs(image[..., :3]).max())
    if peak > MAX_RADIANCE:
        raise InputError(f"image: radiance up to {peak:.3g}; the ray tracer averages rays in float32 and needs "
                         f"values within +-{MAX_RADIANCE:g} (the preview takes them)")
    s = cap_coc(blur.signed_coc(disparity))  # the layers' disparity below is s / K + d_f: capped alike
    sid, plans = plan_layers(s, np.ones((h, w), bool), preview_options)
    max_coc = float(np.abs(s).max())
    tile, need = _tiling.raytrace_tile_size(h, w, plans, max_coc, preview_options)  # may raise ResourceError
    t0 = time.perf_counter()
    if tile is None:
        rgba, disp = _photo_textures(plans, image, s, sid, blur, device)
        t_layers = time.perf_counter()
        out, stats = _trace(rgba, disp, np.zeros((len(plans), 4), np.float32), blur, aperture, options, device,
                            t_layers, progress=progress)
        stats.stage_seconds = {"layers": t_layers - t0, **stats.stage_seconds,
                               "total": stats.stage_seconds["total"] + t_layers - t0}
        del rgba, disp
    else:
        out, stats = _trace_tiles(image, s, sid, plans, blur, aperture, options, device, max_coc,
                                  -(-tile // 16) * 16, t0, progress)
    stats.memory_estimate_mb = need / _tiling.MB
    cov = out[..., 3:4]
    rgb = np.where(cov > 1e-4, out[..., :3] / np.maximum(cov, 1e-12), image[..., :3])
    return rgb.astype(np.float32), stats


def _trace_tiles(image: np.ndarray, s: np.ndarray, sid: np.ndarray, plans: list, blur: BlurParams,
                 aperture: Aperture, options: RaytraceOptions, device: str, max_coc: float, tile: int,
                 t0: float, progress: Callable[[int, int], None] | None = None) -> tuple[np.ndarray, RaytraceStats]:
    """Photo mode tile by tile, equal to the untiled trace.

    Pass 1 builds each tile's layers on its window and gathers what the
    untiled trace takes from whole layers: their disparity ranges (the march
    bounds), their largest CoC and their content tiles (the ray counts).
    Pass 2 builds them again and traces each tile's core.
    """
    from . import _tiling  # noqa: PLC0415

    h, w = s.shape
    n, grid = len(plans), 16
    halo, align = _tiling.raytrace_halo(plans, max_coc)
    cores = _tiling.cores(h, w, tile)
    ranges = np.tile(np.array([[np.inf, -np.inf]], np.float32), (n, 1))
    coc_max = np.zeros(n, np.float32)
    content = np.zeros((n, -(-h // grid), -(-w // grid)), bool)

    def window_layers(core):
        wy0, wy1, wx0, wx1 = _tiling.raytrace_window(h, w, core, halo, align)
        rgba, disp = _photo_textures(plans, image[wy0:wy1, wx0:wx1], s[wy0:wy1, wx0:wx1], sid[wy0:wy1, wx0:wx1],
                                     blur, device)
        cy0, cy1, cx0, cx1 = core
        return (wy0, wx0), (cy0 - wy0, cy1 - wy0, cx0 - wx0, cx1 - wx0), rgba, disp

    for core in cores:
        _, (y0, y1, x0, x1), rgba, disp = window_layers(core)
        d = disp[:, y0:y1, x0:x1]
        np.minimum(ranges[:, 0], d.min(axis=(1, 2)), out=ranges[:, 0])
        np.maximum(ranges[:, 1], d.max(axis=(1, 2)), out=ranges[:, 1])
        for i in range(n):
            coc_max[i] = max(coc_max[i], float(blur.coc_radius(d[i]).max()))
            ty, tx = core[0] // grid, core[2] // grid
            t = _box_max_tiles(rgba[i, y0:y1, x0:x1, 3] > 0, grid)
            content[i, ty : ty + t.shape[0], tx : tx + t.shape[1]] |= t
    reach = [_dilate(content[i], int(np.ceil(float(coc_max[i]) / grid)) + 1) for i in range(n)]

    out = np.empty((h, w, 4), np.float32)
    stats = RaytraceStats(layers=n)
    traced = 0.0
    for k, core in enumerate(cores):
        _, (y0, y1, x0, x1), rgba, disp = window_layers(core)
        cy0, cy1, cx0, cx1 = core
        r_px = np.zeros((cy1 - cy0, cx1 - cx0), np.float32)
        for i in range(n):
            sub = reach[i][cy0 // grid : -(-cy1 // grid), cx0 // grid : -(-cx1 // grid)]  # cores start on the grid
            mask = np.repeat(np.repeat(sub, grid, 0), grid, 1)[: cy1 - cy0, : cx1 - cx0]
            np.maximum(r_px, np.where(mask, blur.coc_radius(disp[i, y0:y1, x0:x1]), 0.0).astype(np.float32), out=r_px)
        tile_progress = None if progress is None else (
            lambda done, total, k=k: progress(k * 1000 + int(1000 * done / max(total, 1)), 1000 * len(cores)))
        part, st = _trace(rgba, disp, np.zeros((n, 4), np.float32), blur, aperture, options, device,
                          time.perf_counter(), ranges=ranges, r_px=r_px, core=(y0, y1, x0, x1),
                          progress=tile_progress)
        out[cy0:cy1, cx0:cx1] = part
        stats.samples_total += st.samples_total
        stats.spp_max = max(stats.spp_max, st.spp_max)
        traced += st.stage_seconds["total"]
        stats.partitions += [p for p in st.partitions if p not in stats.partitions]
    stats.spp_mean = stats.samples_total / float(h * w)
    stats.image_tiles = len(cores)
    total = time.perf_counter() - t0
    stats.stage_seconds = {"layers (both passes)": total - traced, "trace": traced, "total": total}
    return out, stats
