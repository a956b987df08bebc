"""Public rendering API: validation at the boundary, then the chosen quality level."""

from __future__ import annotations

import os
from collections.abc import Callable

import numpy as np

from ._scatter import PreviewOptions, RenderStats, render_preview
from .errors import InputError, NumericalError
from .lens import Aperture, BlurParams
from .raytrace import RaytraceOptions, RaytraceStats, render_raytrace

__all__ = ["QUALITIES", "boost_highlights", "check_disparity", "check_image", "focus_at", "render", "render_with_stats"]

QUALITIES = ("preview", "raytrace")
"""Quality levels: docs/renderer.md (preview) and docs/raytracer.md (raytrace)."""


def _first_bad(mask: np.ndarray) -> tuple[int, ...]:
    return tuple(int(v) for v in np.argwhere(mask)[0])


def check_image(image: np.ndarray, name: str = "image") -> np.ndarray:
    """Validate a scene-linear image: H x W, H x W x 1, H x W x 3 or H x W x 4, finite. Returns float32."""
    a = np.asarray(image)
    if a.ndim == 2:
        a = a[..., None]
    if a.ndim != 3 or a.shape[2] not in (1, 3, 4):
        raise InputError(f"{name}: expected H x W x C with C in (1, 3, 4), got shape {np.shape(image)}")
    if a.shape[0] < 1 or a.shape[1] < 1:
        raise InputError(f"{name}: expected a non-empty image, got shape {a.shape}")
    if not np.issubdtype(a.dtype, np.floating):
        raise InputError(
            f"{name}: expected floating-point scene-linear values, got dtype {a.dtype}; "
            "decode integer images with bokehray.read_image"
        )
    a = np.ascontiguousarray(a, np.float32)
    bad = ~np.isfinite(a)
    if bad.any():
        raise InputError(f"{name}: NaN/Inf at (y, x, c) = {_first_bad(bad)} (after conversion to float32)")
    return a


def check_disparity(disparity: np.ndarray, shape_hw: tuple[int, int], name: str = "disparity") -> np.ndarray:
    """Validate a disparity map: shape ``shape_hw``, finite, within [0, 1]. Returns float32."""
    d = np.asarray(disparity)
    if d.ndim == 3 and d.shape[2] == 1:
        d = d[..., 0]
    if d.shape != tuple(shape_hw):
        raise InputError(
            f"{name}: expected shape {tuple(shape_hw)} (the image's H x W), got {d.shape}; "
            "resize it first (CLI: --resize-disparity)"
        )
    d = np.asarray(d, np.float32)
    bad = ~np.isfinite(d)
    if bad.any():
        raise InputError(f"{name}: NaN/Inf at (y, x) = {_first_bad(bad)}")
    lo, hi = float(d.min()), float(d.max())
    if lo < 0.0 or hi > 1.0:
        raise InputError(
            f"{name}: expected values in [0, 1] (1 = nearest), got [{lo:.4g}, {hi:.4g}]; "
            "normalise it, or convert metric depth with bokehray.disparity_from_depth"
        )
    return np.ascontiguousarray(d)


def focus_at(disparity: np.ndarray, x: int, y: int, window: int = 9) -> float:
    """Focus disparity from a clicked pixel: the median disparity in a ``window`` x ``window`` box.

    The median ignores a few pixels of another depth under the cursor (an edge,
    a strand of hair), which is what "focus where I clicked" should mean.
    """
    d = np.asarray(disparity)
    h, w = d.shape[:2]
    if not (0 <= int(x) < w and 0 <= int(y) < h):
        raise InputError(f"focus point: expected 0 <= x < {w} and 0 <= y < {h}, got ({x}, {y})")
    r = max(0, int(window) // 2)
    patch = d[max(0, y - r) : y + r + 1, max(0, x - r) : x + r + 1]
    return float(np.median(patch))


def render_with_stats(
    image: np.ndarray,
    disparity: np.ndarray,
    blur: BlurParams,
    aperture: Aperture | None = None,
    *,
    quality: str = "preview",
    device: str = "cpu",
    options: PreviewOptions | None = None,
    raytrace_options: RaytraceOptions | None = None,
    highlight_boost: float = 0.0,
    progress: Callable[[int, int], None] | None = None,
    refine: bool | str | os.PathLike = False,
) -> tuple[np.ndarray, RenderStats | RaytraceStats]:
    """Like :func:`render`, and also return what the renderer did (:class:`RenderStats` or :class:`RaytraceStats`)."""
    img = check_image(image)
    d = check_disparity(disparity, img.shape[:2])
    if not isinstance(blur, BlurParams):
        raise InputError(f"blur: expected a bokehray.BlurParams, got {type(blur).__name__}")
    aperture = Aperture() if aperture is None else aperture
    if not isinstance(aperture, Aperture):
        raise InputError(f"aperture: expected a bokehray.Aperture, got {type(aperture).__name__}")
    if quality not in QUALITIES:
        raise InputError(f"quality: expected one of {', '.join(QUALITIES)}, got {quality!r}")
    if not (np.isfinite(highlight_boost) and highlight_boost >= 0):
        raise InputError(f"highlight_boost: expected a finite value >= 0, got {highlight_boost!r}")
    device = _check_device(device)
    if refine is not False and refine is not None and quality != "preview":
        raise InputError("refine: the refiner corrects preview renders (it was trained on them); "
                         "use quality='preview' with refine")

    channels = img.shape[2]
    lowest = float(img.min())
    work = img if channels >= 3 else np.repeat(img, 3, axis=2)
    if highlight_boost > 0:
        work = work.copy()
        work[..., :3] = boost_highlights(work[..., :3], highlight_boost)  # colour only, never alpha
    s = blur.signed_coc(d)
    opts = options or PreviewOptions()

    def run(rgb: np.ndarray, report=None):
        if quality == "raytrace":
            return render_raytrace(rgb, d, blur, aperture, preview_options=opts, options=raytrace_options,
                                   device=device, progress=report)
        return render_preview(rgb, s, aperture, options=opts, device=device, progress=report)

    out_rgb, stats = run(np.ascontiguousarray(work[..., :3]), progress)
    if refine is not False and refine is not None:
        out_rgb, rstats = _refine(work[..., :3], d, blur, out_rgb, refine, device)
        stats.refine = rstats.as_dict()
        stats.stage_seconds["refine"] = rstats.seconds
        if "total" in stats.stage_seconds:
            stats.stage_seconds["total"] += rstats.seconds
    if channels == 4:
        # alpha is rendered like a grey channel: it blurs with the colour it belongs to
        out_a, _ = run(np.ascontiguousarray(np.repeat(work[..., 3:4], 3, axis=2)))
        out = np.concatenate([out_rgb, out_a[..., :1]], axis=2)
    elif channels == 1:
        out = out_rgb[..., :1]
    else:
        out = out_rgb
    if lowest >= 0.0:
        # Every output pixel is a weighted mean of input radiances, so it cannot be negative; float32
        # prefix sums next to very bright sources can leave -1e-7 of their value (found by the soak).
        np.maximum(out, 0.0, out=out)
    bad = ~np.isfinite(out)
    if bad.any():
        raise NumericalError(f"{quality} renderer produced NaN/Inf at (y, x, c) = {_first_bad(bad)}")
    return out.astype(np.float32, copy=False), stats


def render(
    image: np.ndarray,
    disparity: np.ndarray,
    blur: BlurParams,
    aperture: Aperture | None = None,
    *,
    quality: str = "preview",
    device: str = "cpu",
    options: PreviewOptions | None = None,
    raytrace_options: RaytraceOptions | None = None,
    highlight_boost: float = 0.0,
    progress: Callable[[int, int], None] | None = None,
    refine: bool | str | os.PathLike = False,
) -> np.ndarray:
    """Render ``image`` as a thin lens with aperture ``aperture`` would have seen it.

    Args:
        image: all-in-focus photo, float32 H x W x C (C = 1, 3 or 4), scene-linear.
        disparity: H x W in [0, 1], 1 = nearest.
        blur: ``K`` and ``d_f``; CoC radius ``K * |d - d_f|`` pixels.
        aperture: disc (default) or bladed polygon.
        quality: ``"preview"`` (occlusion-aware layered scatter: the more accurate level for photos)
            or ``"raytrace"`` (the same layers ray traced through the aperture: much slower, and on
            photos measured slightly below the preview, docs/raytracer.md; exact for true layer
            stacks, :func:`bokehray.raytrace_layers`).
        device: Warp device, ``"cpu"`` or ``"cuda"`` / ``"cuda:N"``.
        options: layering knobs (:class:`PreviewOptions`), used by both levels.
        raytrace_options: aperture sampling of ``"raytrace"`` (:class:`RaytraceOptions`).
        highlight_boost: > 0 re-inflates clipped highlights of display-referred
            inputs before blurring (:func:`boost_highlights`); 0 = off (default).
        progress: called as ``progress(done, total)`` after each depth layer.
        refine: True runs the shipped neural refiner (``bokehray_refiner``, the ``refiner`` extra) on the
            tiles near depth edges that matter (docs/refiner.md); a path uses those weights instead.

    Returns:
        float32 array shaped like ``image``, scene-linear.

    Raises:
        InputError: bad shapes, ranges, NaN/Inf, unknown options.
    """
    out, _ = render_with_stats(image, disparity, blur, aperture, quality=quality, device=device, options=options,
                               raytrace_options=raytrace_options, highlight_boost=highlight_boost, progress=progress,
                               refine=refine)
    return out


def boost_highlights(image: np.ndarray, strength: float, threshold: float = 0.95) -> np.ndarray:
    """Re-inflate clipped highlights of an 8-bit (display-referred) photo.

    An sRGB file stores a street lamp of radiance 20 as 1.0, so its bokeh ball
    comes out dim. Pixels whose brightest channel exceeds ``threshold`` are
    scaled by ``1 + strength * t^2`` with ``t = (max - threshold) / (1 - threshold)``.
    Off by default, and never used for metrics.
    """
    peak = image.max(axis=2, keepdims=True)
    t = np.clip((peak - threshold) / (1.0 - threshold), 0.0, 1.0)
    return (image * (1.0 + strength * t * t)).astype(np.float32)


def _refine(image: np.ndarray, disparity: np.ndarray, blur: BlurParams, classical: np.ndarray,
            weights: bool | str | os.PathLike, device: str):
    """Run the optional torch refiner; imported only here, so ``bokehray`` never needs torch otherwise."""
    try:
        from bokehray_refiner.refine import load_refiner, refine
    except ImportError as e:
        raise InputError(f"refine: the neural refiner needs its extra: pip install 'bokehray[refiner]' ({e})") from None
    import torch

    tdev = "cuda" if device.startswith("cuda") and torch.cuda.is_available() else "cpu"
    return refine(image, disparity, blur, classical, model=load_refiner(None if weights is True else weights, tdev))


def _check_device(device: str) -> str:
    import warp as wp

    try:
        dev = wp.get_device(device)
    except (RuntimeError, ValueError) as e:
        avail = ", ".join(str(d) for d in wp.get_devices())
        raise InputError(f"device: {device!r} is not available here ({e}); available: {avail}") from None
    return str(dev)
