"""PISA masks for a batch, at whatever resolution an attention layer runs: Warp computes, torch reads.

A U-Net's self-attention layers see token sequences at several resolutions (the
latent, then /2, /4...). :class:`PisaMaskProvider` holds the full-resolution
disparity of each image and computes the masks for a layer's grid on first
request: the disparity is area-averaged to that grid, K is rescaled to it, and
``bokehray_refiner.pisa.pisa_masks`` runs on the Warp device; the arrays reach torch
without a copy (``wp.to_torch``) and are cached per grid.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
import warp as wp

from bokehray.errors import InputError
from bokehray_refiner.pisa import PisaMaskOptions, pisa_masks, window_radius

__all__ = ["LayerMasks", "PisaMaskProvider"]


@dataclass
class LayerMasks:
    """Masks of one grid: ``coc`` and ``visibility`` are ``(B, h, w, (2w+1)^2)`` float32 tensors."""

    coc: torch.Tensor
    visibility: torch.Tensor
    window: int
    shape: tuple[int, int]


class PisaMaskProvider:
    """Lazily computed, cached PISA masks of a batch of images.

    Args:
        disparity: ``(B, H, W)`` (or ``(H, W)``) disparity in [0, 1] at image resolution.
        focus_disparity: ``d_f`` per image (one float or a sequence of B).
        k_px: CoC gain K in image pixels per unit disparity (one float or B of them).
        opts: mask options; the window is shared by the batch (the largest needed).
        warp_device: where the Warp kernels run ("cpu" or "cuda:0").
        torch_device: where the masks are handed over.
    """

    def __init__(
        self,
        disparity: np.ndarray | torch.Tensor,
        focus_disparity: float | Sequence[float],
        k_px: float | Sequence[float],
        opts: PisaMaskOptions | None = None,
        warp_device: str = "cpu",
        torch_device: str | torch.device = "cpu",
    ) -> None:
        d = torch.as_tensor(np.asarray(disparity.detach().cpu() if torch.is_tensor(disparity) else disparity),
                            dtype=torch.float32)
        if d.ndim == 2:
            d = d[None]
        if d.ndim != 3:
            raise InputError(f"disparity: expected (B, H, W) or (H, W), got shape {tuple(d.shape)}")
        self.disparity = d
        b = d.shape[0]
        self.focus = self._per_image(focus_disparity, b, "focus_disparity")
        self.k_px = self._per_image(k_px, b, "k_px")
        self.opts = opts or PisaMaskOptions()
        self.warp_device = warp_device
        self.torch_device = torch.device(torch_device)
        self._cache: dict[tuple[int, int], LayerMasks] = {}

    @staticmethod
    def _per_image(value: float | Sequence[float], b: int, name: str) -> list[float]:
        vals = [float(value)] * b if np.ndim(value) == 0 else [float(v) for v in value]
        if len(vals) != b:
            raise InputError(f"{name}: expected one value or {b}, got {len(vals)}")
        return vals

    @property
    def image_shape(self) -> tuple[int, int]:
        return int(self.disparity.shape[1]), int(self.disparity.shape[2])

    def grid_for_tokens(self, n_tokens: int) -> tuple[int, int]:
        """The ``(h, w)`` grid of a layer with ``n_tokens`` tokens: the image grid divided by a power of 2."""
        h, w = self.image_shape
        for level in range(12):
            f = 2 ** level
            gh, gw = math.ceil(h / f), math.ceil(w / f)
            if gh * gw == n_tokens:
                return gh, gw
            if gh * gw < n_tokens:
                break
        raise InputError(f"{n_tokens} tokens match no power-of-2 reduction of the {h}x{w} disparity map")

    def at(self, h: int, w: int) -> LayerMasks:
        """The masks on an ``h x w`` grid (computed once, then cached)."""
        key = (int(h), int(w))
        if key in self._cache:
            return self._cache[key]
        small = F.interpolate(self.disparity[:, None], size=key, mode="area")[:, 0].clamp(0.0, 1.0).numpy()
        scale = w / self.image_shape[1]
        k_lat = [k * scale for k in self.k_px]
        window = max(window_radius(k * float(np.abs(s - f).max()), self.opts)
                     for k, s, f in zip(k_lat, small, self.focus))
        coc, vis = [], []
        for s, f, k in zip(small, self.focus, k_lat):
            m = pisa_masks(s, f, k, self.opts, window=window, device=self.warp_device)
            coc.append(wp.to_torch(m.coc))
            vis.append(wp.to_torch(m.visibility))
        masks = LayerMasks(
            coc=torch.stack(coc).to(self.torch_device),
            visibility=torch.stack(vis).to(self.torch_device),
            window=window,
            shape=key,
        )
        self._cache[key] = masks
        return masks

    def for_tokens(self, n_tokens: int) -> LayerMasks:
        return self.at(*self.grid_for_tokens(n_tokens))
