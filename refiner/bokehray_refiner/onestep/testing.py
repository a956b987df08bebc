"""A tiny randomly initialised SDXL-layout checkpoint, built locally: for tests, benchmarks and install checks.

Same classes and directory layout as a real SDXL checkpoint (UNet with text-time
conditioning, VAE, two CLIP text encoders with byte-level tokenizers, DDPM
scheduler) at a few MB, so the real loading path runs end to end without any
download. Optionally writes BokehDiff-style rank-8 LoRA weights for the down
blocks and VAE-encoder weights.
"""

from __future__ import annotations

import json
from pathlib import Path

import torch

__all__ = ["write_tiny_sdxl"]


def _bytes_to_unicode() -> list[str]:
    """The 256 printable stand-ins for bytes that CLIP's byte-level BPE uses as its base alphabet."""
    bs = list(range(ord("!"), ord("~") + 1)) + list(range(ord("¡"), ord("¬") + 1)) + list(range(ord("®"), ord("ÿ") + 1))
    cs = bs[:]
    n = 0
    for b in range(256):
        if b not in bs:
            bs.append(b)
            cs.append(256 + n)
            n += 1
    return [chr(c) for c in cs]


def _write_tokenizer(path: Path, max_length: int) -> None:
    from transformers import CLIPTokenizer

    path.mkdir(parents=True, exist_ok=True)
    base = _bytes_to_unicode()
    vocab = {tok: i for i, tok in enumerate(base + [c + "</w>" for c in base] + ["<|startoftext|>", "<|endoftext|>"])}
    (path / "vocab.json").write_text(json.dumps(vocab))
    (path / "merges.txt").write_text("#version: 0.2\n")
    tok = CLIPTokenizer(vocab_file=str(path / "vocab.json"), merges_file=str(path / "merges.txt"),
                        model_max_length=max_length)
    tok.save_pretrained(path)


def write_tiny_sdxl(path: str | Path, seed: int = 0, lora: bool = False, encoder_weights: bool = False) -> Path:
    """Write a tiny random SDXL-layout model to ``path``; returns the path.

    With ``lora``, also ``path/lora/pytorch_lora_weights.safetensors`` (rank 8, down-block attention, non-zero);
    with ``encoder_weights``, ``path/encoder.safetensors`` (a perturbed copy of the VAE encoder).
    """
    from diffusers import AutoencoderKL, DDPMScheduler, UNet2DConditionModel
    from transformers import CLIPTextConfig, CLIPTextModel, CLIPTextModelWithProjection

    path = Path(path)
    torch.manual_seed(seed)
    unet = UNet2DConditionModel(
        block_out_channels=(32, 64), layers_per_block=1, sample_size=16, in_channels=4, out_channels=4,
        down_block_types=("CrossAttnDownBlock2D", "CrossAttnDownBlock2D"),
        up_block_types=("CrossAttnUpBlock2D", "CrossAttnUpBlock2D"),
        attention_head_dim=(2, 4), use_linear_projection=True, addition_embed_type="text_time",
        addition_time_embed_dim=8, transformer_layers_per_block=1, projection_class_embeddings_input_dim=80,
        cross_attention_dim=64, norm_num_groups=8,
    )
    vae = AutoencoderKL(block_out_channels=[8, 16, 16, 16], in_channels=3, out_channels=3,  # / 8, as SDXL's
                        down_block_types=["DownEncoderBlock2D"] * 4, up_block_types=["UpDecoderBlock2D"] * 4,
                        latent_channels=4, norm_num_groups=8, sample_size=64, layers_per_block=1)
    scheduler = DDPMScheduler(beta_start=0.00085, beta_end=0.012, beta_schedule="scaled_linear",
                              num_train_timesteps=1000, prediction_type="epsilon")
    text_cfg = dict(bos_token_id=514 - 2, eos_token_id=514 - 1, pad_token_id=514 - 1, hidden_size=32,
                    intermediate_size=37, layer_norm_eps=1e-05, num_attention_heads=4, num_hidden_layers=2,
                    vocab_size=514, hidden_act="gelu", projection_dim=32, max_position_embeddings=16)
    unet.save_pretrained(path / "unet")
    vae.save_pretrained(path / "vae")
    scheduler.save_pretrained(path / "scheduler")
    CLIPTextModel(CLIPTextConfig(**text_cfg)).save_pretrained(path / "text_encoder")
    CLIPTextModelWithProjection(CLIPTextConfig(**text_cfg)).save_pretrained(path / "text_encoder_2")
    _write_tokenizer(path / "tokenizer", 16)
    _write_tokenizer(path / "tokenizer_2", 16)
    if lora:
        from diffusers import StableDiffusionXLPipeline
        from peft import LoraConfig
        from peft.utils import get_peft_model_state_dict

        unet.add_adapter(LoraConfig(r=8, lora_alpha=8, init_lora_weights="gaussian",
                                    target_modules=[f"down_blocks.{i}.attentions.0.transformer_blocks.0.attn1.{m}"
                                                    for i in range(2) for m in ("to_q", "to_k", "to_v", "to_out.0")]))
        with torch.no_grad():
            for name, p in unet.named_parameters():
                if "lora_B" in name:
                    p.normal_(0.0, 0.05)  # peft initialises B to 0; a test must see the LoRA act
        StableDiffusionXLPipeline.save_lora_weights(path / "lora", unet_lora_layers=get_peft_model_state_dict(unet))
    if encoder_weights:
        from safetensors.torch import save_file

        state = {k: (v + 0.01 * torch.randn_like(v)).contiguous() for k, v in vae.encoder.state_dict().items()}
        save_file(state, str(path / "encoder.safetensors"))
    return path
