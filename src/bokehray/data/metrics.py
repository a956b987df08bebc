"""Image metrics of the benchmarks, scored the way the BLB authors and the path-traced dev set score.

* Images are compared in **sRGB [0, 1] after clipping**: linear predictions and targets are
  clipped to [0, 1] and sRGB-encoded in float64 (:func:`to_srgb`), exactly as
  ``shared/data/pathtraced-dev/score.py`` does.
* **PSNR** with peak 1 over all pixels and channels (:func:`psnr`); identical images give +inf.
* **SSIM** is scikit-image's (7 x 7 uniform window, ``data_range=1``, per channel), and the
  score is the mean of its full SSIM map over every pixel, borders included, averaged over the
  channels (:func:`ssim_map`), again as ``score.py``; scikit-image's own ``mssim`` leaves out a
  3-pixel border, so it differs in the 4th decimal.
* The **band** is every pixel within ``width`` = 8 px (Euclidean) of a depth discontinuity, a
  pair of 4-neighbours whose depths differ by more than 5 % of the nearer one
  (:func:`discontinuity_band`). With depth = 1 / disparity that is
  ``|d1 - d2| / min(d1, d2) > 0.05`` on disparity, which is how it is computed here (disparity 0,
  infinitely far, against anything nearer is always an edge).

Pure numpy/scipy/scikit-image: no torch. Optional perceptual metrics (LPIPS/DISTS) need local
weights: :class:`PerceptualMetric` loads a TorchScript model the user exported, never downloads.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError

__all__ = [
    "BAND_PX",
    "PerceptualMetric",
    "discontinuity_band",
    "exposure_align",
    "psnr",
    "score",
    "ssim_map",
    "to_srgb",
]

BAND_PX = 8.0
"""Half-width of the depth-discontinuity band in pixels (the dev set's ``score.py --band``)."""
REL_JUMP = 0.05
"""Relative depth jump between 4-neighbours that counts as a discontinuity (``score.py``)."""


def to_srgb(linear: np.ndarray) -> np.ndarray:
    """Clip scene-linear values to [0, 1] and sRGB-encode them, in float64."""
    x = np.clip(np.asarray(linear, np.float64), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def _pair(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    if a.shape != b.shape:
        raise InputError(f"metrics: expected images of one shape, got {a.shape} and {b.shape}")
    return a, b


def psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None, peak: float = 1.0) -> float:
    """PSNR in dB between two images of values in [0, peak]; ``mask`` (H x W) restricts the pixels.

    Returns +inf for identical images and NaN for an empty mask.
    """
    a, b = _pair(a, b)
    d = (a - b) ** 2
    if mask is not None:
        m = np.asarray(mask, bool)
        if m.shape != a.shape[:2]:
            raise InputError(f"metrics: expected a {a.shape[:2]} mask, got {m.shape}")
        if not m.any():
            return math.nan
        d = d[m]
    mse = float(d.mean())
    return math.inf if mse == 0.0 else 10.0 * math.log10(peak * peak / mse)


def ssim_map(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per-pixel SSIM (H x W, mean over channels) of two sRGB images in [0, 1] (scikit-image, 7 x 7)."""
    from skimage.metrics import structural_similarity

    a, b = _pair(a, b)
    if a.ndim == 2:
        return structural_similarity(a, b, data_range=1.0, full=True)[1]
    return structural_similarity(a, b, channel_axis=-1, data_range=1.0, full=True)[1].mean(-1)


def discontinuity_band(disparity: np.ndarray, width: float = BAND_PX, rel_jump: float = REL_JUMP) -> np.ndarray:
    """Pixels within ``width`` px of a depth discontinuity (see the module docstring)."""
    from scipy import ndimage

    d = np.asarray(disparity, np.float64)
    if d.ndim != 2:
        raise InputError(f"band: expected an H x W disparity map, got shape {d.shape}")
    edge = np.zeros(d.shape, bool)
    with np.errstate(divide="ignore", invalid="ignore"):
        for ax in (0, 1):
            a = np.take(d, range(d.shape[ax] - 1), axis=ax)
            b = np.take(d, range(1, d.shape[ax]), axis=ax)
            lo = np.minimum(a, b)
            jump = np.where(lo > 0, np.abs(a - b) / np.where(lo > 0, lo, 1.0) > rel_jump, a != b)
            sl = [slice(None)] * 2
            sl[ax] = slice(0, -1)
            edge[tuple(sl)] |= jump
            sl[ax] = slice(1, None)
            edge[tuple(sl)] |= jump
    if not edge.any():
        return np.zeros(d.shape, bool)
    return ndimage.distance_transform_edt(~edge) <= width


def score(pred_linear: np.ndarray, target_linear: np.ndarray, band: np.ndarray | None = None) -> dict:
    """PSNR/SSIM over the whole image and inside ``band`` (if given), in sRGB after clipping.

    Returns ``{"psnr", "ssim", "band_psnr", "band_ssim"}`` (band entries NaN without a band or
    with an empty one).
    """
    p, t = to_srgb(pred_linear[..., :3]), to_srgb(target_linear[..., :3])
    _pair(p, t)
    smap = ssim_map(t, p)
    out = {"psnr": psnr(t, p), "ssim": float(smap.mean()), "band_psnr": math.nan, "band_ssim": math.nan}
    if band is not None and np.any(band):
        out["band_psnr"] = psnr(t, p, band)
        out["band_ssim"] = float(smap[np.asarray(band, bool)].mean())
    return out


def exposure_align(image: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, float]:
    """Global mean alignment (BokehDiff, EBB Val294): scale the linear ``image`` so its mean is the target's.

    One gain for all channels, in linear light (exposure is a multiplication of radiance).
    Returns the scaled image and the gain; a black image is returned unchanged with gain 1.
    """
    m_img = float(np.mean(np.asarray(image, np.float64)[..., :3]))
    m_tgt = float(np.mean(np.asarray(target, np.float64)[..., :3]))
    if m_img <= 0.0:
        return np.asarray(image, np.float32), 1.0
    gain = m_tgt / m_img
    return (np.asarray(image, np.float32) * np.float32(gain)).astype(np.float32), gain


@dataclass
class PerceptualMetric:
    """LPIPS, DISTS or any perceptual distance exported by the user as a TorchScript module.

    The module is called as ``model(x, y)`` with two ``1 x 3 x H x W`` float32 tensors in
    [-1, 1] (sRGB after clipping, mapped by ``2 v - 1``) and must return a tensor whose mean is
    the distance (lower is better). Needs torch; nothing is downloaded: ``path`` is a local file,
    e.g. made once with ``torch.jit.script(lpips.LPIPS(net="alex")).save("lpips_alex.pt")``.
    """

    name: str
    path: str

    def __post_init__(self) -> None:
        if not Path(self.path).is_file():
            raise InputError(f"{self.path}: {self.name} weights file does not exist")
        try:
            import torch
        except ImportError:
            raise InputError(f"{self.name}: needs torch (pip install 'bokehray[refiner]')") from None
        try:
            self._model = torch.jit.load(os.fspath(self.path), map_location="cpu").eval()
        except Exception as exc:  # noqa: BLE001 - any load failure is a bad user file
            raise InputError(f"{self.path}: cannot load a TorchScript {self.name} model: {exc}") from None

    def __call__(self, pred_linear: np.ndarray, target_linear: np.ndarray) -> float:
        import torch

        def tensor(img: np.ndarray) -> torch.Tensor:
            s = to_srgb(img[..., :3]).astype(np.float32) * 2.0 - 1.0
            return torch.from_numpy(np.ascontiguousarray(s.transpose(2, 0, 1)))[None]

        with torch.no_grad():
            return float(self._model(tensor(pred_linear), tensor(target_linear)).mean())
