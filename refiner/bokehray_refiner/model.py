"""The small refiner that ships with bokehray: BokehDiff's one-step formulation at laptop-CPU size.

Where BokehDiff fine-tunes SDXL (2.6 B parameters), this model keeps the
formulation and drops the scale:

* ``z_t = E(x)``: a learned convolutional encoder maps the conditioning (the
  all-in-focus image, the classical render and the signed CoC map) to a latent
  at 1/4 resolution; no noise is added.
* ``eps = U(z_t, T)``: a two-level U-Net at a fixed timestep ``T = 499`` (its
  embedding is a constant, kept so the formulation is literal) with PISA
  self-attention at 1/8 resolution, masks from the Warp kernels.
* ``z0 = (z_t - beta_T eps) / alpha_T`` with the scaled-linear DDPM schedule of
  Stable Diffusion.
* ``D(z0)``: a decoder back to full resolution with skips from the encoder that
  predicts a residual on the classical render (sRGB). The last layer starts at
  zero, so an untrained model returns the classical render unchanged.

Why a residual on the classical render rather than an image from scratch: the
classical renderer is exact where the depth is right, which is almost
everywhere; the refiner only has to learn the fix where depth is wrong (thin
structures, misaligned edges). See docs/refiner.md for the size/time budget.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import torch
import torch.nn as nn
import torch.nn.functional as F

from .attention import pisa_attention
from .masks import PisaMaskProvider

__all__ = ["BokehRefiner", "RefinerConfig", "ddpm_alpha_beta", "fingerprint"]


def ddpm_alpha_beta(t: int, beta_start: float = 0.00085, beta_end: float = 0.012, steps: int = 1000):
    """``alpha_t = sqrt(abar_t)`` and ``beta_t = sqrt(1 - abar_t)`` of the scaled-linear schedule (SD/SDXL)."""
    betas = torch.linspace(beta_start ** 0.5, beta_end ** 0.5, steps, dtype=torch.float64) ** 2
    abar = torch.cumprod(1.0 - betas, 0)[t]
    return float(abar.sqrt()), float((1.0 - abar).sqrt())


@dataclass(frozen=True)
class RefinerConfig:
    """Architecture. ``in_channels``: sRGB all-in-focus (3), sRGB classical render (3), tanh(CoC / coc_scale) (1)."""

    in_channels: int = 7
    stem: int = 16
    mid: int = 32
    latent: int = 32
    deep: int = 64
    heads: int = 4
    timestep: int = 499
    coc_scale: float = 8.0
    latent_factor: int = 8  # PISA grid = image / latent_factor
    groups: int = 8

    def as_dict(self) -> dict:
        return asdict(self)


class _ResBlock(nn.Module):
    def __init__(self, ch: int, groups: int, temb: int):
        super().__init__()
        self.n1, self.c1 = nn.GroupNorm(groups, ch), nn.Conv2d(ch, ch, 3, padding=1)
        self.n2, self.c2 = nn.GroupNorm(groups, ch), nn.Conv2d(ch, ch, 3, padding=1)
        self.t = nn.Linear(temb, ch)

    def forward(self, x: torch.Tensor, temb: torch.Tensor) -> torch.Tensor:
        h = self.c1(F.silu(self.n1(x))) + self.t(temb)[:, :, None, None]
        return x + self.c2(F.silu(self.n2(h)))


class _PISABlock(nn.Module):
    """Pre-norm PISA self-attention with a residual connection."""

    def __init__(self, ch: int, heads: int, groups: int):
        super().__init__()
        self.heads = heads
        self.norm = nn.GroupNorm(groups, ch)
        self.qkv = nn.Conv2d(ch, 3 * ch, 1)
        self.out = nn.Conv2d(ch, ch, 1)

    def forward(self, x: torch.Tensor, pisa: PisaMaskProvider) -> torch.Tensor:
        b, c, h, w = x.shape
        masks = pisa.at(h, w)
        q, k, v = self.qkv(self.norm(x)).view(b, 3, self.heads, c // self.heads, h, w).permute(1, 0, 2, 4, 5, 3)
        a = pisa_attention(q, k, v, masks.coc.to(x.device), masks.visibility.to(x.device), masks.window)
        return x + self.out(a.permute(0, 1, 4, 2, 3).reshape(b, c, h, w))


class BokehRefiner(nn.Module):
    """One-step refiner: ``out = render + D(z0)``, ``z0 = (E(x) - beta eps(E(x), T)) / alpha``."""

    def __init__(self, config: RefinerConfig = RefinerConfig()):
        super().__init__()
        self.config = cfg = config
        g = cfg.groups
        self.alpha, self.beta = ddpm_alpha_beta(cfg.timestep)
        # E: full -> 1/2 -> 1/4
        self.stem = nn.Sequential(nn.Conv2d(cfg.in_channels, cfg.stem, 3, padding=1), nn.SiLU())
        self.down1 = nn.Sequential(nn.Conv2d(cfg.stem, cfg.mid, 3, stride=2, padding=1), nn.SiLU(),
                                   nn.Conv2d(cfg.mid, cfg.mid, 3, padding=1), nn.SiLU())
        self.to_latent = nn.Conv2d(cfg.mid, cfg.latent, 3, stride=2, padding=1)
        # U (eps_theta) at 1/4 and 1/8, fixed timestep embedding
        temb = 4 * cfg.latent
        self.temb = nn.Sequential(nn.Linear(cfg.latent, temb), nn.SiLU(), nn.Linear(temb, temb))
        self.u_in = nn.Conv2d(cfg.latent, cfg.latent, 3, padding=1)
        self.u_res1 = _ResBlock(cfg.latent, g, temb)
        self.u_down = nn.Conv2d(cfg.latent, cfg.deep, 3, stride=2, padding=1)
        self.u_res2 = _ResBlock(cfg.deep, g, temb)
        self.u_pisa = _PISABlock(cfg.deep, cfg.heads, g)
        self.u_res3 = _ResBlock(cfg.deep, g, temb)
        self.u_up = nn.Conv2d(cfg.deep, cfg.latent, 3, padding=1)
        self.u_res4 = _ResBlock(cfg.latent, g, temb)
        self.u_out = nn.Sequential(nn.GroupNorm(g, 2 * cfg.latent), nn.SiLU(), nn.Conv2d(2 * cfg.latent, cfg.latent, 3, padding=1))
        # D: 1/4 -> 1/2 -> full, with encoder skips
        self.d1 = nn.Sequential(nn.Conv2d(cfg.latent + cfg.mid, cfg.mid, 3, padding=1), nn.SiLU())
        self.d2 = nn.Sequential(nn.Conv2d(cfg.mid + cfg.stem, cfg.stem, 3, padding=1), nn.SiLU())
        self.head = nn.Conv2d(cfg.stem, 3, 3, padding=1)
        nn.init.zeros_(self.head.weight)
        nn.init.zeros_(self.head.bias)

    @property
    def size_multiple(self) -> int:
        return self.config.latent_factor

    def _time_embedding(self, b: int, device, dtype) -> torch.Tensor:
        half = self.config.latent // 2
        freqs = torch.exp(-math.log(10000.0) * torch.arange(half, device=device, dtype=torch.float32) / half)
        ang = self.config.timestep * freqs
        e = torch.cat([ang.sin(), ang.cos()])[None].expand(b, -1).to(dtype)
        return self.temb(e)

    def inputs(self, focus_srgb: torch.Tensor, render_srgb: torch.Tensor, coc_px: torch.Tensor) -> torch.Tensor:
        """Stack the conditioning: ``(B, 3, H, W)`` sRGB images and ``(B, H, W)`` signed CoC in pixels."""
        return torch.cat([focus_srgb, render_srgb, torch.tanh(coc_px / self.config.coc_scale)[:, None]], 1)

    def forward(self, focus_srgb: torch.Tensor, render_srgb: torch.Tensor, coc_px: torch.Tensor,
                pisa: PisaMaskProvider) -> torch.Tensor:
        """The refined image (sRGB, not clipped). H and W must be multiples of :attr:`size_multiple`."""
        x = self.inputs(focus_srgb, render_srgb, coc_px)
        f0 = self.stem(x)
        f1 = self.down1(f0)
        z_t = self.to_latent(f1)  # E(x)
        t = self._time_embedding(x.shape[0], x.device, x.dtype)
        h1 = self.u_res1(self.u_in(z_t), t)
        h2 = self.u_res3(self.u_pisa(self.u_res2(self.u_down(h1), t), pisa), t)
        h3 = self.u_res4(self.u_up(F.interpolate(h2, size=h1.shape[-2:], mode="nearest")), t)
        eps = self.u_out(torch.cat([h3, h1], 1))
        z0 = (z_t - self.beta * eps) / self.alpha
        d1 = self.d1(torch.cat([F.interpolate(z0, size=f1.shape[-2:], mode="bilinear", align_corners=False), f1], 1))
        d2 = self.d2(torch.cat([F.interpolate(d1, size=f0.shape[-2:], mode="bilinear", align_corners=False), f0], 1))
        return render_srgb + self.head(d2)


@torch.no_grad()
def fingerprint(model: BokehRefiner) -> list[float]:
    """Output summary on a fixed 64 x 64 input (a step edge in depth): ``[mean, mean |x|, x[0, :, 32, 32]...]``.

    Written next to exported weights, so a test can check that the shipped weights
    load and compute what they computed when they were trained.
    """
    import numpy as np

    rng = np.random.default_rng(1234)
    focus = torch.from_numpy(rng.uniform(0, 1, (1, 3, 64, 64)).astype(np.float32))
    render = torch.from_numpy(rng.uniform(0, 1, (1, 3, 64, 64)).astype(np.float32))
    d = np.full((1, 64, 64), 0.2, np.float32)
    d[:, 16:48, 20:44] = 0.9
    coc = torch.from_numpy(16.0 * (d - 0.9))
    was_training = model.training
    model.eval()
    out = model(focus, render, coc, PisaMaskProvider(d, 0.9, 16.0)).double()
    model.train(was_training)
    return [float(out.mean()), float(out.abs().mean())] + [float(v) for v in out[0, :, 32, 32]]
