"""The learned edge placement: a small network that moves a depth map's edges onto the photo's (refine's first network).

A wrong depth edge changes the render only near the edge, and only in one way: pixels of the near side are rendered
as far, or the other way round. So instead of synthesising the blurred image, this network segments: per pixel of the
edge band where an edge is in reach, the probability that the pixel belongs to the near side (the map's largest
disparity within ``radius_px``, ``near``) rather than the far side (its smallest, ``far``). A pixel the map puts on
one side moves to the other only where the network is sure (probability at least ``threshold``); it then takes that
side's value. The level renders once on the moved map, exactly, with the soft scene's matting at the new edges.

It sees the photo (sRGB), the map's CoC and the near and far candidates' (as differences from it), the band, and the
photo less the local mean colour of either side (:func:`colour_features`); dilated 3 x 3 convolutions (receptive
field ``2 * reach_px + 1``) and a 1 x 1 layer give one logit. Trained on ``bokehray synth`` pairs with their maps
corrupted as real ones are (``bokehray_refiner.training.edges``), against the side the true map puts each pixel on.
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from safetensors.torch import save_file
from torch import nn

from bokehray.errors import InputError
from bokehray.lens import BlurParams

from .saved import load_saved
from .tiles import refine_boxes

__all__ = [
    "DEFAULT_EDGE_WEIGHTS",
    "EdgeConfig",
    "EdgeNet",
    "Placement",
    "candidates",
    "colour_allows",
    "colour_features",
    "edge_features",
    "load_edge_net",
    "map_sides",
    "place_edges",
    "place_edges_once",
    "save_edge_net",
]

DEFAULT_EDGE_WEIGHTS = Path(__file__).parent / "weights" / "edges.safetensors"


@dataclass(frozen=True)
class EdgeConfig:
    """The edge network's shape and the candidates it chooses among.

    Args:
        width: channels of the hidden layers.
        dilations: the dilation of each hidden 3 x 3 convolution after the first.
        radius_px: how far the ``near`` and ``far`` candidates look for their value (a square window).
        coc_scale_px: CoCs are given to the network divided by this, and clipped to +-4.
    """

    width: int = 32
    dilations: tuple[int, ...] = (2, 4, 8, 1)
    radius_px: int = 24
    coc_scale_px: float = 8.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "dilations", tuple(int(d) for d in self.dilations))
        if self.width < 1 or self.radius_px < 1 or not self.dilations or min(self.dilations) < 1 \
                or not self.coc_scale_px > 0:
            raise InputError(f"edge network config: not a valid shape ({self})")

    @property
    def reach_px(self) -> int:
        """How far a pixel's output depends on its inputs (the receptive field's radius)."""
        return 1 + sum(self.dilations)


N_BASE = 7  # photo (3), the map's CoC, near - map, far - map, band
N_INPUTS = N_BASE + 6  # and the photo less the local mean colour of the map's near side, and of its far side
COLOUR_SIGMA_PX = 8.0
"""The reach of the local colour models (a Gaussian's sigma)."""


class EdgeNet(nn.Module):
    """One logit per pixel, the near side's, from :func:`edge_features` (``B x N_INPUTS x H x W``)."""

    def __init__(self, config: EdgeConfig = EdgeConfig()) -> None:
        super().__init__()
        self.config = config
        w = config.width
        layers: list[nn.Module] = [nn.Conv2d(N_INPUTS, w, 3, padding=1), nn.ReLU()]
        for d in config.dilations:
            layers += [nn.Conv2d(w, w, 3, padding=d, dilation=d), nn.ReLU()]
        layers.append(nn.Conv2d(w, 1, 1))
        self.net = nn.Sequential(*layers)

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        return self.net(features)


def candidates(disparity: np.ndarray, radius_px: int) -> tuple[np.ndarray, np.ndarray]:
    """The ``near`` and ``far`` candidate maps: the largest and the smallest disparity within ``radius_px``."""
    from scipy import ndimage

    size = 2 * radius_px + 1
    return (ndimage.maximum_filter(disparity, size=size, mode="nearest"),
            ndimage.minimum_filter(disparity, size=size, mode="nearest"))


def edge_features(focus_srgb: np.ndarray, disparity: np.ndarray, blur: BlurParams, band: np.ndarray,
                  config: EdgeConfig, near_far: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """What the network sees, ``13 x H x W`` float32: the photo, the map's signed CoC, the near and far candidates'
    CoCs less the map's (all divided by ``coc_scale_px``, clipped to +-4), the band, then
    :func:`colour_features` of those. ``near_far``: :func:`candidates` of ``disparity``, when already computed."""
    near, far = candidates(disparity, config.radius_px) if near_far is None else near_far
    c = blur.signed_coc(disparity)
    s = config.coc_scale_px
    cocs = [c / s, (blur.signed_coc(near) - c) / s, (blur.signed_coc(far) - c) / s]
    out = np.empty((N_INPUTS,) + disparity.shape, np.float32)
    out[:3] = np.moveaxis(focus_srgb[..., :3], -1, 0)
    out[3:6] = np.clip(np.stack(cocs), -4.0, 4.0)
    out[6] = band
    out[N_BASE:] = colour_features(out[:N_BASE])
    return out


def colour_features(base: np.ndarray) -> np.ndarray:
    """The photo less the local mean colour of the map's near side, and less that of its far side (``6 x H x W``),
    from the first 7 channels of :func:`edge_features`: what tells, per pixel, which side its colour belongs to.

    A pixel is on the near side where its CoC is nearer the near candidate's than the far one's (signed CoC is
    monotonic in disparity); the means are Gaussian-weighted (``COLOUR_SIGMA_PX``), over pixels where the two
    candidates differ (an edge is in reach)."""
    from scipy import ndimage

    photo, c, dn, dfar = base[:3], base[3], base[4], base[5]
    edge = (dn - dfar) > 1e-3
    near_side = (edge & (-dfar > dn)).astype(np.float32)  # c - far > near - c
    far_side = (edge & (-dfar <= dn)).astype(np.float32)
    out = np.empty((6,) + c.shape, np.float32)
    for k, side in enumerate((near_side, far_side)):
        wsum = ndimage.gaussian_filter(side, COLOUR_SIGMA_PX)
        for ch in range(3):
            mean = ndimage.gaussian_filter(photo[ch] * side, COLOUR_SIGMA_PX) / np.maximum(wsum, 1e-3)
            out[3 * k + ch] = np.where(wsum > 1e-3, photo[ch] - mean, 0.0)
    return out


def colour_allows(features: np.ndarray, margin: float) -> tuple[np.ndarray, np.ndarray]:
    """Where the photo's colour lets a pixel move to the near side, and where to the far side: its colour must be
    nearer (Euclidean, sRGB) the local mean of the side it moves to than that of the other side, by ``margin``.
    ``features``: :func:`edge_features` (its colour channels). A pixel inside a sharp subject has its subject's colour,
    so no move punches a hole in it; a strip the map puts on the wrong side has the other side's colour."""
    to_near = np.sqrt((features[N_BASE:N_BASE + 3] ** 2).sum(0))
    to_far = np.sqrt((features[N_BASE + 3:N_BASE + 6] ** 2).sum(0))
    return to_near + margin < to_far, to_far + margin < to_near


def map_sides(disparity: np.ndarray, near: np.ndarray, far: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where an edge is in reach (the candidates differ), and which of those pixels ``disparity`` puts on the near
    side (nearer the near candidate than the far one; ties count as far)."""
    reach = near > far
    return reach, reach & (disparity - far > near - disparity)


@dataclass(frozen=True)
class Placement:
    """How :func:`place_edges` moves pixels.

    Args:
        threshold: a pixel moves only where the network gives the other side at least this probability.
        tile: the tile side the network runs on (tiles with band pixels, boxes of them with a halo).
        min_region_px: moves in 8-connected regions smaller than this are dropped.
        attached: a region moves only where it touches the side it moves to (no islands, no holes).
        colour_margin: a pixel moves only where its colour is nearer the side it joins by this much
            (:func:`colour_allows`); None: no colour veto.
        passes: :func:`place_edges` runs again on the map it made, up to this many passes in all.
    """

    threshold: float = 0.9
    tile: int = 64
    min_region_px: int = 0
    attached: bool = False
    colour_margin: float | None = None
    passes: int = 1


def place_edges(model: EdgeNet, focus_srgb: np.ndarray, disparity: np.ndarray, blur: BlurParams,
                band: np.ndarray, keep: np.ndarray | None = None, placement: Placement = Placement()) -> np.ndarray:
    """The map with the network's segmentation applied where the band is open and the network is sure (one
    :func:`place_edges_once`), then again on the map it made, up to ``passes`` times in all (fewer where a pass moves
    nothing). Each pass reads the candidates and the sides' colour means of the map the last one made: a misplaced
    strip contaminates both until it is moved, so a second look finds what the first could not (docs/refiner.md,
    docs/design/edge-gate.md). The band stays the one given; ``keep`` marks pixels never moved (clipped lights)."""
    if placement.passes < 1:
        raise ValueError(f"passes must be >= 1, got {placement.passes}")
    out = disparity
    for _ in range(placement.passes):
        moved = place_edges_once(model, focus_srgb, out, blur, band, keep, placement)
        if moved is out or np.array_equal(moved, out):
            break
        out = moved
    return out


def place_edges_once(model: EdgeNet, focus_srgb: np.ndarray, disparity: np.ndarray, blur: BlurParams,
                     band: np.ndarray, keep: np.ndarray | None = None,
                     placement: Placement = Placement()) -> np.ndarray:
    """The map with the network's segmentation applied where the band is open and the network is sure: a pixel the
    map puts on the far side takes the near value where the near side's probability is at least
    ``placement.threshold``, and the other way round; ``keep`` marks pixels never moved (clipped lights). Moves in
    connected regions (8-connected) smaller than ``placement.min_region_px`` are dropped: a misplaced edge moves a
    strip, and a lone pixel moved into the near layer scatters its colour over a whole CoC disc. With
    ``placement.attached``, a region moves only where it touches the side it moves to (the near region grows or
    shrinks from its edge; no islands, no holes). With ``placement.colour_margin``, a pixel moves only where its
    colour is nearer the side it moves to by that much (:func:`colour_allows`).

    The network runs only on the tiles with band pixels, each box of them with a halo of its receptive field, so its
    output there is what it would be on the whole frame."""
    config, threshold, tile = model.config, placement.threshold, placement.tile
    h, w = disparity.shape
    near, far = candidates(disparity, config.radius_px)
    reach, on_near = map_sides(disparity, near, far)
    need_px = (band > 0) & reach
    if keep is not None:
        need_px &= ~keep
    if not need_px.any():
        return disparity
    ty, tx = -(-h // tile), -(-w // tile)
    padded = np.zeros((ty * tile, tx * tile), bool)
    padded[:h, :w] = need_px
    need = padded.reshape(ty, tile, tx, tile).any(axis=(1, 3))
    halo = config.reach_px
    feats = edge_features(focus_srgb, disparity, blur, band, config, (near, far))
    to_near = np.zeros((h, w), bool)
    to_far = np.zeros((h, w), bool)
    device = next(model.parameters()).device
    for (ty0, ty1, tx0, tx1), _ in refine_boxes(need, tile, halo):
        y0, y1 = ty0 * tile, min(ty1 * tile, h)
        x0, x1 = tx0 * tile, min(tx1 * tile, w)
        py0, py1, px0, px1 = max(y0 - halo, 0), min(y1 + halo, h), max(x0 - halo, 0), min(x1 + halo, w)
        with torch.no_grad():
            x = torch.from_numpy(np.ascontiguousarray(feats[:, py0:py1, px0:px1]))[None].to(device)
            p = torch.sigmoid(model(x))[0, 0].cpu().numpy()[y0 - py0:y1 - py0, x0 - px0:x1 - px0]
        sl = (slice(y0, y1), slice(x0, x1))
        to_near[sl] = need_px[sl] & ~on_near[sl] & (p >= threshold)
        to_far[sl] = need_px[sl] & on_near[sl] & (p <= 1.0 - threshold)
    if placement.colour_margin is not None:
        near_ok, far_ok = colour_allows(feats, placement.colour_margin)
        to_near &= near_ok
        to_far &= far_ok
    if placement.min_region_px > 1:
        to_near = _drop_small(to_near, placement.min_region_px)
        to_far = _drop_small(to_far, placement.min_region_px)
    if placement.attached:
        to_near = _touching(to_near, on_near & ~to_far)
        to_far = _touching(to_far, reach & ~on_near & ~to_near)
    return np.where(to_near, near, np.where(to_far, far, disparity))


def _touching(mask: np.ndarray, side: np.ndarray) -> np.ndarray:
    """``mask`` without its 8-connected regions that touch no pixel of ``side`` (8-neighbourhood)."""
    from scipy import ndimage

    labels, n = ndimage.label(mask, structure=np.ones((3, 3), bool))
    if n == 0:
        return mask
    touch = np.unique(labels[ndimage.binary_dilation(side, structure=np.ones((3, 3), bool)) & mask])
    keep = np.zeros(n + 1, bool)
    keep[touch] = True
    keep[0] = False
    return keep[labels]


def _drop_small(mask: np.ndarray, min_px: int) -> np.ndarray:
    """``mask`` without its 8-connected regions of fewer than ``min_px`` pixels."""
    from scipy import ndimage

    labels, n = ndimage.label(mask, structure=np.ones((3, 3), bool))
    if n == 0:
        return mask
    sizes = np.bincount(labels.ravel())
    sizes[0] = 0
    return sizes[labels] >= min_px


def save_edge_net(model: EdgeNet, path: str | os.PathLike, **metadata: str) -> None:
    """Weights as safetensors, the config in their metadata (``load_edge_net`` refuses weights that do not fit it)."""
    config = asdict(model.config)
    save_file({k: v.detach().contiguous().cpu() for k, v in model.state_dict().items()}, str(path),
              metadata={"config": json.dumps(config), "kind": "bokehray-edges", **metadata})


def load_edge_net(path: str | os.PathLike | None = None, device: str = "cpu") -> EdgeNet:
    """Load edge-network weights (default: the shipped ones); cached per file, modification time and device."""
    return load_saved(path, DEFAULT_EDGE_WEIGHTS, device, _build_edge_net, what="edge-network weights",
                      made_by="bokehray", how_to_make="train them with python -m bokehray_refiner.training.edges",
                      kind="bokehray-edges")


def _build_edge_net(config: dict) -> EdgeNet:
    return EdgeNet(EdgeConfig(**config))
