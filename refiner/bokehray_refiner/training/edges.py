"""The edge network's recipe: ``python -m bokehray_refiner.training.edges`` rebuilds ``weights/edges.safetensors``.

Training pairs come from a BLB folder (``bokehray synth``). Each pair's map is corrupted ``--variants`` ways as real
maps are wrong (the exact map; edges misplaced locally by 5-20 px; a monocular estimator's map at 1/3 to 1/8
resolution; a grey opening of radius 1-3 px, so that strands narrower than 3-7 px go missing; near regions grown or
shrunk by 2-6 px), each with its own random draw, then put through the colour-guided depth correction as refine does
(the bank). The network learns, per pixel of the edge band, which side of the edge the pixel is on: the side (near or
far candidate) whose CoC is nearer the true map's. Its loss is the binary cross-entropy against that side, each pixel
weighted by the band, by the CoC span between the candidates (0 to 1 at 4 px) and ``--exact-weight`` on the exact
maps.

The shipped weights (``weights/edges.json`` says how and what they are)::

    bokehray synth -n 80 -o data/train --seed 2000 --size 256 --blur-levels 8,16,24 --depth-rule half \\
        --kinds strands=3,fur=2,whiskers=1,foliage=2,mesh=1,softcut=1.5,cutout=1,lights=1
    python -m bokehray_refiner.training.edges data/train --bank data/edges_bank.npz \\
        --checkpoint data/edges_run.pt --export data/edges.safetensors

The variants measured and not shipped (a loss priced by the render, training on the maps refine runs the network
on, a wider network) and the scoring in the whole pipeline are in research/refiner_edges/.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from contextlib import contextmanager
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from .common import Checkpoints, optimise, region, resume, srgb_photo

__all__ = ["TRAIN_CORRUPTIONS", "EdgeRecipe", "bank", "load_bank", "main", "network_runs", "side_costs", "side_labels", "train",
           "used_map"]


TRAIN_CORRUPTIONS = (("none", 0, 0), ("local", 5, 20), ("estimator", 3, 8), ("missing", 1, 3),
                     ("erode", 2, 6), ("dilate", 2, 6))
"""(kind, smallest amount, largest amount) of each corruption a training map may get."""


def fix(image, disparity, blur, opts, focus=None):
    """The depth fix as refine runs it before the edge network, on every map (``min_fixed_share=0``): the one
    correction :func:`used_map` and :func:`network_runs` both read. ``focus``: the sRGB photo, when made."""
    from bokehray_refiner.refine import _corrected

    return _corrected(image, disparity, blur, replace(opts, edges=False, min_fixed_share=0.0), None, focus)


def used_map(c, blur, opts):
    """The depth fix's map (what the edge network is given), the band refine would open on it, and the pixels the
    fix moved, from its correction ``c`` (:func:`fix`). Every map is corrected: the bank the shipped weights were
    trained on was made so, before refine held back the maps the fix finds right; the caller decides which maps the
    network runs on (:func:`network_runs`)."""
    from bokehray_refiner.refine import edge_band, edge_reach

    used = np.asarray(c.disparity, np.float32)
    reach = edge_reach(blur.signed_coc(used).astype(np.float32), opts.min_jump_px)
    return used, edge_band(reach, opts.band_margin_px, opts.band_feather_px), c.changed


def side_costs(used: np.ndarray, truth: np.ndarray, blur, config, cap_px: float = 8.0) -> np.ndarray:
    """Per pixel, how far (CoC px, capped) the true map is from keeping ``used``, from its near candidate and from its
    far one (``3 x H x W``): the true side is the nearer candidate (:func:`side_labels`)."""
    from bokehray_refiner.edges import candidates

    near, far = candidates(used, config.radius_px)
    t = blur.signed_coc(truth)
    return np.minimum(np.stack([np.abs(blur.signed_coc(m) - t) for m in (used, near, far)]), cap_px)


def map_on_near(x):
    """Where the map puts each pixel on the near side (torch, from the inputs ``B x N_INPUTS x H x W``, which hold
    near - c and far - c): c - far > near - c, as ``bokehray_refiner.edges.map_sides`` decides it."""
    return (-x[:, 5] > x[:, 4]).float()


def side_labels(cost, x, config, keep_margin: float | None = None):
    """From a bank entry's costs and inputs (torch, ``B x 3 x H x W`` and ``B x N_INPUTS x H x W``): the true side
    (1: near, the near candidate is nearer the true CoC than the far one) and how much it counts: the CoC span
    between the candidates, 0 to 1 at 4 px (none where no edge is in reach).

    With ``keep_margin`` (CoC px), the true side is the map's own wherever keeping the map's value is nearer the true
    CoC than either candidate by that much: a pixel of a third layer between the two (a card between a leaf and the
    background) belongs to neither candidate, and the network's one way to leave it alone is to agree with the map.
    """
    near_side = (cost[:, 1] < cost[:, 2]).float()
    if keep_margin is not None:
        keep = cost[:, 0] + keep_margin < cost[:, 1].minimum(cost[:, 2])
        near_side = near_side.where(~keep, map_on_near(x))
    span = ((x[:, 4] - x[:, 5]) * config.coc_scale_px / 4.0).clamp(0.0, 1.0)
    return near_side, span


def _bank_maps(root: str, variants: int, seed: int):
    """The bank's corrupted maps in order: per training pair ``variants`` of them, the exact one, then the other
    kinds in turn (a random amount each), as (sample, its blur, the sRGB photo, the kind, the corrupted map)."""
    import bokehray as br
    from bokehray.data.datasets import BLBDataset
    from bokehray_refiner.training.data import corrupt_disparity

    rng = np.random.default_rng(seed)
    ds = BLBDataset(root)
    for i in range(len(ds)):
        s = ds[i]
        blur = br.BlurParams(s.k_px, s.focus_disparity)
        focus = srgb_photo(s.image)
        kinds = [TRAIN_CORRUPTIONS[0]] + [TRAIN_CORRUPTIONS[1 + (i + j) % (len(TRAIN_CORRUPTIONS) - 1)]
                                          for j in range(variants - 1)]
        for kind, lo, hi in kinds:
            amount = int(rng.integers(lo, hi + 1))
            yield s, blur, focus, kind, np.clip(corrupt_disparity(s.disparity, kind, amount, rng), 0.0, 1.0)
        if (i + 1) % 50 == 0:
            print(f"bank: {i + 1}/{len(ds)} pairs", flush=True)


def bank(root: str, variants: int, seed: int, opts, config) -> list[dict]:
    """The bank (:func:`_bank_maps`): per map the network's inputs (float16), each choice's cost, whether the map is
    exact and whether refine would run the network on it (:func:`network_runs`)."""
    from bokehray_refiner.edges import N_BASE, edge_features

    out = []
    for s, blur, focus, kind, d in _bank_maps(root, variants, seed):
        c = fix(s.image, d, blur, opts, focus)
        used, band, _ = used_map(c, blur, opts)
        out.append({"x": edge_features(focus, used, blur, band, config)[:N_BASE].astype(np.float16),
                    "cost": side_costs(used, s.disparity, blur, config).astype(np.float16),
                    "exact": kind == "none", "runs": network_runs(c, focus, blur, opts, used, band)[0]})
    return out


@dataclass(frozen=True)
class EdgeRecipe:
    """The training loop's settings; the defaults are the shipped weights' (``weights/edges.json``).

    Args:
        steps, batch, crop, seed: AdamW steps of ``batch`` crops of ``crop`` px (the loss counts the crop; the network
            sees its receptive field around it too), drawn with ``seed``.
        exact_weight: the loss weight of the exact maps (where any move is harm).
        lr: the learning rate's peak (one cycle).
        price: with ``price`` > 0 (sRGB), each pixel also weighted by :func:`render_price` (measured, not shipped).
        keep_margin: as in :func:`side_labels` (measured, not shipped).
        log_every: steps between printed loss lines.
    """

    steps: int = 4000
    batch: int = 8
    crop: int = 64
    seed: int = 0
    exact_weight: float = 2.0
    lr: float = 2e-3
    price: float = 0.0
    keep_margin: float | None = None
    log_every: int = 100


def _training_crop(e: dict, rng, crop: int, reach: int) -> tuple[np.ndarray, np.ndarray]:
    """A random crop of the bank entry ``e`` (on the band 9 times in 10) with its receptive field around it, flipped
    and transposed at random: the inputs and (the costs, then where they count)."""
    band = e["x"][6]
    h, w = band.shape
    ys, xx = np.nonzero(band > 0)
    if len(ys) and rng.random() < 0.9:
        j = rng.integers(len(ys))
        y0, x0 = int(np.clip(ys[j] - crop // 2, 0, h - crop)), int(np.clip(xx[j] - crop // 2, 0, w - crop))
    else:
        y0, x0 = int(rng.integers(0, h - crop + 1)), int(rng.integers(0, w - crop + 1))
    # the loss counts the crop; the network sees its receptive field around it too, as on a whole frame
    # (zeros beyond the frame's edges, as there): no output it is trained on sees padding a frame lacks
    x = region(e["x"], y0 - reach, x0 - reach, crop + 2 * reach, lead=1)
    c = np.zeros((4, crop + 2 * reach, crop + 2 * reach), np.float16)  # the costs, then where they count
    c[:3, reach:reach + crop, reach:reach + crop] = e["cost"][:, y0:y0 + crop, x0:x0 + crop]
    c[3, reach:reach + crop, reach:reach + crop] = 1.0
    flip = rng.integers(0, 8)
    if flip & 1:
        x, c = x[:, ::-1], c[:, ::-1]
    if flip & 2:
        x, c = x[:, :, ::-1], c[:, :, ::-1]
    if flip & 4:
        x, c = x.transpose(0, 2, 1), c.transpose(0, 2, 1)
    return np.ascontiguousarray(x, np.float32), np.ascontiguousarray(c, np.float32)


def _model(config, recipe: EdgeRecipe, init):
    """A fresh :class:`EdgeNet` of ``config`` (seeded; ``init``'s weights, if given), AdamW and its one cycle."""
    import torch

    from bokehray_refiner.edges import EdgeNet

    torch.manual_seed(recipe.seed)
    rng = np.random.default_rng(recipe.seed)
    model = EdgeNet(config)
    if init is not None:
        model.load_state_dict(init.state_dict())
    opt = torch.optim.AdamW(model.parameters(), lr=recipe.lr, weight_decay=1e-4)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=recipe.lr, total_steps=recipe.steps,
                                                pct_start=min(0.3, max(0.05, 10 / recipe.steps)))
    return {"model": model, "opt": opt, "sched": sched}, rng


def train(entries: list[dict], config, recipe: EdgeRecipe = EdgeRecipe(), checkpoint: str | None = None,
          checkpoint_every: int = 500, init=None):
    """AdamW on the binary cross-entropy against the true side (:func:`side_labels`), on random crops on the band
    (:func:`_training_crop`), each pixel weighted by the band, the candidates' CoC span and ``recipe.exact_weight``
    on exact maps; the learning rate rises to ``recipe.lr`` and falls (one cycle); ``init``: an :class:`EdgeNet` of
    ``config`` to start from, else a fresh one. With ``checkpoint``, written every ``checkpoint_every`` steps and
    resumed bit for bit (:mod:`.common`). Returns the model and the losses."""
    import torch
    import torch.nn.functional as F

    r = recipe
    parts, rng = _model(config, r, init)
    checkpoints = Checkpoints(checkpoint, r.steps, r.seed, checkpoint_every)
    losses, start = resume(checkpoints, parts, rng)
    wrong_seen: list[float] = []
    map_wrong = _map_wrong(entries, r.exact_weight, config, r.keep_margin)
    for step in range(start, r.steps):
        xs, costs, ws = [], [], []
        for i in rng.integers(0, len(entries), r.batch):
            x, c = _training_crop(entries[i], rng, r.crop, config.reach_px)
            xs.append(x)
            costs.append(c)
            ws.append(r.exact_weight if entries[i]["exact"] else 1.0)
        x = torch.from_numpy(np.stack(xs))
        cost = torch.from_numpy(np.stack(costs))
        cost, counted = cost[:, :3], cost[:, 3]
        weight = x[:, 6] * counted * torch.tensor(ws)[:, None, None]
        logit = parts["model"](x)[:, 0]
        label, span = side_labels(cost, x, config, r.keep_margin)
        weight = weight * span
        priced = weight * render_price(x, r.price) if r.price > 0 else weight
        loss = (F.binary_cross_entropy_with_logits(logit, label, reduction="none") * priced).sum() \
            / priced.sum().clamp_min(1.0)
        with torch.no_grad():  # the share of counted pixels put on the wrong side at 0.5 (unpriced, as the map's)
            wrong_seen.append(float((((logit > 0).float() != label).float() * weight).sum()
                                    / weight.sum().clamp_min(1.0)))
        optimise(loss, step, parts, losses, rng, checkpoints)
        if (step + 1) % r.log_every == 0:
            print(f"step {step + 1}: loss {np.mean(losses[-r.log_every:]):.4f}, wrong side "
                  f"{np.mean(wrong_seen[-r.log_every:]):.3f} (the map's: {map_wrong:.3f})", flush=True)
    return parts["model"], losses


def render_price(x, scale: float):
    """What putting a pixel on the wrong side costs the render, relative (torch, ``B x H x W`` from the inputs
    ``B x N_INPUTS x H x W``): the squared colour step between the two sides' local means over ``scale`` squared,
    clamped to [1/20, 4]. The pixel's light lands on the wrong disc, so its error is its side's colour less the
    other's, and PSNR counts it squared; an edge with no colour step costs the render nothing whichever side a pixel
    takes."""
    from bokehray_refiner.edges import N_BASE

    # the two sides' local means differ by (photo - far mean) - (photo - near mean)
    step = (x[:, N_BASE + 3:N_BASE + 6] - x[:, N_BASE:N_BASE + 3]).square().sum(1)
    return (step / scale ** 2).clamp(0.05, 4.0)


def _map_wrong(entries: list[dict], exact_weight: float, config, keep_margin: float | None = None) -> float:
    """The share of counted pixels the given maps themselves put on the wrong side (what a network that keeps every
    map scores)."""
    import torch

    wrong = total = 0.0
    for e in entries:
        x, cost = torch.from_numpy(e["x"][None].astype(np.float32)), torch.from_numpy(e["cost"][None].astype(np.float32))
        label, span = side_labels(cost, x, config, keep_margin)
        on_near = map_on_near(x)
        w = x[:, 6] * span * (exact_weight if e["exact"] else 1.0)
        wrong += float(((on_near != label).float() * w).sum())
        total += float(w.sum())
    return wrong / max(total, 1.0)


def network_runs(c, focus, blur, opts, used=None, band=None) -> tuple[bool, float | None]:
    """Whether refine runs the edge network on the map the depth fix made of a corrupted one (``c``, :func:`fix`),
    decided as refine does: its local passes moved at least ``min_fixed_share`` of the band (a global shift not
    counted) and left disagreement (``edge_min_disagreement``); and that share (None: the fix did not run).
    ``used``, ``band``: :func:`used_map` of ``c``, when made. On every map ``c`` is the map refine's own correction
    makes where it finds the map wrong, so the share decides as refine's ``min_fixed_share`` does."""
    from bokehray_refiner.refine import disagreement

    if not c.found_wrong or (opts.min_fixed_share > 0 and (c.share is None or c.share < opts.min_fixed_share)):
        return False, c.share
    if opts.edge_min_disagreement <= 0:
        return True, c.share
    if used is None:
        used, band, _ = used_map(c, blur, opts)
    coc = blur.signed_coc(used).astype(np.float32)
    return disagreement(focus, used, coc, band, None, opts) >= opts.edge_min_disagreement, c.share


def _save_bank(path: str, entries: list[dict]) -> None:
    """Write the bank whole or not at all (a stopped write leaves the one before)."""
    tmp = f"{path}.partial"
    with open(tmp, "wb") as f:
        np.savez(f, n=len(entries), **{f"{i}_{k}": v for i, e in enumerate(entries) for k, v in e.items()})
    os.replace(tmp, path)


def load_bank(path: str | None, root: str, variants: int, seed: int, opts, config) -> list[dict]:
    """The bank at ``path`` if written, else made from ``root`` (:func:`bank`) and written there."""
    if path and Path(path).is_file():
        with np.load(path) as z:
            return [{k: z[f"{i}_{k}"] for k in ("x", "cost", "exact", "runs") if f"{i}_{k}" in z}
                    for i in range(int(z["n"]))]
    entries = bank(root, variants, seed, opts, config)
    if path:
        _save_bank(path, entries)
    return entries


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="python -m bokehray_refiner.training.edges",
                                 description=__doc__.splitlines()[0])
    ap.add_argument("train", help="BLB folder to train on (bokehray synth; the recipe's command is above)")
    ap.add_argument("--export", required=True, help="write the trained network here (safetensors, with its JSON)")
    ap.add_argument("--bank", default=None, help="cache of the training inputs (.npz): read if present, else written")
    ap.add_argument("--checkpoint", default=None,
                    help="the training state, written every --checkpoint-every steps; an existing one is resumed")
    ap.add_argument("--checkpoint-every", type=int, default=500)
    ap.add_argument("--variants", type=int, default=5, help="corrupted maps per training pair (the first exact)")
    ap.add_argument("--steps", type=int, default=4000)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--crop", type=int, default=64,
                    help="side of the crop the loss counts (the network sees its receptive field around it too)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--exact-weight", type=float, default=2.0, help="loss weight of the exact maps")
    ap.add_argument("--lr", type=float, default=2e-3, help="the learning rate's peak (one cycle)")
    ap.add_argument("--width", type=int, default=32)
    ap.add_argument("--dilations", default="2,4,8,1", help="the hidden 3 x 3 convolutions' dilations")
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    return ap


@contextmanager
def _torch_settings(threads: int | None):
    """The recipe's torch settings (denormals flushed to zero, as the shipped weights were trained; ``threads``),
    restored afterwards: the process may go on (a test, a notebook)."""
    import torch

    before = torch.get_num_threads()
    if threads:
        torch.set_num_threads(threads)
    torch.set_flush_denormal(True)
    try:
        yield
    finally:
        torch.set_flush_denormal(False)
        torch.set_num_threads(before)


def _make(args: argparse.Namespace) -> int:
    """The bank, the training and the export, as :func:`main` parsed them."""
    from bokehray.errors import InputError
    from bokehray_refiner.edges import EdgeConfig, colour_features, save_edge_net
    from bokehray_refiner.refine import RefineOptions

    config = EdgeConfig(width=args.width, dilations=tuple(int(v) for v in args.dilations.split(",")))
    t = time.perf_counter()
    try:
        entries = load_bank(args.bank, args.train, args.variants, args.seed, RefineOptions(), config)
    except InputError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    for e in entries:  # the bank keeps the first channels; the colour models are made from them
        e["x"] = np.concatenate([e["x"], colour_features(e["x"].astype(np.float32)).astype(np.float16)])
    print(f"bank: {len(entries)} maps in {time.perf_counter() - t:.0f} s", flush=True)
    t = time.perf_counter()
    recipe = EdgeRecipe(steps=args.steps, batch=args.batch, crop=args.crop, seed=args.seed,
                        exact_weight=args.exact_weight, lr=args.lr)
    model, _ = train(entries, config, recipe, args.checkpoint, args.checkpoint_every)
    model.eval()
    save_edge_net(model, args.export, steps=str(args.steps), seed=str(args.seed))
    print(f"trained {args.steps} steps in {time.perf_counter() - t:.0f} s; wrote {args.export}", flush=True)
    return 0


def main(argv: list[str] | None = None) -> int:
    """Make the bank, train, export: the shipped weights with the defaults."""
    args = _parser().parse_args(argv)
    if not Path(args.train).is_dir():
        print(f"error: {args.train}: no such training folder (make it with the bokehray synth command of --help)",
              file=sys.stderr)
        return 2
    with _torch_settings(args.threads):
        return _make(args)


if __name__ == "__main__":
    sys.exit(main())
