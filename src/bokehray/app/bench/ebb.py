"""The EBB Val294 protocol of BokehDiff (appendix): focus, K search, exposure alignment.

Real pairs (an f/16 all-in-focus input and an f/1.8 photo) come with neither ``K`` nor the
focus, so the benchmark chooses them the way the paper and BokehMe do:

* **focus disparity** ``d_f``: the median disparity inside the salient-region mask when one is
  given (``<root>/mask/<stem>.png``, non-zero = salient), else the median disparity of the
  ground truth's sharpest region (:func:`focus_from_sharpness`): the in-focus part of a
  wide-aperture photo is where its local detail is highest;
* **K** per method and per image by a bracketing search on ``[k_lo, k_hi]`` that maximises SSIM
  against the ground truth (:func:`search_k`; golden-section search, the usual "binary search"
  for the maximum of a unimodal function, to ``tol`` px);
* **exposure alignment**: the input is scaled so its global mean equals the ground truth's
  (:func:`bokehray.data.metrics.exposure_align`). Scores are reported for the original and for the
  aligned input; K is searched on the aligned input (the paper's main table) and reused for the
  original one.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ...data.metrics import ssim_map, to_srgb

__all__ = ["focus_from_mask", "focus_from_sharpness", "search_k", "sharpness_map"]


def focus_from_mask(disparity: np.ndarray, mask: np.ndarray) -> float:
    """Median disparity where ``mask`` is set (salient region)."""
    from ...errors import InputError

    m = np.asarray(mask)
    if m.ndim == 3:
        m = m[..., 0]
    if m.shape != disparity.shape:
        raise InputError(f"salient mask: expected {disparity.shape[1]} x {disparity.shape[0]} pixels, "
                         f"got {m.shape[1]} x {m.shape[0]}")
    sel = m > 0.5 * float(m.max()) if m.max() > 0 else np.zeros(m.shape, bool)
    if not sel.any():
        raise InputError("salient mask: expected some non-zero pixels, got an empty mask")
    return float(np.median(disparity[sel]))


def sharpness_map(target_linear: np.ndarray, window: int | None = None) -> np.ndarray:
    """Local detail of an image: box mean of the squared Laplacian of its sRGB luma."""
    from scipy import ndimage

    s = to_srgb(target_linear[..., :3])
    luma = s @ np.array([0.2126, 0.7152, 0.0722])
    lap = ndimage.laplace(luma, mode="nearest")
    win = window or max(5, min(luma.shape) // 32)
    return ndimage.uniform_filter(lap * lap, size=win, mode="nearest")


def focus_from_sharpness(target_linear: np.ndarray, disparity: np.ndarray, top: float = 0.02,
                         window: int | None = None) -> float:
    """Median disparity over the ``top`` share of pixels where the ground truth is sharpest."""
    sharp = sharpness_map(target_linear, window)
    thresh = np.quantile(sharp, 1.0 - top)
    sel = sharp >= thresh
    return float(np.median(disparity[sel]))


def search_k(render: Callable[[float], np.ndarray], target_linear: np.ndarray, k_lo: float = 0.0,
             k_hi: float = 64.0, tol: float = 0.25, max_evals: int = 24) -> tuple[float, float, int]:
    """K in ``[k_lo, k_hi]`` maximising SSIM(render(K), target), by Brent's bounded search (scipy).

    Assumes SSIM is unimodal in K (one best blur); evaluations are cached and the best K ever
    evaluated is returned, so a non-unimodal curve still gives the best point seen.

    Returns:
        ``(k, ssim, evaluations)``.
    """
    t = to_srgb(target_linear[..., :3])
    seen: dict[float, float] = {}

    def f(k: float) -> float:
        k = round(k, 6)
        if k not in seen:
            seen[k] = float(ssim_map(t, to_srgb(render(k)[..., :3])).mean())
        return seen[k]

    from scipy.optimize import minimize_scalar

    res = minimize_scalar(lambda k: -f(k), bounds=(float(k_lo), float(k_hi)), method="bounded",
                          options={"xatol": tol, "maxiter": max_evals})
    f(float(res.x))
    k_best = max(seen, key=lambda k: (seen[k], -k))
    return k_best, seen[k_best], len(seen)
