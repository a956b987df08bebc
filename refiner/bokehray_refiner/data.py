"""Training pairs for the refiner: exact targets, inputs rendered from *corrupted* disparity.

Depth estimators fail in characteristic ways around thin structures and object
edges: the near region is too fat (dilated) or too thin (eroded), edges are
smeared (blurred) or sit a few pixels off (shifted). :func:`corrupt_disparity`
imitates these; the classical preview is rendered from the corrupted map,
while the target stays the exact ray-traced render of the true scene. A share
of samples keeps the true map, so the model also learns to leave a correct
render alone.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from skimage.filters import gaussian
from tqdm import tqdm

from bokehray.colour import linear_to_srgb
from bokehray.data.datasets import BLBDataset, perturb_disparity
from bokehray.errors import InputError
from bokehray.lens import BlurParams
from bokehray.pipeline import render

__all__ = ["CORRUPTIONS", "CORRUPTION_PROBS", "EVAL_CORRUPTIONS", "PairBank", "corrupt_disparity"]

CORRUPTIONS = ("none", "erode", "dilate", "blur", "shift")
EVAL_CORRUPTIONS = CORRUPTIONS + ("estimator",)
"""Also accepted by :func:`corrupt_disparity` (evaluation only; training draws from :data:`CORRUPTIONS`)."""
CORRUPTION_PROBS = (0.35, 0.25, 0.25, 0.075, 0.075)
"""Default share of each corruption in :data:`CORRUPTIONS` order."""


def corrupt_disparity(d: np.ndarray, kind: str, amount: int, rng: np.random.Generator | None = None) -> np.ndarray:
    """Disparity with a depth estimator's typical error.

    Args:
        kind: ``"none"``; ``"erode"`` / ``"dilate"`` (grey-level, disc of radius ``amount`` px: near regions
            shrink / grow, paper fig. 7); ``"blur"`` (Gaussian, sigma ``amount`` / 2 px); ``"shift"`` (the
            map moves by up to ``amount`` px in a random direction: misaligned edges); ``"estimator"``
            (what a monocular depth network gives: the map area-averaged to 1/``amount`` resolution and
            upsampled bilinearly, so it is smooth and its edges sit up to ``amount / 2`` px off).
    """
    d = np.asarray(d, np.float32)
    if kind == "none" or amount == 0:
        return d.copy()
    if kind in ("erode", "dilate"):
        return perturb_disparity(d, -amount if kind == "erode" else amount)
    if kind == "blur":
        return gaussian(d, sigma=amount / 2.0, preserve_range=True).astype(np.float32)
    if kind == "shift":
        rng = rng or np.random.default_rng(0)
        a = rng.uniform(0, 2 * np.pi)
        dy, dx = int(round(amount * np.sin(a))), int(round(amount * np.cos(a)))
        p = amount
        return np.pad(d, p, mode="edge")[p - dy: p - dy + d.shape[0], p - dx: p - dx + d.shape[1]].copy()
    if kind == "estimator":
        from scipy import ndimage

        f = int(amount)
        h, w = d.shape
        hp, wp = -(-h // f) * f, -(-w // f) * f
        low = np.pad(d, ((0, hp - h), (0, wp - w)), mode="edge").reshape(hp // f, f, wp // f, f).mean(axis=(1, 3))
        yy = (np.arange(h, dtype=np.float32) + 0.5) / f - 0.5
        xx = (np.arange(w, dtype=np.float32) + 0.5) / f - 0.5
        grid = np.stack(np.meshgrid(yy, xx, indexing="ij"))
        return ndimage.map_coordinates(low, grid, order=1, mode="nearest").astype(np.float32)
    raise InputError(f"corruption: expected one of {EVAL_CORRUPTIONS}, got {kind!r}")


@dataclass
class Pair:
    focus: np.ndarray  #: H x W x 3 sRGB float16, all in focus
    target: np.ndarray  #: H x W x 3 sRGB float16, exact render
    renders: list[np.ndarray]  #: per variant, H x W x 3 sRGB float16 classical preview from the corrupted map
    disparities: list[np.ndarray]  #: per variant, H x W float16 corrupted disparity
    kinds: list[str]
    k_px: float
    focus_disparity: float


class PairBank:
    """Pairs of a BLB-layout folder, each with ``variants`` corrupted-depth preview renders, held in memory.

    Deterministic for a seed, so a resumed training run rebuilds the same bank.
    """

    def __init__(self, root: str, variants: int = 2, max_corruption_px: int = 5, seed: int = 0,
                 limit: int | None = None, progress: bool = True,
                 probs: tuple[float, ...] = CORRUPTION_PROBS):
        if len(probs) != len(CORRUPTIONS) or min(probs) < 0 or abs(sum(probs) - 1.0) > 1e-6:
            raise InputError(f"corruption probabilities: expected {len(CORRUPTIONS)} shares summing to 1, got {probs}")
        if max_corruption_px < 1:
            raise InputError(f"max_corruption_px: expected >= 1, got {max_corruption_px}")
        ds = BLBDataset(root)
        n = len(ds) if limit is None else min(limit, len(ds))
        rng = np.random.default_rng(seed)
        self.pairs: list[Pair] = []
        for i in tqdm(range(n), desc="rendering corrupted-depth inputs", disable=not progress, unit="pair"):
            s = ds[i]
            renders, disps, kinds = [], [], []
            for _ in range(variants):
                kind = str(rng.choice(CORRUPTIONS, p=list(probs)))
                amount = int(rng.integers(1, max_corruption_px + 1))
                dc = np.clip(corrupt_disparity(s.disparity, kind, amount, rng), 0.0, 1.0)
                r = render(s.image, dc, BlurParams(s.k_px, s.focus_disparity))
                renders.append(linear_to_srgb(np.clip(r, 0.0, 1.0)).astype(np.float16))
                disps.append(dc.astype(np.float16))
                kinds.append(kind)
            self.pairs.append(Pair(
                focus=linear_to_srgb(np.clip(s.image, 0.0, 1.0)).astype(np.float16),
                target=linear_to_srgb(np.clip(s.target, 0.0, 1.0)).astype(np.float16),
                renders=renders, disparities=disps, kinds=kinds,
                k_px=float(s.k_px), focus_disparity=float(s.focus_disparity)))
        if not self.pairs:
            raise InputError(f"{root}: no pairs")
        self.min_side = min(min(p.focus.shape[:2]) for p in self.pairs)

    def __len__(self) -> int:
        return len(self.pairs)

    def batch(self, rng: np.random.Generator, size: int, crop: int) -> dict[str, np.ndarray]:
        """A random batch of ``crop x crop`` crops (random pair, variant, position and left-right flip)."""
        if crop > self.min_side:
            raise InputError(f"crop {crop} is larger than the smallest image ({self.min_side} px)")
        out: dict[str, list] = {k: [] for k in ("focus", "render", "target", "disparity", "k_px", "focus_disparity")}
        for _ in range(size):
            p = self.pairs[int(rng.integers(len(self.pairs)))]
            v = int(rng.integers(len(p.renders)))
            h, w = p.focus.shape[:2]
            y, x = int(rng.integers(h - crop + 1)), int(rng.integers(w - crop + 1))
            flip = bool(rng.integers(2))
            sl = (slice(y, y + crop), slice(x, x + crop))
            for key, arr in (("focus", p.focus), ("render", p.renders[v]), ("target", p.target),
                             ("disparity", p.disparities[v])):
                a = arr[sl].astype(np.float32)
                out[key].append(a[:, ::-1].copy() if flip else a)
            out["k_px"].append(p.k_px)
            out["focus_disparity"].append(p.focus_disparity)
        return {k: np.stack(v) if k not in ("k_px", "focus_disparity") else np.array(v, np.float32)
                for k, v in out.items()}
