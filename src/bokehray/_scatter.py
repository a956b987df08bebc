"""Launcher of the preview renderer: layered, occlusion-aware scatter (docs/renderer.md).

Pipeline (all heavy work in ``bokehray_kernels``):

0. The frame is extended by its edge pixels (colour and signed CoC) as far as its
   border's CoC reaches (``border_pad``: the clamped border), rendered, and cropped.
1. Signed CoC ``s = K (d - d_f)`` per pixel. Tiles whose pixels, and every pixel
   within CoC reach of them, have ``|s| < 0.5`` are *copied*: never scattered,
   never composited.
2. The rest is cut into layers by ``s`` (``layer_edges``: an in-focus layer,
   cuts in the depth gaps, wide runs split); layer ids grow towards the camera.
3. Each layer, independently (one worker thread per CPU core): its pixels
   become sources ``(RGB, 1)``; where a nearer layer hides it, within the CoC
   reach of the nearer layers, it is extended by pull-push filling; all
   sources are scattered with their own exact radius on the radius pyramid,
   the light of the salient ones (``route_salient``) at full resolution.
4. Layers are composited back to front with "over" (opacity = scattered
   coverage clipped to 1, colour normalised by coverage), and the result is
   divided by the total opacity.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np
import warp as wp

import bokehray_kernels as bk

from .errors import InputError
from .lens import Aperture

__all__ = ["PreviewOptions", "RenderStats", "render_preview"]


@dataclass(frozen=True, slots=True)
class PreviewOptions:
    """Knobs of the preview renderer (defaults are what the benchmarks measure).

    Args:
        max_layers: most depth layers; more resolves more occlusion, costs more.
        max_layer_px: widest layer (in CoC pixels) on a gap-free depth range.
        min_layer_px: a CoC range narrower than this is one layer.
        level_radius_px: largest radius scattered at a pyramid level before moving
            to the next coarser one (cost per source is O(level_radius_px)).
        tile_px: side of the tiles used to skip in-focus regions.
        fill: extend layers behind nearer ones by pull-push (see bokehray_kernels.fill).
        threads: worker threads on the CPU (default: all cores).
        tile_size: render in independent square tiles of this many pixels a side
            (each with a halo that makes the result equal the untiled render, see
            ``bokehray._tiling``); None (default) tiles only when the untiled
            render would not fit the memory budget.
        memory_limit_mb: memory budget of one render in MB; None (default) is 80 %
            of the memory available when the render starts. A render that cannot
            fit even in tiles raises :class:`~bokehray.errors.ResourceError` before
            allocating anything large.
        exact_highlights: scatter the sources whose own disc outline is visible (lights,
            highlights; ``route_salient``) at full resolution instead of on the radius
            pyramid (the default); False is the faster, approximate mode (``--quality fast``).
        clamp_border: take the unknown outside the frame as its edge pixels continued
            outwards (``border_pad``, the default); False divides by the coverage the
            frame got instead (the rule before, which brightens lights near the border).
    """

    max_layers: int = 8
    max_layer_px: float = 8.0
    min_layer_px: float = 1.0
    level_radius_px: float = 8.0
    tile_px: int = 16
    fill: bool = True
    threads: int | None = None
    tile_size: int | None = None
    memory_limit_mb: float | None = None
    exact_highlights: bool = True
    clamp_border: bool = True

    def __post_init__(self) -> None:
        for name in ("max_layers", "tile_px"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
                raise InputError(f"{name}: expected an integer >= 1, got {v!r}")
        for name in ("max_layer_px", "min_layer_px", "level_radius_px"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float, np.floating)) and math.isfinite(v) and v > 0):
                raise InputError(f"{name}: expected a finite number > 0, got {v!r}")
        if self.level_radius_px < 2.0:
            raise InputError(f"level_radius_px: expected >= 2 px (smaller coarsens every blur), got {self.level_radius_px}")
        if self.threads is not None and (not isinstance(self.threads, int) or self.threads < 1):
            raise InputError(f"threads: expected None (all cores) or an integer >= 1, got {self.threads!r}")
        t = self.tile_size
        if t is not None and (isinstance(t, bool) or not isinstance(t, (int, np.integer)) or t < self.tile_px):
            raise InputError(f"tile_size: expected None (automatic) or an integer >= tile_px ({self.tile_px}), got {t!r}")
        m = self.memory_limit_mb
        if m is not None and not (isinstance(m, (int, float, np.floating)) and not isinstance(m, bool)
                                  and math.isfinite(m) and m > 0):
            raise InputError(f"memory_limit_mb: expected None (automatic) or a finite number > 0, got {m!r}")


@dataclass(slots=True)
class RenderStats:
    """What a render did and skipped. Times in seconds.

    ``image_tiles`` > 1: the render went tile by tile (bokehray._tiling); ``sources_filled``
    then counts the fill of each tile's halo again. ``memory_estimate_mb``: the estimated
    peak that chose between tiled and untiled.
    """

    shape: tuple[int, int] = (0, 0)
    device: str = "cpu"
    max_coc_px: float = 0.0
    tiles_total: int = 0
    tiles_copied: int = 0
    layers: int = 0
    sources_scattered: int = 0
    sources_filled: int = 0
    pyramid_levels: int = 0
    threads: int = 1
    image_tiles: int = 1
    memory_estimate_mb: float = 0.0
    stage_seconds: dict[str, float] = field(default_factory=dict)
    refine: dict | None = None  #: what ``refine=`` did (tiles refined, share, seconds), None without it

    def as_dict(self) -> dict:
        return {
            "shape": list(self.shape),
            "device": self.device,
            "max_coc_px": round(self.max_coc_px, 3),
            "tiles_total": self.tiles_total,
            "tiles_copied": self.tiles_copied,
            "layers": self.layers,
            "sources_scattered": self.sources_scattered,
            "sources_filled": self.sources_filled,
            "pyramid_levels": self.pyramid_levels,
            "threads": self.threads,
            "image_tiles": self.image_tiles,
            "memory_estimate_mb": round(self.memory_estimate_mb, 1),
            "stage_seconds": {k: round(v, 4) for k, v in self.stage_seconds.items()},
            "refine": self.refine,
        }


def cap_coc(signed_coc: np.ndarray) -> np.ndarray:
    """Compress CoC radii beyond twice the image diagonal (order kept): their light covers the frame uniformly.

    Every aperture (a triangle at worst) contains the disc of half its circumradius, so a
    source whose radius exceeds twice the diagonal lights every pixel of the frame equally:
    a larger radius only spreads less of its light inside the frame. Without the cap a CoC
    far beyond the image (K = 1e5 on a small image) leaves each pixel a coverage below the
    float32 noise floor of the compositing (1e-4), and the render would fall back to the
    unblurred input; the ray tracer's march would take O(K) steps per ray. Beyond the cap
    ``c`` a radius ``r`` becomes ``c + log1p(r - c)`` (still ordered, so layers keep their
    depth order; not idempotent, so the entry points apply it once). Renders whose CoC stays
    within the cap are unchanged.
    """
    h, w = signed_coc.shape
    cap = np.float32(2.0 * math.hypot(h, w) + 2.0)
    if signed_coc.size == 0 or max(float(signed_coc.max()), -float(signed_coc.min())) <= cap:
        return signed_coc  # the normal case: no copy
    r = np.abs(signed_coc)
    big = r > cap
    out = signed_coc.copy()
    out[big] = np.sign(signed_coc[big]) * (cap + np.log1p(r[big] - cap))
    return out.astype(np.float32)


def _box_max_tiles(values: np.ndarray, tile: int) -> np.ndarray:
    h, w = values.shape
    th, tw = -(-h // tile), -(-w // tile)
    pad = np.zeros((th * tile, tw * tile), values.dtype)
    pad[:h, :w] = values
    return pad.reshape(th, tile, tw, tile).max(axis=(1, 3))


def _dilate(mask: np.ndarray, k: int) -> np.ndarray:
    """Binary dilation of a small 2-D mask by a (2k+1)^2 square, via 2-D prefix sums."""
    if k <= 0:
        return mask.copy()
    h, w = mask.shape
    c = np.zeros((h + 1, w + 1), np.int32)
    c[1:, 1:] = np.cumsum(np.cumsum(mask.astype(np.int32), 0), 1)
    y0 = np.clip(np.arange(h) - k, 0, h)
    y1 = np.clip(np.arange(h) + k + 1, 0, h)
    x0 = np.clip(np.arange(w) - k, 0, w)
    x1 = np.clip(np.arange(w) + k + 1, 0, w)
    s = c[y1][:, x1] - c[y0][:, x1] - c[y1][:, x0] + c[y0][:, x0]
    return s > 0


def copy_tiles(radius: np.ndarray, tile: int) -> np.ndarray:
    """Boolean tile grid: True where the tile can be copied from the input.

    A tile is copied when no pixel whose CoC reaches into it has a radius of
    half a pixel or more (its own pixels included).
    """
    tmax = _box_max_tiles(radius, tile)
    blurred = tmax >= 0.5
    needed = np.zeros_like(blurred)
    if blurred.any():
        reach = np.ceil((tmax + 1.0) / tile).astype(np.int64)
        for k in np.unique(reach[blurred]):
            needed |= _dilate(blurred & (reach == k), int(k))
    return ~needed


def layer_edges(signed_coc: np.ndarray, options: PreviewOptions) -> np.ndarray:
    """Edges (ascending, in CoC px) of the depth layers for the given signed CoC values.

    Layers exist to resolve occlusion; on a continuous surface every layer edge
    is a seam (two one-sided blurs composited instead of one). So edges go
    (1) around the focus, ``s = -0.5`` and ``s = +0.5``: the in-focus layer is
    its own, so nothing blurred behind it can halo over it;
    (2) into the gaps of the CoC histogram, where the depth jumps; and
    (3) where a gap-free run is still wider than ``max_layer_px``, at even
    spacing, so an in-focus subject and a far background on one continuous
    range still get separate layers (no halo). At most ``max_layers`` layers:
    the narrowest gaps are dropped first, and what the budget leaves for (3) is
    shared between the wide runs in proportion to their width.
    """
    signed_coc = np.asarray(signed_coc, np.float32).ravel()
    lo, hi = float(signed_coc.min()), float(signed_coc.max())
    if hi - lo < options.min_layer_px:
        return np.array([lo - 0.5, hi + 0.5])
    bin_px = 0.25
    n_bins = int(math.ceil((hi - lo) / bin_px)) + 1
    hist = np.bincount(((signed_coc - lo) / bin_px).astype(np.int64), minlength=n_bins)
    empty = hist == 0
    # runs of empty bins: candidate cuts at their centres, ranked by width
    change = np.flatnonzero(np.diff(np.concatenate([[0], empty.astype(np.int8), [0]])))
    runs = change.reshape(-1, 2)
    gaps = [(lo + bin_px * (a + b) / 2.0, (b - a) * bin_px) for a, b in runs]
    gaps.sort(key=lambda g: -g[1])
    ranked = [c for c in (-0.5, 0.5) if lo < c < hi] + [pos for pos, _ in gaps]  # focus cuts first
    cuts = set(ranked[: max(0, options.max_layers - 1)])
    edges = np.array(sorted({lo - 0.5, hi + 0.5} | cuts))
    # split the runs that are still too wide, sharing what is left of the layer budget
    # between them in proportion to their width (the focus and gap cuts always stay)
    widths = np.diff(edges)
    want = np.maximum(1, np.ceil(widths / options.max_layer_px)).astype(int)
    spare = options.max_layers - len(widths)
    if want.sum() - len(widths) > spare:
        extra = want - 1
        share = np.floor(extra * max(spare, 0) / max(extra.sum(), 1)).astype(int)
        want = 1 + share
    out = [edges[0]]
    for a, b, n in zip(edges[:-1], edges[1:], want):
        out.extend(a + (b - a) * np.arange(1, n + 1) / n)
    edges = np.array(out)
    return edges


@dataclass(slots=True)
class _Layer:
    index: int
    s_lo: float
    s_hi: float
    bbox: tuple[int, int, int, int]  # y0, y1, x0, x1
    max_radius: float
    fill_reach: float


def plan_layers(signed_coc: np.ndarray, active: np.ndarray, options: PreviewOptions) -> tuple[np.ndarray, list[_Layer]]:
    """Cut the active pixels into depth layers: per-pixel layer ids (-1 = inactive) and the layer records.

    Each record holds the layer's CoC range, its bounding box (its tiles, padded
    by its largest CoC and, when filled, by the fill's reach) and the reach of
    everything nearer (how far behind it a nearer blur can reveal).
    """
    h, w = signed_coc.shape
    max_coc = float(np.abs(signed_coc[active]).max())
    edges = layer_edges(signed_coc[active], options)
    sid = (np.searchsorted(edges, signed_coc, side="right") - 1).astype(np.int32)
    np.clip(sid, 0, len(edges) - 2, out=sid)
    sid[~active] = -1
    n_slices = len(edges) - 1

    # Per-layer extents on the tile grid (host side, on small arrays): a layer's
    # bounding box is the union of the tiles holding any of its pixels.
    t = options.tile_px
    th, tw = -(-h // t), -(-w // t)
    pad_h, pad_w = th * t - h, tw * t - w
    sid_t = np.pad(sid, ((0, pad_h), (0, pad_w)), constant_values=-1).reshape(th, t, tw, t)
    tile_lo = np.where(sid_t < 0, n_slices, sid_t).min(axis=(1, 3))
    tile_hi = sid_t.max(axis=(1, 3))
    counts = np.bincount(sid[active], minlength=n_slices)
    present = counts > 0
    # CoC reach of everything nearer than each layer: suffix maximum of the layers' radius bounds
    max_r_slice = np.minimum(np.maximum(np.abs(edges[:-1]), np.abs(edges[1:])), max_coc)
    nearer_reach = np.zeros(n_slices)
    run = 0.0
    for i in range(n_slices - 1, -1, -1):
        nearer_reach[i] = run
        if present[i]:
            run = max(run, max_r_slice[i])
    layers: list[_Layer] = []
    for i in np.flatnonzero(present):
        ty, tx = np.nonzero((tile_lo <= i) & (tile_hi >= i))
        lo, hi = float(edges[i]), float(edges[i + 1])
        reach = nearer_reach[i] if options.fill else 0.0
        pad_fill = int(math.ceil(1.4142 * reach)) + 2 if reach >= 0.5 else 0
        # a level-l scatter spreads up to 2^l px beyond the radius (coarse pixels, bilinear upsampling)
        coarse = 2 << (_levels_for(float(max_r_slice[i]), options.level_radius_px) - 1)
        pad = pad_fill + int(math.ceil(max_r_slice[i])) + 2 + coarse
        bbox = (max(0, ty.min() * t - pad), min(h, (ty.max() + 1) * t + pad),
                max(0, tx.min() * t - pad), min(w, (tx.max() + 1) * t + pad))
        layers.append(_Layer(int(i), lo, hi, bbox, float(max_r_slice[i]), float(reach)))
    return sid, layers


def _pull_levels(fill_reach: float) -> int:
    """Levels of the pull-push pyramid that fills a layer hidden up to ``fill_reach`` px deep."""
    return max(1, min(16, int(math.ceil(math.log2(1.4142 * fill_reach + 2.0))) + 1))


def _levels_for(max_radius: float, r0: float) -> int:
    n = 1
    while max_radius > r0 * (1 << (n - 1)) and n < bk.MAX_LEVELS:
        n += 1
    return n


def aperture_area(aperture: Aperture) -> float:
    """Area of the aperture at unit circumradius (the scatter's normalisation, docs/renderer.md).

    A disc is pi; N straight blades the inscribed regular polygon; curved blades add on each
    side the circular segment of radius 1 / curvature through the two vertices (that arc lies
    inside the unit circle, so the CoC disc does not clip it).
    """
    if aperture.is_disc:
        return math.pi
    n = aperture.blades
    poly = 0.5 * n * math.sin(2.0 * math.pi / n)
    if aperture.curvature < 1e-4:  # as Aperture.blade_discs: straight
        return poly
    big_r = 1.0 / aperture.curvature
    theta = 2.0 * math.asin(math.sin(math.pi / n) / big_r)
    return poly + n * 0.5 * big_r * big_r * (theta - math.sin(theta))


def _layer_sources(
    layer: _Layer, image: wp.array, signed_coc: wp.array, slice_id: wp.array, filled: wp.array, device: str
) -> tuple[wp.array, wp.array]:
    """One layer's sources on its bounding box: (premultiplied RGB, coverage) and signed CoC.

    The layer's own pixels, plus (when ``layer.fill_reach >= 0.5``) the pull-push
    fill of the region nearer layers hide, at the layer's density; the number of
    filled sources is added to ``filled[layer.index]`` (read once per render).
    """
    y0, y1, x0, x1 = layer.bbox
    h, w = y1 - y0, x1 - x0
    src = wp.empty((h, w), dtype=wp.vec4, device=device)
    coc = wp.empty((h, w), dtype=float, device=device)
    fill = layer.fill_reach >= 0.5
    pp_shape = (h, w) if fill else (1, 1)  # the pull-push pyramid, only when this layer is filled
    totals = [wp.empty(pp_shape, dtype=wp.vec4, device=device)]
    weights = [wp.empty(pp_shape, dtype=float, device=device)]
    knowns = [wp.empty(pp_shape, dtype=float, device=device)]
    wp.launch(
        bk.layer_sources_kernel,
        dim=(h, w),
        inputs=[image, signed_coc, slice_id, layer.index, x0, y0, int(fill)],
        outputs=[src, coc, totals[0], weights[0], knowns[0]],
        device=device,
    )
    if fill:
        for _ in range(_pull_levels(layer.fill_reach)):
            ph, pw = totals[-1].shape
            ch, cw = (ph + 1) // 2, (pw + 1) // 2
            totals.append(wp.empty((ch, cw), dtype=wp.vec4, device=device))
            weights.append(wp.empty((ch, cw), dtype=float, device=device))
            knowns.append(wp.empty((ch, cw), dtype=float, device=device))
            wp.launch(bk.pull_kernel, dim=(ch, cw), inputs=[totals[-2], weights[-2], knowns[-2]],
                      outputs=[totals[-1], weights[-1], knowns[-1]], device=device)
        top = len(totals) - 1
        for lv in range(top, -1, -1):
            c = min(lv + 1, top)  # the top level has no coarser level (flag 1): it passes itself
            wp.launch(bk.push_kernel, dim=totals[lv].shape,
                      inputs=[totals[c], weights[c], knowns[c], int(lv == top)],
                      outputs=[totals[lv], weights[lv], knowns[lv]], device=device)
        dist = wp.empty((h, w), dtype=float, device=device)
        wp.launch(bk.row_distance_kernel, dim=h, inputs=[slice_id, layer.index, x0, y0, w], outputs=[dist],
                  device=device)
        band = 1 if wp.get_device(device).is_cuda else 64
        wp.launch(bk.column_distance_kernel, dim=(w + band - 1) // band, inputs=[dist, h, band], device=device)
        wp.launch(
            bk.fill_sources_kernel,
            dim=(h, w),
            inputs=[slice_id, layer.index, x0, y0, totals[0], weights[0], dist, signed_coc, layer.s_lo, layer.s_hi],
            outputs=[src, coc, filled],
            device=device,
        )
    return src, coc


SALIENT_VISIBLE = 0.002
"""A source's disc outline counts as visible when its plateau exceeds 1 % of its surroundings."""
SALIENT_FLOOR = 1e-6
"""Darkest surroundings (linear radiance) the visibility test compares with: on black every light shows."""


def route_salient(src: wp.array, coc: wp.array, n_levels: int, r0: float, device: str) -> wp.array:
    """Flags (uint8, the sources' shape) of the pyramid-level sources to scatter at level 0 instead.

    A source on pyramid level ``l`` gets its outline blurred by about ``2^l`` px. That is
    invisible where many similar discs overlap (smooth content), not where one source stands
    out: ``bk.salience_kernel`` scores each source's excess radiance over its coverage of the
    layer's local colour (the 3 x 3 level-``l`` cells of a radiance pyramid around it) against ``SALIENT_VISIBLE * pi r^2 *
    max(mean, SALIENT_FLOOR)``; ``bk.route_cells_kernel`` then keeps, in each level-``l`` cell,
    the ``max(1, 2^(l-1))`` best-scored of them, so the level-0 work stays below half of the
    pyramid work whatever the radius (flat cost in R). Every decision depends only on
    pyramid-aligned cells of the layer's box, so tiled renders route the same sources.
    """
    h, w = src.shape
    exact = wp.zeros((h, w), dtype=wp.uint8, device=device)
    n_means = n_levels - 1  # radiance pyramid levels 1 .. n_levels - 1
    h1, w1 = (h + 1) // 2, (w + 1) // 2
    means = wp.zeros((n_means, h1, w1), dtype=wp.vec2, device=device)
    counts = wp.zeros((n_means, h1, w1), dtype=float, device=device)
    wp.launch(bk.radiance_mean_kernel, dim=(h1, w1), inputs=[src], outputs=[means, counts], device=device)
    fh, fw = h1, w1
    for k in range(1, n_means):
        ch, cw = (fh + 1) // 2, (fw + 1) // 2
        wp.launch(bk.halve_mean_kernel, dim=(ch, cw), inputs=[means, counts, k, fh, fw], device=device)
        fh, fw = ch, cw
    score = wp.empty((h, w), dtype=float, device=device)
    wp.launch(bk.salience_kernel, dim=(h, w),
              inputs=[src, coc, means, counts, float(r0), n_levels, SALIENT_VISIBLE, SALIENT_FLOOR], outputs=[score],
              device=device)
    for lev in range(1, n_levels):
        side = 1 << lev
        wp.launch(bk.route_cells_kernel, dim=((h + side - 1) // side, (w + side - 1) // side),
                  inputs=[score, coc, float(r0), n_levels, lev, max(1, side // 2)], outputs=[exact], device=device)
    return exact


def _render_layer(
    layer: _Layer,
    image: wp.array,
    signed_coc: wp.array,
    slice_id: wp.array,
    filled: wp.array,
    blades: wp.array,
    n_blades: int,
    extent: wp.vec2,
    area: float,
    opts: PreviewOptions,
    device: str,
) -> wp.array:
    y0, y1, x0, x1 = layer.bbox
    h, w = y1 - y0, x1 - x0
    src, coc = _layer_sources(layer, image, signed_coc, slice_id, filled, device)
    n_levels = _levels_for(layer.max_radius, opts.level_radius_px)
    bufs = []
    for lv in range(bk.MAX_LEVELS):
        if lv < n_levels:
            shape = ((h + (1 << lv) - 1) >> lv, ((w + (1 << lv) - 1) >> lv) + 2)
            bufs.append(wp.zeros(shape, dtype=wp.vec4, device=device))
        else:
            bufs.append(bufs[0] if lv > 0 else None)
    if opts.exact_highlights and n_levels > 1:
        exact = route_salient(src, coc, n_levels, opts.level_radius_px, device)
    else:
        exact = wp.zeros((1, 1), dtype=wp.uint8, device=device)
    wp.launch(bk.scatter_kernel, dim=(h, w),
              inputs=[src, coc, exact, blades, n_blades, extent, area, float(opts.level_radius_px), n_levels, *bufs], device=device)
    for lv in range(n_levels):
        wp.launch(bk.prefix_rows_kernel, dim=bufs[lv].shape[0], inputs=[bufs[lv]], device=device)
    out = src  # the sources are scattered: reuse their memory for the result
    wp.launch(bk.resolve_levels_kernel, dim=(h, w), inputs=[n_levels, *bufs], outputs=[out], device=device)
    return out


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
    limit = 0.5 * max(signed_coc.shape)
    rims = (signed_coc[0, :], signed_coc[-1, :], signed_coc[:, 0], signed_coc[:, -1])
    radii = [float(np.abs(rim).max()) for rim in rims]
    if max(radii) > limit:
        return 0, 0, 0, 0
    return tuple(-(-(int(math.ceil(r)) + 1) // tile_px) * tile_px if r >= 0.5 else 0 for r in radii)


def render_preview(
    image: np.ndarray,
    signed_coc: np.ndarray,
    aperture: Aperture,
    *,
    options: PreviewOptions = PreviewOptions(),
    device: str = "cpu",
    progress: Callable[[int, int], None] | None = None,
) -> tuple[np.ndarray, RenderStats]:
    """Render an RGB float32 image (validated by the caller) with a per-pixel signed CoC map."""
    from . import _tiling  # noqa: PLC0415 - _tiling imports this module

    t_start = time.perf_counter()
    stats = RenderStats(shape=image.shape[:2], device=device)
    stats.max_coc_px = max(float(signed_coc.max()), -float(signed_coc.min())) if signed_coc.size else 0.0
    signed_coc = cap_coc(signed_coc)
    pt, pb, pl, pr = border_pad(signed_coc, options.tile_px) if options.clamp_border else (0, 0, 0, 0)
    h0, w0 = signed_coc.shape
    h, w = h0 + pt + pb, w0 + pl + pr
    _tiling.check_whole_image(h0, w0, _tiling.PREVIEW_WHOLE_IMAGE_B, options)  # before allocating anything large
    if (h, w) != (h0, w0) and _tiling.PREVIEW_WHOLE_IMAGE_B * h * w > _tiling.budget_bytes(options):
        (pt, pb, pl, pr), h, w = (0, 0, 0, 0), h0, w0  # the clamped border does not fit: the frame alone
    if (h, w) != (h0, w0):
        image = np.pad(image, ((pt, pb), (pl, pr), (0, 0)), mode="edge")
        signed_coc = np.pad(signed_coc, ((pt, pb), (pl, pr)), mode="edge")
    radius = np.abs(signed_coc)

    copy = copy_tiles(radius, options.tile_px)
    del radius
    t = options.tile_px  # the frame's tiles (the border pad is whole tiles)
    frame_tiles = copy[pt // t: pt // t + -(-h0 // t), pl // t: pl // t + -(-w0 // t)]
    stats.tiles_total, stats.tiles_copied = int(frame_tiles.size), int(frame_tiles.sum())
    copy_px = np.repeat(np.repeat(copy, options.tile_px, 0), options.tile_px, 1)[:h, :w]

    active = ~copy_px
    if not active.any():
        stats.stage_seconds["plan"] = time.perf_counter() - t_start
        stats.stage_seconds["total"] = stats.stage_seconds["plan"]
        return image[pt:pt + h0, pl:pl + w0].copy(), stats

    sid, layers = plan_layers(signed_coc, active, options)
    del active, copy_px
    stats.layers = len(layers)
    stats.sources_scattered = int((sid >= 0).sum())
    stats.pyramid_levels = max(_levels_for(lyr.max_radius, options.level_radius_px) for lyr in layers)
    threads = 1 if wp.get_device(device).is_cuda else max(1, options.threads or os.cpu_count() or 1)
    stats.threads = threads
    tile = _tiling.preview_tile_size(h, w, layers, options, threads, stats)  # may raise ResourceError
    t_plan = time.perf_counter()
    stats.stage_seconds["plan"] = t_plan - t_start

    if tile is None:
        out_np, n_filled = _render_region(image, signed_coc, sid, layers, aperture, options, device, threads, progress)
    else:
        out_np, n_filled = _tiling.render_preview_tiles(image, signed_coc, sid, layers, aperture, options, device,
                                                        threads, tile, progress, stats,
                                                        frame=(pt, pt + h0, pl, pl + w0))
    stats.sources_filled = n_filled
    stats.sources_scattered += n_filled
    stats.stage_seconds["layers"] = time.perf_counter() - t_plan
    stats.stage_seconds["total"] = time.perf_counter() - t_start
    return np.ascontiguousarray(out_np[pt:pt + h0, pl:pl + w0]), stats


def _render_region(
    image: np.ndarray,
    signed_coc: np.ndarray,
    sid: np.ndarray,
    layers: list[_Layer],
    aperture: Aperture,
    options: PreviewOptions,
    device: str,
    threads: int,
    progress: Callable[[int, int], None] | None = None,
) -> tuple[np.ndarray, int]:
    """Scatter and composite ``layers`` (bounding boxes in the coordinates of the given arrays), then finalise.

    Returns the rendered RGB and the number of filled sources.
    """
    h, w = signed_coc.shape
    img_wp = wp.array(np.ascontiguousarray(image, np.float32), dtype=wp.vec3, device=device)
    s_wp = wp.array(np.ascontiguousarray(signed_coc, np.float32), dtype=float, device=device)
    sid_wp = wp.array(np.ascontiguousarray(sid), dtype=wp.int32, device=device)
    blade_rows = aperture.blade_discs()
    blades = wp.array(blade_rows if len(blade_rows) else np.zeros((1, 4), np.float32), dtype=wp.vec4, device=device)
    extent = wp.vec2(*aperture.vertical_extent())
    area = aperture_area(aperture)
    acc = wp.zeros((h, w), dtype=wp.vec4, device=device)

    # Layers render independently (Warp CPU launches release the GIL); they are
    # composited strictly back to front as they complete, with at most
    # ``threads + 1`` layers in flight to bound memory.
    done = 0

    filled = wp.zeros(max(lyr.index for lyr in layers) + 1, dtype=wp.int32, device=device)

    def render_layer(lyr: _Layer) -> wp.array:
        return _render_layer(lyr, img_wp, s_wp, sid_wp, filled, blades, len(blade_rows), extent, area, options,
                             device)

    with ThreadPoolExecutor(max_workers=threads) as pool:
        pending: list[tuple[_Layer, Future]] = []
        it = iter(layers)

        def submit_next() -> None:
            lyr = next(it, None)
            if lyr is not None:
                pending.append((lyr, pool.submit(render_layer, lyr)))

        for _ in range(threads + 1):
            submit_next()
        while pending:
            lyr, fut = pending.pop(0)
            out = fut.result()
            submit_next()
            y0, y1, x0, x1 = lyr.bbox
            wp.launch(bk.composite_kernel, dim=(y1 - y0, x1 - x0), inputs=[out, x0, y0], outputs=[acc], device=device)
            done += 1
            if progress is not None:
                progress(done, len(layers))

    result = wp.empty((h, w), dtype=wp.vec3, device=device)
    wp.launch(bk.finalize_kernel, dim=(h, w), inputs=[acc, img_wp, sid_wp], outputs=[result], device=device)
    return result.numpy(), int(filled.numpy().sum())
