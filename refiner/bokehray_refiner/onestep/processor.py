"""A diffusers attention processor that swaps PISA into chosen self-attention layers of a U-Net.

Usage::

    install_pisa(unet)                          # PISA in the down blocks' self-attention (the paper's choice)
    eps = unet(z, t, text, cross_attention_kwargs={"pisa": provider}).sample

``provider`` is a :class:`bokehray_refiner.masks.PisaMaskProvider`; each PISA layer
asks it for the masks of its own token grid. Without a provider (or for
cross-attention) a layer computes ordinary attention, and every other attention
module gets a pass-through processor that accepts and ignores the ``pisa``
keyword, so diffusers does not warn about it.
"""

from __future__ import annotations

import re

import torch
from diffusers.models.attention_processor import Attention, AttnProcessor2_0

from bokehray.errors import InputError
from bokehray_refiner.attention import pisa_attention
from bokehray_refiner.masks import PisaMaskProvider

__all__ = ["PISAAttnProcessor", "PassThroughAttnProcessor", "install_pisa", "pisa_layer_names"]


class PassThroughAttnProcessor(AttnProcessor2_0):
    """Diffusers' default processor, accepting (and ignoring) the ``pisa`` keyword."""

    def __call__(self, attn: Attention, hidden_states: torch.Tensor, encoder_hidden_states=None,
                 attention_mask=None, temb=None, pisa: PisaMaskProvider | None = None) -> torch.Tensor:
        return super().__call__(attn, hidden_states, encoder_hidden_states, attention_mask, temb)


class PISAAttnProcessor(PassThroughAttnProcessor):
    """Self-attention with PISA weights (eq. 8) on the layer's token grid."""

    def __call__(self, attn: Attention, hidden_states: torch.Tensor, encoder_hidden_states=None,
                 attention_mask=None, temb=None, pisa: PisaMaskProvider | None = None) -> torch.Tensor:
        if pisa is None or encoder_hidden_states is not None:
            return super().__call__(attn, hidden_states, encoder_hidden_states, attention_mask, temb)
        if attention_mask is not None:
            raise InputError("PISA self-attention takes its masks from the provider, not from attention_mask")
        residual = hidden_states
        if attn.spatial_norm is not None:
            hidden_states = attn.spatial_norm(hidden_states, temb)
        shape = hidden_states.shape
        if hidden_states.ndim == 4:
            b, ch, hh, ww = shape
            hidden_states = hidden_states.view(b, ch, hh * ww).transpose(1, 2)
        if attn.group_norm is not None:
            hidden_states = attn.group_norm(hidden_states.transpose(1, 2)).transpose(1, 2)
        hidden_states = attn.to_out[1](attn.to_out[0](self._attend(attn, hidden_states, pisa)))
        if len(shape) == 4:
            hidden_states = hidden_states.transpose(-1, -2).reshape(shape)
        if attn.residual_connection:
            hidden_states = hidden_states + residual
        return hidden_states / attn.rescale_output_factor

    @staticmethod
    def _attend(attn: Attention, hidden_states: torch.Tensor, pisa: PisaMaskProvider) -> torch.Tensor:
        """PISA attention of the tokens ``(B, N, C)`` on their grid; returns ``(B, N, heads * d)`` before the output
        projection."""
        b, n, _ = hidden_states.shape
        masks = pisa.for_tokens(n)
        gh, gw = masks.shape
        query, key, value = attn.to_q(hidden_states), attn.to_k(hidden_states), attn.to_v(hidden_states)
        head_dim = key.shape[-1] // attn.heads

        def grid(x: torch.Tensor) -> torch.Tensor:  # (B, N, heads*d) -> (B, heads, h, w, d)
            return x.view(b, gh, gw, attn.heads, -1).permute(0, 3, 1, 2, 4)

        query, key, value = grid(query), grid(key), grid(value)
        if attn.norm_q is not None:
            query = attn.norm_q(query)
        if attn.norm_k is not None:
            key = attn.norm_k(key)
        out = pisa_attention(query, key, value, masks.coc.to(query.device), masks.visibility.to(query.device),
                             masks.window, scale=attn.scale)
        return out.permute(0, 2, 3, 1, 4).reshape(b, n, attn.heads * head_dim).to(query.dtype)


def pisa_layer_names(unet: torch.nn.Module, pattern: str = r"^down_blocks\..*\.attn1\.processor$") -> list[str]:
    """The attention-processor names that :func:`install_pisa` would swap (``attn1`` = self-attention)."""
    return [name for name in unet.attn_processors if re.search(pattern, name)]


def install_pisa(unet: torch.nn.Module, pattern: str = r"^down_blocks\..*\.attn1\.processor$") -> list[str]:
    """Put PISA into the self-attention layers whose processor name matches ``pattern``; returns their names.

    The default pattern is the paper's: every self-attention layer of the down blocks.
    """
    names = pisa_layer_names(unet, pattern)
    if not names:
        raise InputError(f"no attention processor of the model matches {pattern!r}")
    chosen = set(names)
    unet.set_attn_processor({name: PISAAttnProcessor() if name in chosen else PassThroughAttnProcessor()
                             for name in unet.attn_processors})
    return names
