"""The one-step diffusion wrapper of BokehDiff (paper sec. 3.1), loaded from a local directory only.

::

    z_t   = E(I_f)                                  scaled VAE latent, no noise added
    z0    = (z_t - beta_T * eps_theta(z_t, T, c)) / alpha_T,   T = 499
    I_b   = D(z0)

with ``alpha_T = sqrt(abar_T)`` and ``beta_T = sqrt(1 - abar_T)`` from the
checkpoint's own scheduler (``v_prediction`` and ``sample`` checkpoints are
converted the matching way). PISA runs in the U-Net's down-block self-attention
with masks from the Warp kernels. The prompt embedding is computed once.

The checkpoint is a diffusers SDXL layout (``unet/ vae/ scheduler/
text_encoder/ text_encoder_2/ tokenizer/ tokenizer_2/``); a model without text
encoders instead carries ``prompt_embeds.safetensors`` (keys ``prompt_embeds`` and,
for SDXL U-Nets, ``pooled_prompt_embeds``). BokehDiff-style LoRA weights
(``pytorch_lora_weights.safetensors``) and fine-tuned VAE-encoder weights load on
top. Nothing is downloaded: every ``from_pretrained`` runs with
``local_files_only=True``.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np
import torch
from safetensors.torch import load_file

from bokehray.colour import linear_to_srgb, srgb_to_linear
from bokehray.errors import InputError
from bokehray.lens import BlurParams
from bokehray_refiner.masks import PisaMaskProvider
from bokehray_refiner.pisa import PisaMaskOptions
from bokehray_refiner.tiles import blend_tiles, tile_grid

from .processor import install_pisa

__all__ = ["OneStepBokeh", "OneStepOptions", "load_one_step", "refine_one_step"]

TIMESTEP = 499


@dataclass(frozen=True)
class OneStepOptions:
    """Inference settings.

    Args:
        timestep: the fixed diffusion timestep T (499 in the paper).
        tile: tile size in image pixels for large images (a multiple of ``size_multiple``).
        overlap: overlap of neighbouring tiles in image pixels, blended with a raised cosine.
        masks: PISA mask options (inference uses the hardest edge, ``k_max``).
    """

    timestep: int = TIMESTEP
    tile: int = 1024
    overlap: int = 128
    masks: PisaMaskOptions = PisaMaskOptions()


class OneStepBokeh(torch.nn.Module):
    """One-step bokeh renderer around a diffusers U-Net and VAE.

    Args:
        unet: a ``UNet2DConditionModel`` (PISA is installed into its down-block self-attention).
        vae: an ``AutoencoderKL``.
        scheduler: any diffusers scheduler with ``alphas_cumprod`` (DDPM, Euler, ...).
        prompt_embeds, pooled_prompt_embeds: the cached text condition (batch 1).
        options: inference settings.
    """

    def __init__(self, unet, vae, scheduler, prompt_embeds: torch.Tensor,
                 pooled_prompt_embeds: torch.Tensor | None = None, options: OneStepOptions = OneStepOptions()):
        super().__init__()
        self.unet, self.vae, self.options = unet, vae, options
        self.pisa_layers = install_pisa(unet)
        abar = scheduler.alphas_cumprod[options.timestep].double()
        self.alpha, self.beta = float(abar.sqrt()), float((1.0 - abar).sqrt())
        self.prediction_type = scheduler.config.get("prediction_type", "epsilon")
        if self.prediction_type not in ("epsilon", "v_prediction", "sample"):
            raise InputError(f"scheduler prediction_type {self.prediction_type!r} is not supported")
        self.register_buffer("prompt_embeds", prompt_embeds, persistent=False)
        self.register_buffer("pooled_prompt_embeds", pooled_prompt_embeds, persistent=False)
        cfg = vae.config
        self.latent_scale = float(cfg.scaling_factor)
        self.latent_shift = float(cfg.get("shift_factor", None) or 0.0)
        self.vae_factor = 2 ** (len(cfg.block_out_channels) - 1)
        self.size_multiple = self.vae_factor * 2 ** (len(unet.config.block_out_channels) - 1)

    # --- the three steps -------------------------------------------------------------------------
    def encode(self, image: torch.Tensor) -> torch.Tensor:
        """``z_t = E(I_f)``: sRGB image in [0, 1], ``(B, 3, H, W)`` -> scaled latent (the mode, no noise)."""
        latent = self.vae.encode(image * 2.0 - 1.0).latent_dist.mode()
        return (latent - self.latent_shift) * self.latent_scale

    def denoise(self, z_t: torch.Tensor, pisa: PisaMaskProvider) -> torch.Tensor:
        """``z0 = (z_t - beta_T eps) / alpha_T`` with PISA masks from ``pisa``."""
        b, _, h, w = z_t.shape
        kwargs = {}
        if self.unet.config.get("addition_embed_type") == "text_time":
            ih, iw = h * self.vae_factor, w * self.vae_factor
            time_ids = torch.tensor([[ih, iw, 0, 0, ih, iw]], dtype=z_t.dtype, device=z_t.device).expand(b, -1)
            kwargs["added_cond_kwargs"] = {"text_embeds": self.pooled_prompt_embeds.expand(b, -1).to(z_t.dtype),
                                           "time_ids": time_ids}
        t = torch.full((b,), self.options.timestep, device=z_t.device, dtype=torch.long)
        out = self.unet(z_t, t, encoder_hidden_states=self.prompt_embeds.expand(b, -1, -1).to(z_t.dtype),
                        cross_attention_kwargs={"pisa": pisa}, **kwargs).sample
        if self.prediction_type == "epsilon":
            return (z_t - self.beta * out) / self.alpha
        if self.prediction_type == "v_prediction":
            return self.alpha * z_t - self.beta * out
        return out

    def decode(self, z0: torch.Tensor) -> torch.Tensor:
        """``I_b = D(z0)``, sRGB in [0, 1]."""
        image = self.vae.decode(z0 / self.latent_scale + self.latent_shift).sample
        return ((image + 1.0) / 2.0).clamp(0.0, 1.0)

    def forward(self, image: torch.Tensor, pisa: PisaMaskProvider) -> torch.Tensor:
        """Render one batch: sRGB ``(B, 3, H, W)`` in [0, 1], H and W multiples of ``size_multiple``."""
        return self.decode(self.denoise(self.encode(image), pisa))

    # --- whole images ----------------------------------------------------------------------------
    @torch.no_grad()
    def render(self, image: np.ndarray, disparity: np.ndarray, params: BlurParams) -> np.ndarray:
        """Render a scene-linear ``H x W x 3`` image with its disparity, tile by tile; returns scene-linear.

        The VAE works on display-referred sRGB: the input is clipped to [0, 1] first, so highlights
        brighter than 1 come out at 1 (the shipped refiner, which corrects a classical render, keeps them).
        """
        img = np.asarray(image, dtype=np.float32)
        if img.ndim != 3 or img.shape[2] != 3:
            raise InputError(f"image: expected H x W x 3, got shape {img.shape}")
        if np.shape(disparity) != img.shape[:2]:
            raise InputError(f"disparity: expected shape {img.shape[:2]}, got {np.shape(disparity)}")
        srgb = linear_to_srgb(np.clip(img, 0.0, 1.0)).astype(np.float32)
        opts = self.options
        tiles = tile_grid(img.shape[:2], opts.tile, opts.overlap, self.size_multiple)
        device = next(self.unet.parameters()).device
        dtype = next(self.unet.parameters()).dtype
        outputs = []
        for (y0, y1, x0, x1), (ph, pw) in tiles:
            crop = np.pad(srgb[y0:y1, x0:x1], ((0, ph), (0, pw), (0, 0)), mode="reflect")
            dcrop = np.pad(np.asarray(disparity, np.float32)[y0:y1, x0:x1], ((0, ph), (0, pw)), mode="reflect")
            pisa = PisaMaskProvider(dcrop, params.focus_disparity, params.k_px, opts.masks)
            x = torch.from_numpy(crop).permute(2, 0, 1)[None].to(device, dtype)
            y = self(x, pisa)[0].permute(1, 2, 0).float().cpu().numpy()
            outputs.append(y[: y1 - y0, : x1 - x0])
        out = blend_tiles(outputs, [t for t, _ in tiles], img.shape[:2], opts.overlap)
        return srgb_to_linear(out).astype(np.float32)


def _encode_prompt(path: Path, unet, vae, scheduler, prompt: str, device) -> tuple[torch.Tensor, torch.Tensor | None]:
    """The cached text condition: ``prompt_embeds.safetensors`` if present, else the text encoders."""
    fixed = path / "prompt_embeds.safetensors"
    if fixed.is_file():
        t = load_file(str(fixed))
        if "prompt_embeds" not in t:
            raise InputError(f"{fixed}: expected a tensor named 'prompt_embeds'")
        return t["prompt_embeds"].to(device), t.get("pooled_prompt_embeds", None)
    from diffusers import StableDiffusionXLPipeline
    from transformers import CLIPTextModel, CLIPTextModelWithProjection, CLIPTokenizer

    missing = [d for d in ("text_encoder", "text_encoder_2", "tokenizer", "tokenizer_2") if not (path / d).is_dir()]
    if missing:
        raise InputError(f"{path}: no prompt_embeds.safetensors and no text encoders (missing {', '.join(missing)})")
    pipe = StableDiffusionXLPipeline(
        vae=vae, unet=unet, scheduler=scheduler,
        text_encoder=CLIPTextModel.from_pretrained(path / "text_encoder", local_files_only=True),
        text_encoder_2=CLIPTextModelWithProjection.from_pretrained(path / "text_encoder_2", local_files_only=True),
        tokenizer=CLIPTokenizer.from_pretrained(path / "tokenizer", local_files_only=True),
        tokenizer_2=CLIPTokenizer.from_pretrained(path / "tokenizer_2", local_files_only=True),
    )
    with torch.no_grad():
        embeds, _, pooled, _ = pipe.encode_prompt(prompt, device=device, num_images_per_prompt=1,
                                                  do_classifier_free_guidance=False)
    return embeds, pooled


def _first_line(e: BaseException) -> str:
    return (str(e).strip().splitlines() or [type(e).__name__])[0][:300]


def _load_checked(cls, path: Path, sub: str):
    """``path/sub`` loaded as ``cls``, refused (one line naming the folder) where its weights do not fit its
    ``config.json``: a tensor of another shape, one missing or one left over. diffusers would otherwise start the
    missing ones from random values."""
    try:
        model, info = cls.from_pretrained(path / sub, local_files_only=True, output_loading_info=True)
    except (OSError, ValueError, RuntimeError) as e:
        raise InputError(f"{path}: the weights in {sub}/ do not fit {sub}/config.json ({_first_line(e)})") from None
    for key in ("missing_keys", "unexpected_keys", "mismatched_keys"):
        if info.get(key):
            names = ", ".join(str(k) for k in list(info[key])[:3])
            raise InputError(f"{path}: the weights in {sub}/ do not fit {sub}/config.json ({key.replace('_', ' ')}: "
                             f"{names}{', ...' if len(info[key]) > 3 else ''})")
    return model


def load_one_step(
    model_dir: str | os.PathLike,
    lora: str | os.PathLike | None = None,
    encoder_weights: str | os.PathLike | None = None,
    prompt: str = "",
    options: OneStepOptions = OneStepOptions(),
    device: str = "cpu",
    dtype: torch.dtype = torch.float32,
) -> OneStepBokeh:
    """Load a one-step bokeh model from local files (no hub access).

    Args:
        model_dir: a diffusers SDXL-layout directory (see the module docstring).
        lora: a directory holding ``pytorch_lora_weights.safetensors``, or the file itself.
        encoder_weights: a safetensors state dict for the VAE encoder (keys with or without ``encoder.``).
        prompt: the text condition, encoded once.
    """
    from diffusers import AutoencoderKL, DDPMScheduler, UNet2DConditionModel

    path = Path(model_dir)
    for sub in ("unet", "vae", "scheduler"):
        if not (path / sub).is_dir():
            raise InputError(f"{path}: not a diffusers model directory (no {sub}/)")
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    unet = _load_checked(UNet2DConditionModel, path, "unet")
    vae = _load_checked(AutoencoderKL, path, "vae")
    try:
        scheduler = DDPMScheduler.from_pretrained(path / "scheduler", local_files_only=True)
    except (OSError, ValueError) as e:
        raise InputError(f"{path}: scheduler/ does not load ({_first_line(e)})") from None
    if not 0 <= options.timestep < len(scheduler.alphas_cumprod):
        raise InputError(f"timestep {options.timestep} is outside the scheduler's {len(scheduler.alphas_cumprod)} steps")
    if encoder_weights is not None:
        state = load_file(str(encoder_weights))
        state = {k.removeprefix("encoder."): v for k, v in state.items()}
        vae.encoder.load_state_dict(state, strict=True)
    if lora is not None:
        from diffusers import StableDiffusionXLPipeline

        lora = Path(lora)
        weight_name = lora.name if lora.is_file() else "pytorch_lora_weights.safetensors"
        lora_dir = lora.parent if lora.is_file() else lora
        if not (lora_dir / weight_name).is_file():
            raise InputError(f"{lora_dir / weight_name}: LoRA weights not found")
        state, alphas = StableDiffusionXLPipeline.lora_state_dict(str(lora_dir), weight_name=weight_name)
        StableDiffusionXLPipeline.load_lora_into_unet(state, alphas, unet, adapter_name="bokeh")
    embeds, pooled = _encode_prompt(path, unet, vae, scheduler, prompt, device)
    if embeds.ndim != 3 or embeds.shape[0] != 1:
        raise InputError(f"{path}: prompt embeddings must be 1 x tokens x features, got {tuple(embeds.shape)}")
    if unet.config.get("addition_embed_type") == "text_time" and pooled is None:
        raise InputError(f"{path}: this U-Net needs pooled prompt embeddings (pooled_prompt_embeds)")
    model = OneStepBokeh(unet, vae, scheduler, embeds, pooled, options).to(device, dtype)
    return model.eval()


@lru_cache(maxsize=2)
def _cached(model_dir: str, modified: float, device: str) -> OneStepBokeh:
    """The folder's model, with ``lora/`` (BokehDiff-style LoRA weights) and ``encoder.safetensors`` (fine-tuned
    VAE-encoder weights) on top where the folder holds them."""
    path = Path(model_dir)
    lora = path / "lora" if (path / "lora").is_dir() else None
    encoder = path / "encoder.safetensors" if (path / "encoder.safetensors").is_file() else None
    return load_one_step(path, lora=lora, encoder_weights=encoder, device=device)


def refine_one_step(image: np.ndarray, disparity: np.ndarray, blur: BlurParams, model_dir: str | os.PathLike,
                    device: str = "cpu", classical: np.ndarray | None = None, rerender=None):
    """``render(refine=True, refine_options=RefineOptions(model=DIR))`` and ``--refiner-model DIR``: the one-step
    model in ``DIR`` (with ``DIR/lora/`` and ``DIR/encoder.safetensors`` where present) renders the whole frame from the all-in-focus photo (PISA attention, tile by tile); the
    classical level still renders once (``rerender``, when ``classical`` is None) for its statistics and alpha.
    Returns (scene-linear RGB, a ``RefineStats`` counting the model's tiles). The model is loaded once per folder,
    modification time and device."""
    from bokehray_refiner.refine import RefineStats

    path = Path(model_dir)
    if not path.is_dir():
        raise InputError(f"{path}: not a folder (a one-step model is a diffusers-layout folder)")
    if classical is None and rerender is not None:
        rerender(np.asarray(disparity, np.float32))
    t = time.perf_counter()
    model = _cached(str(path.resolve()), (path / "unet").stat().st_mtime if (path / "unet").is_dir() else 0.0, device)
    out = model.render(image, disparity, blur)
    n = len(tile_grid(np.shape(image)[:2], model.options.tile, model.options.overlap, model.size_multiple))
    return out, RefineStats(tiles_total=n, tiles_refined=n, seconds=time.perf_counter() - t)
