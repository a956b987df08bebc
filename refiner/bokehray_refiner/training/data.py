"""Training pairs for the refiner: exact targets, inputs rendered from *corrupted* disparity, exactly as at inference.

Depth maps fail in characteristic ways around thin structures and object edges. :func:`corrupt_disparity`
imitates them: a monocular estimator's map (low resolution, upsampled: smooth edges a few pixels off), edges
misplaced by 5-20 px *locally* (each stretch of edge in its own direction), thin structures missing from the map
entirely (hair, whiskers, stems narrower than a few pixels), near regions too fat or too thin, and the exact map
(to learn to leave a right render alone). The refiner's input is then made the way ``render --refine`` makes it:
the colour-guided depth correction (``bokehray_refiner.depthfix``) on the corrupted map, then the classical level (with
the soft scene) on the corrected map (:func:`bokehray_refiner.refine.correct_and_render`). The target stays the
exact ray-traced render of the true scene, and the loss counts only the edge band where ``refine`` keeps the
network's output (:func:`bokehray_refiner.refine.edge_band`).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from skimage.filters import gaussian
from tqdm import tqdm

from bokehray.colour import linear_to_srgb
from bokehray.data.datasets import BLBDataset, perturb_disparity
from bokehray.errors import InputError
from bokehray.lens import BlurParams
from bokehray.output.atomic import atomic_write
from bokehray.pipeline import render

__all__ = ["AMOUNTS", "CORRUPTIONS", "CORRUPTION_PROBS", "EVAL_CORRUPTIONS", "PairBank", "corrupt_disparity"]

CORRUPTIONS = ("none", "erode", "dilate", "blur", "shift", "estimator", "local", "missing")
EVAL_CORRUPTIONS = CORRUPTIONS
"""Every kind :func:`corrupt_disparity` knows (kept as a name for the benchmarks)."""
CORRUPTION_PROBS = (0.2, 0.05, 0.05, 0.0, 0.0, 0.2, 0.25, 0.25)
"""Default share of each corruption in :data:`CORRUPTIONS` order: the failures the depth fix cannot undo
(locally misplaced edges, an estimator's map, missing thin structures) weighted up, the exact map kept."""
AMOUNTS = {"none": (0, 0), "erode": (1, 5), "dilate": (1, 5), "blur": (1, 5), "shift": (1, 5),
           "estimator": (3, 8), "local": (5, 20), "missing": (1, 4)}
"""The range of ``amount`` (inclusive) a training variant draws for each kind."""


def _local_warp(d: np.ndarray, amount: int, rng: np.random.Generator) -> np.ndarray:
    """The map resampled (nearest neighbour: edges stay steps) through a smooth random displacement field whose
    vectors, one per ~48 px cell and interpolated between, have lengths of 0.5-1 x ``amount`` px in random
    directions: every stretch of edge moves its own way."""
    from scipy import ndimage

    h, w = d.shape
    gy, gx = max(2, round(h / 48) + 1), max(2, round(w / 48) + 1)
    length = rng.uniform(0.5, 1.0, (gy, gx)) * amount
    angle = rng.uniform(0, 2 * np.pi, (gy, gx))
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    cy, cx = yy * (gy - 1) / max(h - 1, 1), xx * (gx - 1) / max(w - 1, 1)
    dy = ndimage.map_coordinates(length * np.sin(angle), [cy, cx], order=3, mode="nearest")
    dx = ndimage.map_coordinates(length * np.cos(angle), [cy, cx], order=3, mode="nearest")
    return ndimage.map_coordinates(d, [yy + dy, xx + dx], order=0, mode="nearest").astype(np.float32)


def _disc(radius: int) -> np.ndarray:
    r = np.arange(-radius, radius + 1)
    return (r[:, None] ** 2 + r[None, :] ** 2) <= radius * radius + radius


def corrupt_disparity(d: np.ndarray, kind: str, amount: int, rng: np.random.Generator | None = None) -> np.ndarray:
    """Disparity with a depth map's typical error.

    Args:
        kind: ``"none"``; ``"erode"`` / ``"dilate"`` (grey-level, disc of radius ``amount`` px: near regions
            shrink / grow, paper fig. 7); ``"blur"`` (Gaussian, sigma ``amount`` / 2 px); ``"shift"`` (the
            map moves by up to ``amount`` px in a random direction: misaligned edges); ``"estimator"``
            (what a monocular depth network gives: the map area-averaged to 1/``amount`` resolution and
            upsampled bilinearly, so it is smooth and its edges sit up to ``amount / 2`` px off); ``"local"``
            (edges misplaced by up to ``amount`` px, each stretch in its own direction: a smooth random warp);
            ``"missing"`` (a grey opening with a disc of radius ``amount``: near structures narrower than
            ``2 amount + 1`` px, strands and whiskers, vanish into what is behind them; large regions keep
            their outline).
        rng: draws the random kinds (``shift``, ``local``); default a fixed seed.
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
    if kind == "local":
        return _local_warp(d, int(amount), rng or np.random.default_rng(0))
    if kind == "missing":
        from scipy import ndimage

        return ndimage.grey_opening(d, footprint=_disc(int(amount)), mode="nearest").astype(np.float32)
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
    raise InputError(f"corruption: expected one of {CORRUPTIONS}, got {kind!r}")


@dataclass
class Pair:
    focus: np.ndarray  #: H x W x 3 sRGB float16, all in focus (shared by the pairs of one scene)
    target: np.ndarray  #: H x W x 3 sRGB float16, exact render
    renders: list[np.ndarray]  #: per variant, H x W x 3 sRGB float16: the level on the corrected map
    disparities: list[np.ndarray]  #: per variant, H x W float16: the corrected map (what the network sees)
    bands: list[np.ndarray]  #: per variant, H x W float16: where refine keeps the network's output (its weight:
    #: the edge band, times the confidence gate in a ``gated`` bank)
    kinds: list[str]
    k_px: float
    focus_disparity: float


BANK_VERSION = 3
"""Bumped when the way inputs are made changes; a cached bank of another version is rebuilt."""


class PairBank:
    """Pairs of a BLB-layout folder, each with ``variants`` corrupted-depth inputs, held in memory.

    For each scene, blur level ``K`` and variant, one corruption is drawn (kind with the shares ``probs``, amount
    from :data:`AMOUNTS`), then at each focus of the scene corrected and rendered as ``render --refine`` would
    (:func:`bokehray_refiner.refine.correct_and_render`: the depth fix depends on ``K`` alone, but the map-level
    gate's disagreement and the edge network read the CoC, which depends on the focus). Deterministic for a seed,
    so a resumed training run rebuilds the same bank; :meth:`cached` keeps it on disk.

    Each input's weight (``bands``) is the edge band where refine keeps the network's output; with ``gated`` it is
    also multiplied by the confidence gate, exactly the weight refine blends by
    (:func:`bokehray_refiner.refine.blend_weight`), so the loss counts only what the network will be let change.
    """

    def __init__(self, root: str, variants: int = 2, seed: int = 0, limit: int | None = None,
                 progress: bool = True, probs: tuple[float, ...] = CORRUPTION_PROBS, gated: bool = False):
        from bokehray_refiner.gate import GateOptions
        from bokehray_refiner.refine import RefineOptions, blend_weight, correct_and_render

        if len(probs) != len(CORRUPTIONS) or min(probs) < 0 or abs(sum(probs) - 1.0) > 1e-6:
            raise InputError(f"corruption probabilities: expected {len(CORRUPTIONS)} shares summing to 1, got {probs}")
        if variants < 1:
            raise InputError(f"variants: expected >= 1, got {variants}")
        ds = BLBDataset(root)
        n = len(ds) if limit is None else min(limit, len(ds))
        rng = np.random.default_rng(seed)
        opts = RefineOptions()
        # the loss weight is refine's blend weight, with the gate open everywhere unless ``gated``
        weight_opts = opts if gated else RefineOptions(gate=GateOptions(enabled=False))
        self.pairs: list[Pair] = []
        scene_of, key_of = None, None  # the scene, and the scene and K, whose pairs are being rendered
        for i in tqdm(range(n), desc="rendering corrupted-depth inputs", disable=not progress, unit="pair"):
            s = ds[i]
            scene = s.name.split("/")[0]
            if scene != scene_of:
                scene_of = scene
                focus_full = linear_to_srgb(np.clip(s.image, 0.0, 1.0))
                focus16 = focus_full.astype(np.float16)
            if (scene, float(s.k_px)) != key_of:  # the corrupted maps of this scene and K, for every focus
                key_of = (scene, float(s.k_px))
                variants_of = []  # (kind, corrupted map)
                for _ in range(variants):
                    kind = str(rng.choice(CORRUPTIONS, p=list(probs)))
                    lo, hi = AMOUNTS[kind]
                    amount = int(rng.integers(lo, hi + 1))
                    variants_of.append((kind, np.clip(corrupt_disparity(s.disparity, kind, amount, rng), 0.0, 1.0)))
            renders, disps, bands, kinds = [], [], [], []
            blur = BlurParams(s.k_px, s.focus_disparity)
            for kind, dc in variants_of:
                r, dfix = correct_and_render(s.image, dc, blur, lambda d, s=s, blur=blur: render(s.image, d, blur), opts)
                coc = blur.signed_coc(dfix).astype(np.float32)
                band = blend_weight(s.image, focus_full, dfix, r, coc, weight_opts)[1]
                renders.append(linear_to_srgb(np.clip(r[..., :3], 0.0, 1.0)).astype(np.float16))
                disps.append(dfix.astype(np.float16))
                bands.append(band.astype(np.float16))
                kinds.append(kind)
            self.pairs.append(Pair(
                focus=focus16, target=linear_to_srgb(np.clip(s.target, 0.0, 1.0)).astype(np.float16),
                renders=renders, disparities=disps, bands=bands, kinds=kinds,
                k_px=float(s.k_px), focus_disparity=float(s.focus_disparity)))
        if not self.pairs:
            raise InputError(f"{root}: no pairs")
        self._finish()

    def _finish(self) -> None:
        self.min_side = min(min(p.focus.shape[:2]) for p in self.pairs)
        self._band_px = [[np.flatnonzero(b > 0) for b in p.bands] for p in self.pairs]

    @classmethod
    def cached(cls, path: str | Path, root: str, progress: bool = True, **kw) -> PairBank:
        """The bank of ``PairBank(root, **kw)``, read from ``path`` when that file was written for the same
        folder, arguments and code version (and its first input still renders the same), else built and written
        there (atomically)."""
        path = Path(path)
        key = json.dumps({"root": str(Path(root).resolve()), "version": BANK_VERSION, "pairs": len(BLBDataset(root)),
                          **{k: list(v) if isinstance(v, tuple) else v for k, v in sorted(kw.items())}},
                         sort_keys=True)
        if path.is_file():
            bank = cls._read(path, key)
            if bank is not None and bank._same_first_input(root, kw):
                return bank
        bank = cls(root, progress=progress, **kw)
        atomic_write(path, lambda tmp: bank._write(tmp, key))
        return bank

    def _same_first_input(self, root: str, kw: dict) -> bool:
        first = PairBank(root, progress=False, **(kw | {"limit": 1}))
        return np.array_equal(first.pairs[0].renders[0], self.pairs[0].renders[0])

    def _write(self, tmp: str, key: str) -> None:
        arrays: dict[str, np.ndarray] = {}
        meta = []
        focus_ids: dict[int, int] = {}
        for i, p in enumerate(self.pairs):
            fid = focus_ids.setdefault(id(p.focus), len(focus_ids))
            if f"focus_{fid}" not in arrays:
                arrays[f"focus_{fid}"] = p.focus
            arrays[f"target_{i}"] = p.target
            for v in range(len(p.renders)):
                arrays[f"render_{i}_{v}"] = p.renders[v]
                arrays[f"disparity_{i}_{v}"] = p.disparities[v]
                arrays[f"band_{i}_{v}"] = p.bands[v]
            meta.append({"focus": fid, "kinds": p.kinds, "k_px": p.k_px, "focus_disparity": p.focus_disparity})
        arrays["meta"] = np.frombuffer(json.dumps({"key": key, "pairs": meta}).encode(), np.uint8)
        with open(tmp, "wb") as fh:
            np.savez(fh, **arrays)

    @classmethod
    def _read(cls, path: Path, key: str) -> PairBank | None:
        try:
            with np.load(path) as z:
                meta = json.loads(bytes(z["meta"]).decode())
                if meta["key"] != key:
                    return None
                bank = cls.__new__(cls)
                focus = {}
                bank.pairs = []
                for i, m in enumerate(meta["pairs"]):
                    if m["focus"] not in focus:
                        focus[m["focus"]] = z[f"focus_{m['focus']}"]
                    nv = len(m["kinds"])
                    bank.pairs.append(Pair(
                        focus=focus[m["focus"]], target=z[f"target_{i}"],
                        renders=[z[f"render_{i}_{v}"] for v in range(nv)],
                        disparities=[z[f"disparity_{i}_{v}"] for v in range(nv)],
                        bands=[z[f"band_{i}_{v}"] for v in range(nv)],
                        kinds=list(m["kinds"]), k_px=float(m["k_px"]), focus_disparity=float(m["focus_disparity"])))
        except (OSError, KeyError, ValueError):
            return None
        bank._finish()
        return bank

    def __len__(self) -> int:
        return len(self.pairs)

    def batch(self, rng: np.random.Generator, size: int, crop: int, edge_share: float = 0.0) -> dict[str, np.ndarray]:
        """A random batch of ``crop x crop`` crops (random pair, variant, position and left-right flip); ``exact``
        marks the crops whose input was rendered on the exact map.

        ``edge_share``: the share of crops centred on a random pixel of the variant's edge band (where the loss
        counts), the rest placed uniformly.
        """
        if crop > self.min_side:
            raise InputError(f"crop {crop} is larger than the smallest image ({self.min_side} px)")
        keys = ("focus", "render", "target", "disparity", "band", "k_px", "focus_disparity", "exact")
        out: dict[str, list] = {k: [] for k in keys}
        for _ in range(size):
            i = int(rng.integers(len(self.pairs)))
            p = self.pairs[i]
            v = int(rng.integers(len(p.renders)))
            h, w = p.focus.shape[:2]
            band_px = self._band_px[i][v]
            if edge_share > 0 and band_px.size and rng.random() < edge_share:
                cy, cx = divmod(int(band_px[rng.integers(band_px.size)]), w)
                y = int(np.clip(cy - crop // 2, 0, h - crop))
                x = int(np.clip(cx - crop // 2, 0, w - crop))
            else:
                y, x = int(rng.integers(h - crop + 1)), int(rng.integers(w - crop + 1))
            flip = bool(rng.integers(2))
            sl = (slice(y, y + crop), slice(x, x + crop))
            for key, arr in (("focus", p.focus), ("render", p.renders[v]), ("target", p.target),
                             ("disparity", p.disparities[v]), ("band", p.bands[v])):
                a = arr[sl].astype(np.float32)
                out[key].append(a[:, ::-1].copy() if flip else a)
            out["k_px"].append(p.k_px)
            out["focus_disparity"].append(p.focus_disparity)
            out["exact"].append(p.kinds[v] == "none")
        scalars = {"k_px": np.float32, "focus_disparity": np.float32, "exact": bool}
        return {k: np.array(v, scalars[k]) if k in scalars else np.stack(v) for k, v in out.items()}
