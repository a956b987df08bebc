"""PISA physics masks at a latent resolution: the CoC constraint and the occlusion visibility.

The masks feed BokehDiff's physics-inspired self-attention (paper sec. 3.2) as
attention biases; the attention itself lives in the torch package
``bokehray_refiner``. Here the masks are computed by Warp kernels
(``bokehray_kernels.pisa``) on CPU or GPU, in a *key-centric window*: entry
``[y, x, o]`` is the pair (key ``(y, x)``, query ``(y, x) + offset(o)``), see
:func:`window_offsets`. Torch reads the arrays without a copy (``wp.to_torch``).

Choices where the paper is ambiguous are written down in docs/refiner.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import bokehray_kernels.pisa as kp
import numpy as np
import warp as wp

from bokehray.errors import InputError
from bokehray.validate import check_disparity

__all__ = ["K_MAX", "PisaMaskOptions", "PisaMasks", "edge_slope", "pisa_masks", "window_offsets", "window_radius"]

K_MAX = 1.0e6
"""Hardness at which the soft CoC edge stops sharpening (paper appendix A)."""

_COLLINEAR = {"thin_lens": kp.COLLINEAR_THIN_LENS, "paper": kp.COLLINEAR_PAPER}


def edge_slope(hardness: float, k_max: float = K_MAX) -> float:
    """Slope of the soft CoC edge: ``Soft(x, k) = sigmoid(ln(1 + min(k, k_max)) * x)``.

    The appendix's ``(1 + min(k, k_max) e^x)^-1`` is ~0 inside the circle if taken
    literally; this form keeps its intent: 1 inside, 0 outside, 1/2 on the
    circle, sharpening as ``k`` grows (slope 13.8 per latent pixel at 1e6).
    """
    return math.log1p(min(hardness, k_max))


@dataclass(frozen=True)
class PisaMaskOptions:
    """How the masks are computed.

    Args:
        hardness: the soft edge's ``k`` (training schedules raise it to ``k_max``; inference uses ``k_max``).
        k_max: the hardness cap (1e6 in the paper).
        dist_scale: ``c`` in eq. 6, multiplies the query-key distance (latent pixels).
        n_sources: jittered light sources per key for the expectation of eq. 8 (odd: one on the key,
            the rest in mirrored pairs, so their mean is the key).
        source_sigma: standard deviation of the source jitter ``epsilon_s``, latent pixels.
        n_steps: disparity samples ``d~`` along each ray (stratified over ``(d_s, 1)``).
        margin_px: an occluder must be nearer than the ray by this CoC, in latent
            pixels (``margin = margin_px / k_lat`` in disparity), so a surface does not
            occlude itself through sampling noise.
        collinear: ``"thin_lens"`` (exact thin-lens ray, default) or ``"paper"`` (eq. 7 as printed).
        eps: clamp of the singular eq. 7 factor (``d_s <= 1 - eps``, ``d~ >= eps``) and of
            the in-focus thin-lens denominator.
        max_window: the largest window radius allowed, latent pixels (memory bound).
    """

    hardness: float = K_MAX
    k_max: float = K_MAX
    dist_scale: float = 1.0
    n_sources: int = 5
    source_sigma: float = 0.5
    n_steps: int = 8
    margin_px: float = 0.5
    collinear: str = "thin_lens"
    eps: float = 1.0e-3
    max_window: int = 16

    def __post_init__(self) -> None:
        for name in ("hardness", "k_max", "dist_scale", "margin_px", "eps"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise InputError(f"PisaMaskOptions.{name}: expected a finite value > 0, got {v!r}")
        if not (math.isfinite(self.source_sigma) and self.source_sigma >= 0):
            raise InputError(f"PisaMaskOptions.source_sigma: expected a finite value >= 0, got {self.source_sigma!r}")
        if not 1 <= self.n_sources <= 64 or not 1 <= self.n_steps <= 64:
            raise InputError(f"PisaMaskOptions: n_sources and n_steps must lie in [1, 64], "
                             f"got {self.n_sources}, {self.n_steps}")
        if self.collinear not in _COLLINEAR:
            raise InputError(f"PisaMaskOptions.collinear: expected one of {sorted(_COLLINEAR)}, got {self.collinear!r}")
        if self.eps >= 0.5:
            raise InputError(f"PisaMaskOptions.eps: expected < 0.5, got {self.eps!r}")
        if not 0 <= self.max_window <= 64:
            raise InputError(f"PisaMaskOptions.max_window: expected 0..64, got {self.max_window!r}")

    @property
    def slope(self) -> float:
        return edge_slope(self.hardness, self.k_max)


@dataclass
class PisaMasks:
    """The two masks in the key-centric window, ``H x W x (2w+1)^2`` float32 Warp arrays.

    ``coc[y, x, o]`` is ``C[q, k]`` and ``visibility[y, x, o]`` is ``E_s[M_vis]`` for key
    ``k = (y, x)`` and query ``q = k + window_offsets(w)[o]``; 0 where ``q`` is outside.
    """

    coc: wp.array
    visibility: wp.array
    window: int
    k_lat: float

    def numpy(self) -> tuple[np.ndarray, np.ndarray]:
        return self.coc.numpy(), self.visibility.numpy()


def window_offsets(window: int) -> np.ndarray:
    """``(2w+1)^2 x 2`` integer (dy, dx) offsets of the window, row-major: ``o = (dy + w) * n + (dx + w)``."""
    r = np.arange(-window, window + 1)
    dy, dx = np.meshgrid(r, r, indexing="ij")
    return np.stack([dy.ravel(), dx.ravel()], axis=1)


def window_radius(r_max: float, opts: PisaMaskOptions) -> int:
    """The window that holds the CoC mask down to ``sigmoid(-10) = 4.5e-5``: ``ceil((r_max + 10/slope) / c)``, capped."""
    w = math.ceil((r_max + 10.0 / opts.slope) / opts.dist_scale)
    return int(min(max(w, 0), opts.max_window))


def pisa_masks(
    disparity: np.ndarray,
    focus_disparity: float,
    k_lat: float,
    opts: PisaMaskOptions | None = None,
    window: int | None = None,
    device: str = "cpu",
) -> PisaMasks:
    """Compute the CoC and visibility masks of one disparity map at its own (latent) resolution.

    Args:
        disparity: ``h x w`` disparity in [0, 1] (1 = nearest) at the latent resolution.
        focus_disparity: ``d_f`` in [0, 1].
        k_lat: CoC gain in latent pixels per unit disparity (the image's K times latent/image size).
        opts: mask options (defaults: inference hardness ``k_max``).
        window: window radius in latent pixels; default :func:`window_radius` of the largest CoC.
        device: Warp device.
    """
    opts = opts or PisaMaskOptions()
    d = np.asarray(disparity)
    if d.ndim != 2 or d.size == 0:
        raise InputError(f"disparity: expected a non-empty h x w array, got shape {d.shape}")
    d = check_disparity(d, d.shape)
    if not (math.isfinite(focus_disparity) and 0.0 <= focus_disparity <= 1.0):
        raise InputError(f"focus_disparity: expected a value in [0, 1], got {focus_disparity!r}")
    if not (math.isfinite(k_lat) and 0.0 <= k_lat <= 1.0e5):
        raise InputError(f"k_lat: expected a finite value in [0, 1e5], got {k_lat!r}")
    r_max = float(k_lat * np.abs(d - focus_disparity).max())
    w = window_radius(r_max, opts) if window is None else int(window)
    if not 0 <= w <= 64:
        raise InputError(f"window: expected 0..64 latent pixels, got {w}")
    n_off = (2 * w + 1) ** 2
    h, wd = d.shape
    disp = wp.array(d, dtype=float, device=device)
    coc = wp.empty((h, wd, n_off), dtype=float, device=device)
    vis = wp.empty((h, wd, n_off), dtype=float, device=device)
    wp.launch(kp.pisa_coc_kernel, dim=(h, wd, n_off),
              inputs=[disp, float(focus_disparity), float(k_lat), float(opts.dist_scale), float(opts.slope), w],
              outputs=[coc], device=device)
    margin = opts.margin_px / k_lat if k_lat > 0 else 2.0  # no blur: nothing can occlude
    wp.launch(kp.pisa_visibility_kernel, dim=(h, wd, n_off),
              inputs=[disp, float(focus_disparity), float(k_lat), w, int(opts.n_sources), float(opts.source_sigma),
                      int(opts.n_steps), float(margin), _COLLINEAR[opts.collinear], float(opts.eps)],
              outputs=[vis], device=device)
    return PisaMasks(coc=coc, visibility=vis, window=w, k_lat=float(k_lat))
