"""The public rendering pipeline: validate at the boundary, build the context, run the chosen level, refine.

``render_with_stats`` = check arguments -> expand grey / split alpha -> optional highlight boost -> the level
(``bokehray.levels``) on the colour -> optional refine -> the level again on alpha (RGBA inputs) -> output checks.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import replace
from numbers import Integral, Real

import numpy as np

from . import scene, tiling
from ._memory import bound_heap
from .errors import InputError, NumericalError
from .lens import Aperture, BlurParams
from .levels import LEVELS, RenderContext, get_level
from .levels.refine import REFINABLE, check_refine_options, refine_render
from .options import LayerOptions, MemoryOptions, PreviewOptions, RaytraceOptions
from .stats import Clock, RenderStats
from .validate import (
    MAX_RADIANCE,
    array_shape,
    check_disparity,
    check_image,
    check_number,
    check_radiance,
    check_type,
    first_bad_index,
)

__all__ = ["QUALITIES", "Handover", "boost_highlights", "focus_at", "render", "render_handed_over", "render_with_stats"]

QUALITIES = tuple(LEVELS)
"""Quality levels: docs/renderer.md (preview) and docs/raytracer.md (raytrace)."""

Progress = Callable[[int, int], None]

HELD_DURING_SPLIT_B = 24
"""Bytes a pixel of the frame held while the mixed pixels are split: the photo (12), its disparity and its signed CoC
(4 each), the snapped CoC (4)."""


def focus_at(disparity: np.ndarray, x: int, y: int, window: int = 9) -> float:
    """Focus disparity from a clicked pixel: the median disparity in a ``window`` x ``window`` box.

    The median ignores a few pixels of another depth under the cursor (an edge,
    a strand of hair), which is what "focus where I clicked" should mean.
    """
    d = np.asarray(disparity)
    if d.ndim == 3 and d.shape[2] == 1:
        d = d[..., 0]
    if d.ndim != 2 or d.size == 0:
        raise InputError(f"disparity: expected a non-empty H x W map, got shape {d.shape}")
    for name, v in (("x", x), ("y", y), ("window", window)):
        if isinstance(v, bool) or not isinstance(v, Integral):
            raise InputError(f"focus point: expected integer pixel coordinates and window, got {name} = {v!r}")
    h, w = d.shape
    if not (0 <= int(x) < w and 0 <= int(y) < h):
        raise InputError(f"focus point: expected 0 <= x < {w} and 0 <= y < {h}, got ({x}, {y})")
    r = max(0, int(window) // 2)
    patch = d[max(0, y - r) : y + r + 1, max(0, x - r) : x + r + 1]
    return float(np.median(patch))


def boost_highlights(image: np.ndarray, strength: float, threshold: float = 0.95) -> np.ndarray:
    """Re-inflate clipped highlights of an 8-bit (display-referred) photo.

    An sRGB file stores a street lamp of radiance 20 as 1.0, so its bokeh ball
    comes out dim. Pixels whose brightest channel exceeds ``threshold`` are
    scaled by ``1 + strength * t^2`` with ``t = (max - threshold) / (1 - threshold)``.
    Off by default, and never used for metrics. A boost that would take a pixel beyond the radiance a render
    takes (:data:`~bokehray.validate.MAX_RADIANCE`) is refused, naming the pixel.
    """
    if not strength <= float(np.finfo(np.float32).max):  # the kernels compute in float32 (a Python float: no cast)
        raise InputError(f"highlight_boost: expected a value within float32's range (3.4e38), got {strength:g}")
    peak = image.max(axis=2, keepdims=True)
    with np.errstate(over="ignore", invalid="ignore"):  # an overflow is refused below, naming the pixel
        t = np.clip((peak - threshold) / (1.0 - threshold), 0.0, 1.0)
        out = image * (1.0 + strength * t * t)
    bad = ~np.isfinite(out) | (np.abs(out) > MAX_RADIANCE)
    if bad.any():
        y, x = (int(v) for v in np.argwhere(bad)[0][:2])
        raise InputError(f"highlight_boost: expected a boost that keeps radiance within +-{MAX_RADIANCE:g}, the "
                         f"radiance a render takes, got {strength:g}, which takes pixel (y, x) = ({y}, {x}) from "
                         f"{float(peak[y, x, 0]):.4g} to {float(peak[y, x, 0]) * (1.0 + strength * float(t[y, x, 0]) ** 2):.4g}")
    return out.astype(np.float32)


def _check_device(device: str) -> str:
    import warp as wp

    from ._quiet import native_stderr_quiet

    check_type(device, str, "device", "a Warp device name such as 'cpu' or 'cuda:0'")
    try:
        with native_stderr_quiet():  # Warp prints two native lines per failed "cuda" lookup
            dev = wp.get_device(device)
    except (RuntimeError, ValueError) as e:
        avail = ", ".join(str(d) for d in wp.get_devices())
        raise InputError(f"device: {device!r} is not available here ({e}); available: {avail}") from None
    return str(dev)


def _soft_scene(image: np.ndarray, signed_coc: np.ndarray, layers: LayerOptions, device: str,
                finite_checked: bool = False, clock: Clock | None = None, progress: Progress | None = None,
                memory: MemoryOptions | None = None, coc_bounds: tuple[float, float] | None = None):
    """The scene's map and its split pixels: ramps in the map snapped to their plateaus (``LayerOptions.soft_maps``,
    ``bokehray.ramps``), the gaps of strands the map breaks into dashes bridged (``LayerOptions.strand_gaps``,
    ``bokehray.strands``), then the mixed pixels at its depth edges split by matting (``LayerOptions.soft_edges``),
    a ``scene.SoftEdges`` checked against the image (None when off). ``finite_checked``: both arrays are known finite
    (the context's checked photo and the CoC of its checked map), so the matting does not scan them again.
    ``clock``: laps "soft maps", "strands" and "edges" on it. ``progress``: called as ``progress(0, 1)`` (no layer
    done yet) between the steps' parts, so that a render abandoned by its callback stops within a fraction of a
    second.
    ``memory``: the split is refused before the matting when its band cannot fit the budget beside the photo, its
    map and its CoC (``matting.check_split_fits``). ``coc_bounds``: the CoC of disparity 0 and 1; with
    ``LayerOptions.thin_depth``, thin structures the map's blur flattened get their depth back within them
    (``bokehray.thin_depth``; None: not attempted)."""
    clock = clock or Clock()
    check = None if progress is None else (lambda: progress(0, 1))
    if not layers.soft_edges:
        return signed_coc, None
    from .matting import MattingRule, split_mixed_pixels
    from .ramps import snap_ramps

    rule = MattingRule()  # the matting's own reading of ramps: its band and window widen with the ramp width
    if layers.soft_maps and layers.thin_depth and coc_bounds is not None:
        from .thin_depth import restore_thin

        signed_coc, _ = restore_thin(image, signed_coc, bounds=coc_bounds, check=check)
        clock.lap("thin depth")
    if layers.soft_maps:
        signed_coc, _ = snap_ramps(image, signed_coc, device=device, check=check)
        clock.lap("soft maps")
        rule = MattingRule(max_ramp_px=0)  # the ramps are steps now (docs/design/soft-maps.md: 10x less work)
    if layers.strand_gaps:
        from .strands import bridge_strands

        signed_coc, _ = bridge_strands(image, signed_coc, device=device, check=check)
        clock.lap("strands")
    budget = None if memory is None else tiling.budget_bytes(memory) - HELD_DURING_SPLIT_B * signed_coc.size
    soft = split_mixed_pixels(image, signed_coc, rule, finite_checked=finite_checked, check=check,
                              budget_bytes=budget)
    if layers.strand_gaps:  # lights an opaque strand hides, from the split's lit far parts beside it
        from .strands import hidden_lights

        soft, _ = hidden_lights(image, signed_coc, soft)
    scene.check_soft_edges(soft, signed_coc.shape)
    clock.lap("edges")
    return signed_coc, soft


def _coc_bounds(blur: BlurParams, signed_coc: np.ndarray, capped: np.ndarray) -> tuple[float, float] | None:
    """The CoC of disparity 0 and 1, or None where the cap compressed the map (no longer a blur of one)."""
    if capped is not signed_coc:
        return None
    ends = blur.signed_coc(np.array([0.0, 1.0], np.float32))
    return float(ends[0]), float(ends[1])


def _check_shape_fits(image: object, level_whole_image_b: int, memory: MemoryOptions) -> None:
    """Refuse a render from the input's shape alone, before anything is copied (a broadcast view of 1e10
    pixels must not be turned into a 112 GiB array first)."""
    shape = array_shape(image, "image")
    if len(shape) >= 2 and all(isinstance(v, Integral) for v in shape[:2]):
        tiling.check_whole_image(int(shape[0]), int(shape[1]), level_whole_image_b, memory)


def _check_refine(refine: object, quality: str, refine_options: object = None) -> bool:
    if refine is None or refine is False:
        if refine_options is not None:
            raise InputError("refine_options: given without refine (pass refine=True or a path to weights)")
        return False
    if not (refine is True or isinstance(refine, (str, os.PathLike))):
        raise InputError(f"refine: expected True, False or a path to refiner weights, got {refine!r}")
    if quality not in REFINABLE:
        raise InputError("refine: the refiner corrects preview renders (it was trained on them); "
                         "use quality='preview' with refine")
    check_refine_options(refine_options)
    return True


class Handover:
    """A photo and its disparity map handed over to :func:`render_handed_over`, which owns them from then on.

    The caller builds it and keeps no other reference to the arrays (``inputs = Handover(image, disparity)``, then
    ``del image, disparity``); the render takes them out of the holder (:meth:`take`: it is then empty) and drops
    each as soon as it no longer reads it, so that an array nobody else holds is freed before the layers start
    (at 12 MP the command line's photo, disparity and CoC: 240 MB). The arrays are never written to. A holder
    serves one render.
    """

    __slots__ = ("disparity", "image", "taken")

    def __init__(self, image: np.ndarray, disparity: np.ndarray) -> None:
        self.image, self.disparity, self.taken = image, disparity, False

    def take(self) -> tuple[np.ndarray, np.ndarray]:
        """The arrays, once: the holder keeps no reference to them (the arrays' own checks come after)."""
        if self.taken:
            raise InputError("inputs: this Handover was already rendered (a holder serves one render)")
        arrays = self.image, self.disparity
        self.image = self.disparity = None
        self.taken = True
        return arrays


def render_with_stats(
    image: np.ndarray,
    disparity: np.ndarray,
    blur: BlurParams,
    aperture: Aperture | None = None,
    *,
    quality: str = "preview",
    device: str = "cpu",
    options: PreviewOptions | RaytraceOptions | None = None,
    layers: LayerOptions | None = None,
    memory: MemoryOptions | None = None,
    highlight_boost: float = 0.0,
    progress: Progress | None = None,
    refine: bool | str | os.PathLike = False,
    refine_options: object | None = None,
) -> tuple[np.ndarray, RenderStats]:
    """Like :func:`render`, and also return what the renderer did (a :class:`~bokehray.RenderStats`:
    :class:`~bokehray.PreviewStats` or :class:`~bokehray.RaytraceStats`).

    Stages: :func:`_checked_arguments` -> :func:`_context` (validated pixels, grey / alpha, boost, the capped CoC,
    the soft edges) -> the level, or :func:`_render_refined` -> :func:`_output` (alpha through the level, the
    output checks). The caller's arrays are read, never written to, and stay the caller's."""
    return _render_with_stats(Handover(image, disparity), blur, aperture, quality=quality, device=device,
                              options=options, layers=layers, memory=memory, highlight_boost=highlight_boost,
                              progress=progress, refine=refine, refine_options=refine_options)


def render_handed_over(inputs: Handover, blur: BlurParams, aperture: Aperture | None = None, **kwargs):
    """:func:`render_with_stats` of the photo and disparity in ``inputs`` (a :class:`Handover`), which the render
    owns: it takes them out of the holder and drops each array once it no longer reads it (the preview: once the
    scene is split), so that arrays the caller holds no other reference to are freed while the layers render. The
    same values as :func:`render_with_stats` of the same arrays. The command line renders through it."""
    check_type(inputs, Handover, "inputs", "a bokehray.pipeline.Handover")
    return _render_with_stats(inputs, blur, aperture, **kwargs)


def _render_with_stats(inputs: Handover, blur: BlurParams, aperture: Aperture | None, *, quality: str = "preview",
                       device: str = "cpu", options: PreviewOptions | RaytraceOptions | None = None,
                       layers: LayerOptions | None = None, memory: MemoryOptions | None = None,
                       highlight_boost: float = 0.0, progress: Progress | None = None,
                       refine: bool | str | os.PathLike = False,
                       refine_options: object | None = None) -> tuple[np.ndarray, RenderStats]:
    clock = Clock()
    level = get_level(quality)
    layers, memory, options, aperture, device = _checked_arguments(
        level, blur, aperture, device, options, layers, memory, highlight_boost, progress)
    refining = _check_refine(refine, quality, refine_options)
    _check_shape_fits(inputs.image, level.whole_image_bytes(), memory)
    bound_heap()  # the C heap held to what is in use (the estimate counts arrays, not freed pages kept)
    # the context takes the arrays out of the holder: from here only the context (and the caller) holds them
    ctx, work, raw_max, channels, lowest = _context(inputs, blur, aperture, layers, memory, options, device,
                                                    progress, highlight_boost, keep_pixels=refining, clock=clock)
    if refining:
        out_rgb, stats, ctx = _render_refined(level, ctx, work, refine, refine_options)
    else:
        out_rgb, stats = level.render(ctx)
    clock.lap_as(stats.stage_seconds, "level (other)")  # the level's crop, the refiner's second scene
    stats.max_coc_px = raw_max
    out = _output(level, ctx, work, out_rgb, quality, channels, lowest)
    clock.lap("output")
    stats.stage_seconds = {**clock.laps, "total": clock.total()}
    return out, stats


def _checked_arguments(level, blur: object, aperture: object, device: object, options: object, layers: object,
                       memory: object, highlight_boost: object, progress: object):
    """The arguments other than the pixels, checked and defaulted: (layers, memory, options, aperture, device)."""
    layers = LayerOptions() if layers is None else layers
    memory = MemoryOptions() if memory is None else memory
    options = level.options_type() if options is None else options
    check_type(layers, LayerOptions, "layers", "a bokehray.LayerOptions")
    check_type(memory, MemoryOptions, "memory", "a bokehray.MemoryOptions")
    if not isinstance(options, level.options_type):
        raise InputError(f"options: quality {level.name!r} takes a bokehray.{level.options_type.__name__}, "
                         f"got {type(options).__name__}")
    if memory.tile_size is not None and memory.tile_size < layers.tile_px:
        raise InputError(f"tile_size: expected None (automatic) or an integer >= tile_px ({layers.tile_px}), "
                         f"got {memory.tile_size!r}")
    check_type(blur, BlurParams, "blur", "a bokehray.BlurParams")
    aperture = Aperture() if aperture is None else aperture
    check_type(aperture, Aperture, "aperture", "a bokehray.Aperture")
    if isinstance(highlight_boost, bool) or not isinstance(highlight_boost, Real):
        raise InputError(f"highlight_boost: expected a finite number >= 0, got {highlight_boost!r}")
    check_number(highlight_boost, "highlight_boost", 0.0)
    if progress is not None and not callable(progress):
        raise InputError(f"progress: expected a callable progress(done, total) or None, got {progress!r}")
    return layers, memory, options, aperture, _check_device(device)


def _context(inputs: Handover, blur: BlurParams, aperture: Aperture, layers: LayerOptions, memory: MemoryOptions,
             options: object, device: str, progress: Progress | None, highlight_boost: float,
             keep_pixels: bool, clock: Clock) -> tuple[RenderContext, np.ndarray | None, float, int, float]:
    """The validated pixels as one render's context, the working image (RGB or RGBA, boosted; None when nothing
    after the level reads it), the largest CoC before the cap, the input's channels and its smallest value.

    The context is ``disposable`` (the level drops its pixels once read: ``RenderContext.release_pixels``) unless
    something reads them after the level: the alpha of an RGBA input, or the refiner (``keep_pixels``)."""
    image, disparity = inputs.take()
    img = check_image(image)
    check_radiance(img)
    d = check_disparity(disparity, img.shape[:2])
    work = img if img.shape[2] >= 3 else np.repeat(img, 3, axis=2)
    if highlight_boost > 0:
        work = work.copy()
        work[..., :3] = boost_highlights(work[..., :3], highlight_boost)  # colour only, never alpha
    s = blur.signed_coc(d)
    raw_max = max(float(s.max()), -float(s.min())) if s.size else 0.0
    rgb, capped = np.ascontiguousarray(work[..., :3]), scene.cap_coc(s, raw_max)
    disposable = not keep_pixels and img.shape[2] != 4
    clock.lap("checks")
    capped, soft = _soft_scene(rgb, capped, layers, device, finite_checked=True, clock=clock, progress=progress,
                               memory=memory, coc_bounds=_coc_bounds(blur, s, capped))
    ctx = RenderContext(rgb, d, capped, blur, aperture, layers, memory, options, device, progress, soft, disposable)
    return ctx, None if disposable else work, raw_max, img.shape[2], float(img.min())


def _render_refined(level, ctx: RenderContext, work: np.ndarray, refine: bool | str | os.PathLike,
                    refine_options: object | None = None):
    """The refiner's depth correction first, so the level renders once, on the corrected map; then the refiner.
    Returns the refined RGB, the level's stats (with the refiner's) and the context the level rendered."""
    rendered = {}
    d, blur, layers = ctx.disparity, ctx.blur, ctx.layers

    def render_level(dd: np.ndarray) -> np.ndarray:
        if dd is d:
            c = ctx
        else:  # a corrected depth moves the depth edges: split its mixed pixels anew
            s = blur.signed_coc(dd)
            sc = scene.cap_coc(s)
            sc, soft = _soft_scene(ctx.image, sc, layers, ctx.device, progress=ctx.progress, memory=ctx.memory,
                                   coc_bounds=_coc_bounds(blur, s, sc))
            c = replace(ctx, disparity=dd, signed_coc=sc, soft=soft)
        rgb, rendered["stats"] = level.render(c)
        rendered["ctx"] = c
        return rgb

    out_rgb, rstats = refine_render(work[..., :3], d, blur, None, refine, ctx.device, render_level, refine_options)
    stats = rendered["stats"]
    stats.refine = rstats.as_dict()
    stats.stage_seconds["refine"] = rstats.seconds
    return out_rgb, stats, rendered["ctx"]  # alpha blurs with the corrected depth too


def _output(level, ctx: RenderContext, work: np.ndarray | None, out_rgb: np.ndarray, quality: str, channels: int,
            lowest: float) -> np.ndarray:
    """The output in the input's ``channels`` (alpha rendered like a grey channel, through the same level), checked:
    finite, and non-negative for an input whose smallest value ``lowest`` is."""
    if channels == 4:
        # alpha is rendered like a grey channel: it blurs with the colour it belongs to
        out_a, _ = level.render(ctx.with_image(np.ascontiguousarray(np.repeat(work[..., 3:4], 3, axis=2))))
        out = np.concatenate([out_rgb, out_a[..., :1]], axis=2)
    elif channels == 1:
        out = out_rgb[..., :1]
    else:
        out = out_rgb
    if lowest >= 0.0:
        # Every output pixel is a weighted mean of input radiances, so it cannot be negative; float32 prefix sums
        # next to very bright sources can leave -1e-7 of their value (docs/robustness.md).
        np.maximum(out, 0.0, out=out)
    bad = ~np.isfinite(out)
    if bad.any():
        raise NumericalError(f"{quality} renderer produced NaN/Inf at (y, x, c) = {first_bad_index(bad)}")
    return out.astype(np.float32, copy=False)


def render(
    image: np.ndarray,
    disparity: np.ndarray,
    blur: BlurParams,
    aperture: Aperture | None = None,
    *,
    quality: str = "preview",
    device: str = "cpu",
    options: PreviewOptions | RaytraceOptions | None = None,
    layers: LayerOptions | None = None,
    memory: MemoryOptions | None = None,
    highlight_boost: float = 0.0,
    progress: Progress | None = None,
    refine: bool | str | os.PathLike = False,
    refine_options: object | None = None,
) -> np.ndarray:
    """Render ``image`` as a thin lens with aperture ``aperture`` would have seen it.

    Args:
        image: all-in-focus photo, float32 H x W x C (C = 1, 3 or 4), scene-linear.
        disparity: H x W in [0, 1], 1 = nearest.
        blur: ``K`` and ``d_f``; CoC radius ``K * |d - d_f|`` pixels.
        aperture: disc (default) or bladed polygon.
        quality: a level of ``bokehray.QUALITIES``: ``"preview"`` (occlusion-aware layered scatter) or
            ``"raytrace"`` (the same layers ray traced through the aperture).
        device: Warp device, ``"cpu"`` or ``"cuda"`` / ``"cuda:N"``.
        options: the level's own knobs: :class:`~bokehray.PreviewOptions` or :class:`~bokehray.RaytraceOptions`.
        layers: how the photo is cut into depth layers (:class:`~bokehray.LayerOptions`), for every level.
        memory: memory budget and tiling (:class:`~bokehray.MemoryOptions`), for every level.
        highlight_boost: > 0 re-inflates clipped highlights of display-referred
            inputs before blurring (:func:`boost_highlights`); 0 = off (default).
        progress: called as ``progress(done, total)`` after each depth layer.
        refine: True runs the shipped neural refiner (``bokehray_refiner``, the ``refiner`` extra) on the
            tiles near depth edges that matter (docs/refiner.md); a path uses those weights instead.
        refine_options: with ``refine``, a ``bokehray_refiner.refine.RefineOptions`` (default: its defaults), e.g.
            ``RefineOptions(min_fixed_share=0)`` to refine a map the depth fix finds right.

    Returns:
        float32 array shaped like ``image``, scene-linear.

    Raises:
        InputError: bad shapes, ranges, NaN/Inf, unknown options or argument types.
        ResourceError: the render does not fit the memory budget (refused before allocating).
    """
    out, _ = render_with_stats(image, disparity, blur, aperture, quality=quality, device=device, options=options,
                               layers=layers, memory=memory, highlight_boost=highlight_boost, progress=progress,
                               refine=refine, refine_options=refine_options)
    return out
