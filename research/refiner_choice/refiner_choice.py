"""A learned choice among renders: how much of a perfect choice's gain a small network reaches.

``refiner_headroom.py --choices`` bounds what choosing, per pixel of the edge band, among the level rendered on the
corrected map and on it with its near regions grown and shrunk by 3, 6 and 12 px could gain (an oracle that sees the
exact render). This script trains a small convolutional network to make that choice from what refine has at
inference (the all-in-focus photo, the seven renders, the band) and scores it beside the oracle, per corruption of
``bench_refiner.NET_CONDITIONS``, in the score band of the true depth (as ``bench_refiner.py``):

* ``fix``: the depth fix's render (what refine starts from, ``RefineOptions(neural=False)``);
* ``learned``: the network's choice, blended by the band (``fix`` where the band is 0);
* ``oracle``: the perfect choice (each pixel the render whose 5 x 5 px mean error is least), blended by the band.

Training pairs come from a BLB folder (``bokehray synth``); each pair gets one corrupted map: the exact one for
``--exact-share`` of them (where the right choice is the render as it is; loss weight ``--exact-weight``), else one
of the three corruptions. Each score is also given behind refine's confidence gate (``learned_gated``). With
``--alignment`` the chooser also sees, per candidate map, how well its depth edges run along the photo's colour edges
(:func:`edge_alignment`). A research
measurement: refine does not use the choice (seven renders of the level are over the refine pass's 3x budget;
docs/refiner.md, "A learned choice among renders").

    bokehray synth -n 80 -o data/train --seed 2000 --size 256 --blur-levels 8,16,24 --depth-rule half \\
        --kinds strands=3,fur=2,whiskers=1,foliage=2,mesh=1,softcut=1.5,cutout=1,lights=1
    bokehray synth -n 12 -o data/heldout --seed 9000 ... (the same kinds)
    python research/refiner_choice/refiner_choice.py --train data/train --heldout data/heldout \\
        --devset ../shared/data/pathtraced-dev --steps 1500 --exact-share 0.4 --exact-weight 3 --save data/chooser.pt
    python research/refiner_choice/refiner_choice.py ... --load data/chooser.pt   # score a saved chooser (no training)
    python research/refiner_choice/refiner_choice.py ... --steps 50000 --checkpoint data/run.pt  # in pieces: rerun to go on

Writes ``research/refiner_choice/results/refiner_choice.json`` (and the trained chooser's state to ``--save``, if given).
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "research" / "refiner_choice"))
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks" / "refiner"))
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

from bench_refiner import NET_CONDITIONS, devset_samples, synth_samples
from bokehray_refiner.training.common import Checkpoints
from bokehray_refiner.training.common import optimise as _optimise
from bokehray_refiner.training.common import region as _region
from bokehray_refiner.training.common import resume as _resume
from bokehray_refiner.training.common import srgb_photo as _srgb
from common import REPO, machine_info, write_json

RADII = (3, 6, 12)
"""Near regions grown and shrunk by these radii [px]: with the render as it is, 7 candidates."""
N_CAND = 1 + 2 * len(RADII)
KEEP_LOGIT = 3.0
"""The chooser's initial preference for the render as it is (its logit's bias over the others')."""


def candidate_maps(used: np.ndarray) -> list[np.ndarray]:
    """The maps of the candidates: ``used``, then its near regions grown and shrunk by each of ``RADII``."""
    from scipy import ndimage

    out = [used]
    for r in RADII:
        footprint = np.ones((2 * r + 1, 2 * r + 1), bool)
        out += [ndimage.grey_dilation(used, footprint=footprint), ndimage.grey_erosion(used, footprint=footprint)]
    return out


def other_renders(image: np.ndarray, maps: list[np.ndarray], blur) -> list[np.ndarray]:
    """The level (``bokehray.render``) on each of :func:`candidate_maps` ``maps`` but the first (the map the render
    at hand used): the candidates besides the render as it is."""
    import bokehray as br

    return [br.render(image, m, blur) for m in maps[1:]]


ALIGN_SIGMA_PX = 6.0
"""How far along a map's depth edge :func:`edge_alignment` averages the photo's colour step (a Gaussian's sigma)."""


def edge_alignment(focus: np.ndarray, maps: list[np.ndarray], coc_of, min_jump_px: float = 1.0) -> np.ndarray:
    """Per candidate map, how strongly the photo changes colour on that map's depth edges near each pixel (K x H x W,
    each pixel's largest 1): the signal that tells a right edge from a misplaced one.

    A map's edge pixels are those whose 3 x 3 neighbourhood spans a CoC jump over ``min_jump_px``; the photo's step
    is its sRGB gradient magnitude (Sobel, over the three channels). Near each pixel, the Gaussian-weighted mean of
    the step over a map's edge pixels (``ALIGN_SIGMA_PX``), divided by the largest candidate's (plus 0.02, so that
    where no map has a colour edge all read low)."""
    from scipy import ndimage

    grad = np.sqrt(sum(ndimage.sobel(focus[..., c], a) ** 2 for c in range(3) for a in (0, 1))) / 8.0
    means = []
    for m in maps:
        coc = coc_of(m)
        edge = (ndimage.maximum_filter(coc, 3) - ndimage.minimum_filter(coc, 3) > min_jump_px).astype(np.float32)
        w = ndimage.gaussian_filter(edge, ALIGN_SIGMA_PX)
        means.append(ndimage.gaussian_filter(edge * grad, ALIGN_SIGMA_PX) / np.maximum(w, 1e-3))
    means = np.stack(means)
    return (means / (means.max(0, keepdims=True) + 0.02)).astype(np.float32)


def blend(base, weight, pick):
    """``base + weight (pick - base)``: a choice let in by a weight (the band, or the band times the gate); NumPy
    or torch."""
    return base + weight * (pick - base)


def bank_entry(image, disparity, blur, target, kind: str, amount: int, opts) -> dict:
    """What the chooser sees for one corrupted map, and the exact render it is scored against (sRGB)."""
    from bokehray_refiner.refine import blend_weight, correct_and_render
    from bokehray_refiner.training.data import corrupt_disparity

    import bokehray as br

    d = np.clip(corrupt_disparity(disparity, kind, amount), 0.0, 1.0)
    render, used = correct_and_render(image, d, blur, lambda dd: br.render(image, dd, blur), opts)
    focus = _srgb(image)
    band, gated = blend_weight(image, focus, used, render, blur.signed_coc(used).astype(np.float32), opts)
    maps = candidate_maps(used)
    cands = [render, *other_renders(image, maps, blur)]
    align = edge_alignment(focus, maps, blur.signed_coc)
    return {"focus": focus, "cands": np.stack([_srgb(c) for c in cands]), "band": band.astype(np.float32),
            "disparity": used.astype(np.float32), "target": _srgb(target), "exact": kind == "none",
            "gated": gated.astype(np.float32), "align": align}


def oracle_choice(cands: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Per pixel, the candidate (``cands``: K x H x W x 3) whose 5 x 5 px mean error is least (the first of equals:
    the render as it is where no other is better)."""
    from scipy import ndimage

    err = np.stack([ndimage.uniform_filter(((c - target) ** 2).sum(-1), 5) for c in cands])
    return err.argmin(0)


def oracle_pick(cands: np.ndarray, target: np.ndarray) -> np.ndarray:
    """The perfect choice's pixels (:func:`oracle_choice`)."""
    return np.take_along_axis(cands, oracle_choice(cands, target)[None, ..., None].repeat(3, -1), 0)[0]


def oracle(entry: dict) -> np.ndarray:
    """The perfect choice, blended by the band."""
    return blend(entry["cands"][0], entry["band"][..., None], oracle_pick(entry["cands"], entry["target"]))


def weighted(logits, cands):
    """The candidates (B, K, 3, H, W) weighted by the softmax of ``logits`` (B, K, H, W) per pixel."""
    import torch

    return (torch.softmax(logits, 1)[:, :, None] * cands).sum(1)


def make_chooser(width: int = 32, alignment: bool = False):
    import torch
    from torch import nn

    class Chooser(nn.Module):
        """Per-pixel softmax weights over the candidates from the photo, the render, the other renders' differences
        from it, the map the render used and the band; dilated 3 x 3 convolutions (receptive field 65 px); the output
        is the render plus the band times (the weighted candidates - the render). It starts out keeping the render
        (its logit 3 above the others'). With ``alignment``, the candidates' :func:`edge_alignment` is an input too."""

        def __init__(self) -> None:
            super().__init__()
            self.alignment = alignment
            c_in = 3 + 3 * N_CAND + 2 + (N_CAND if alignment else 0)
            layers: list[nn.Module] = [nn.Conv2d(c_in, width, 3, padding=1), nn.ReLU()]
            for dil in (2, 4, 8, 16, 1):
                layers += [nn.Conv2d(width, width, 3, padding=dil, dilation=dil), nn.ReLU()]
            layers.append(nn.Conv2d(width, N_CAND, 1))
            with torch.no_grad():
                layers[-1].bias.zero_()
                layers[-1].bias[0] = KEEP_LOGIT
            self.net = nn.Sequential(*layers)

        def logits(self, focus, cands, band, disparity, align):
            # (B, 3, H, W), (B, K, 3, H, W), (B, 1, H, W) twice, (B, K, H, W)
            base = cands[:, 0]
            diff = (cands[:, 1:] - base[:, None]).flatten(1, 2)
            extra = [align] if self.alignment else []
            return self.net(torch.cat([focus, base, diff, disparity, band, *extra], 1))

        def choose(self, focus, cands, band, disparity, align):
            """The weighted candidates (B, 3, H, W)."""
            return weighted(self.logits(focus, cands, band, disparity, align), cands)

        def forward(self, focus, cands, band, disparity, align):
            return blend(cands[:, 0], band, self.choose(focus, cands, band, disparity, align))

    return Chooser()


def _tensors(entries: list[dict]):
    import torch

    focus = torch.from_numpy(np.stack([e["focus"] for e in entries])).permute(0, 3, 1, 2)
    cands = torch.from_numpy(np.stack([e["cands"] for e in entries])).permute(0, 1, 4, 2, 3)
    band = torch.from_numpy(np.stack([e["band"] for e in entries]))[:, None]
    disparity = torch.from_numpy(np.stack([e["disparity"] for e in entries]))[:, None]
    align = torch.from_numpy(np.stack([e["align"] for e in entries]))
    target = torch.from_numpy(np.stack([e["target"] for e in entries])).permute(0, 3, 1, 2)
    weight = torch.tensor([e["weight"] for e in entries], dtype=torch.float32)
    return focus, cands, band, disparity, align, target, weight


def train(entries: list[dict], steps: int, batch: int, crop: int, seed: int, exact_weight: float = 1.0,
          choice_weight: float = 0.0, alignment: bool = False, log_every: int = 100, checkpoint: str | None = None,
          checkpoint_every: int = 500, context: int = 0):
    """AdamW on the band's squared error (weighted ``exact_weight`` on exact maps), plus ``choice_weight`` times the
    cross-entropy of the logits against the oracle's choice in the band (the render that is right, told directly).

    With ``checkpoint`` the run's whole state (model, optimiser, schedule, both generators, the losses so far) is
    written there every ``checkpoint_every`` steps and at the end (atomically), and a run started with an existing
    one goes on from it: the same steps, bit for bit, as one run without a stop (long training in pieces).

    ``context`` [px]: each crop comes with that much of the frame around it and the loss counts the crop only, so
    that (with ``context`` at least the receptive field's radius, 32 px) no output it learns from sees padding that a
    whole frame does not have (0: the crop alone, as in rounds 6 and 7)."""
    import torch
    import torch.nn.functional as F

    if choice_weight:
        for e in entries:
            e.setdefault("choice", oracle_choice(e["cands"], e["target"]))

    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    model = make_chooser(alignment=alignment)
    opt = torch.optim.AdamW(model.parameters(), lr=2e-3, weight_decay=1e-4)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=2e-3, total_steps=steps,
                                                pct_start=min(0.3, max(0.05, 10 / steps)))
    parts = {"model": model, "opt": opt, "sched": sched}
    checkpoints = Checkpoints(checkpoint, steps, seed, checkpoint_every)
    losses, start = _resume(checkpoints, parts, rng)
    for step in range(start, steps):
        crops = []
        for i in rng.integers(0, len(entries), batch):
            e = entries[i]
            h, w = e["band"].shape
            ys, xs = np.nonzero(e["band"] > 0)
            if len(ys) and rng.random() < 0.9:  # crops on the band, where the choice matters
                j = rng.integers(len(ys))
                y0 = int(np.clip(ys[j] - crop // 2, 0, h - crop))
                x0 = int(np.clip(xs[j] - crop // 2, 0, w - crop))
            else:
                y0, x0 = int(rng.integers(0, h - crop + 1)), int(rng.integers(0, w - crop + 1))
            # with ``context``, the crop plus that much around it (zeros beyond the frame), the loss on the crop only
            def cut(a, lead=0, y0=y0, x0=x0):
                return _region(a, y0 - context, x0 - context, crop + 2 * context, lead)

            counted = np.zeros((crop + 2 * context,) * 2, np.float32)
            counted[context:context + crop, context:context + crop] = 1.0
            crops.append({"focus": cut(e["focus"]), "cands": cut(e["cands"], 1), "band": cut(e["band"]),
                          "disparity": cut(e["disparity"]), "align": cut(e["align"], 1), "target": cut(e["target"]),
                          "counted": counted, "weight": exact_weight if e["exact"] else 1.0,
                          **({"choice": cut(e["choice"])} if choice_weight else {})})
        focus, cands, band, disparity, align, target, weight = _tensors(crops)
        logits = model.logits(focus, cands, band, disparity, align)
        out = blend(cands[:, 0], band, weighted(logits, cands))
        counted = torch.from_numpy(np.stack([c["counted"] for c in crops]))[:, None]
        band_w = band * counted * weight[:, None, None, None]
        loss = (((out - target) ** 2).sum(1, keepdim=True) * band_w).sum() / band_w.sum().clamp_min(1.0)
        if choice_weight:
            labels = torch.from_numpy(np.stack([c["choice"] for c in crops]))
            ce = F.cross_entropy(logits, labels, reduction="none")[:, None]
            loss = loss + choice_weight * (ce * band_w).sum() / band_w.sum().clamp_min(1.0)
        _optimise(loss, step, parts, losses, rng, checkpoints)
        if (step + 1) % log_every == 0:
            print(f"step {step + 1}: band loss {np.mean(losses[-log_every:]):.5f}", flush=True)
    return model, losses


def _psnr(err2: np.ndarray) -> float:
    mse = float(err2.mean())
    return 10.0 * math.log10(1.0 / mse) if mse > 0 else 99.0


def score(model, samples, opts) -> tuple[list[dict], list[dict]]:
    """Band PSNR of fix, learned and oracle, per render and condition, and their means per condition."""
    import torch

    rows = []
    for name, image, disparity, blur, target, score_band in samples:
        m = np.asarray(score_band, bool)
        for kind, amount in NET_CONDITIONS:
            e = bank_entry(image, disparity, blur, target, kind, amount, opts)
            with torch.no_grad():
                pick = model.choose(*_tensors([e | {"weight": 1.0}])[:5])[0].permute(1, 2, 0).numpy()
            base = e["cands"][0]
            learned = blend(base, e["band"][..., None], pick)
            gated = blend(base, e["gated"][..., None], pick)  # behind refine's confidence gate as well
            row = {"pair": name, "corruption": kind, "px": amount}
            for key, img in (("fix", base), ("learned", learned), ("learned_gated", gated), ("oracle", oracle(e))):
                row[key] = _psnr(((img - e["target"]) ** 2).mean(-1)[m])
            rows.append(row)
        print(name, flush=True)
    summary = []
    for kind, amount in NET_CONDITIONS:
        sel = [r for r in rows if (r["corruption"], r["px"]) == (kind, amount)]
        summary.append({"corruption": kind, "px": amount,
                        **{k: float(np.mean([r[k] for r in sel])) for k in ("fix", "learned", "learned_gated", "oracle")},
                        "learned_worst": float(min(r["learned"] - r["fix"] for r in sel)),
                        "learned_gated_worst": float(min(r["learned_gated"] - r["fix"] for r in sel))})
    return rows, summary


def training_bank(args: argparse.Namespace, opts) -> list[dict]:
    """One corrupted map per training pair (the exact one for ``--exact-share`` of them), read from ``--bank`` when
    it exists, else rendered (and written there)."""
    import bokehray as br
    from bokehray.data.datasets import BLBDataset

    if args.bank and Path(args.bank).is_file():
        with np.load(args.bank) as z:
            keys = {name.split("_", 1)[1] for name in z.files if name != "n"} - {"exact"}
            return [{k: z[f"{i}_{k}"] for k in keys} | {"exact": bool(z[f"{i}_exact"])} for i in range(int(z["n"]))]
    rng = np.random.default_rng(args.seed)
    ds = BLBDataset(args.train)
    others = [c for c in NET_CONDITIONS if c[0] != "none"]
    entries = []
    for i in range(len(ds)):
        s = ds[i]
        kind, amount = ("none", 0) if rng.random() < args.exact_share else others[int(rng.integers(len(others)))]
        entries.append(bank_entry(s.image, s.disparity, br.BlurParams(s.k_px, s.focus_disparity), s.target, kind,
                                  amount, opts))
    if args.bank:
        np.savez(args.bank, n=len(entries), **{f"{i}_{k}": v for i, e in enumerate(entries) for k, v in e.items()})
    return entries


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--train", required=True, help="BLB folder to train on (bokehray synth)")
    ap.add_argument("--heldout", help="held-out BLB folder to score on")
    ap.add_argument("--devset", help="the path-traced dev set folder (with score.py) to score on")
    ap.add_argument("--pairs", type=int, default=24, help="--heldout: pairs to score")
    ap.add_argument("--steps", type=int, default=1500)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--crop", type=int, default=96)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--exact-share", type=float, default=0.25, help="share of training pairs given the exact map")
    ap.add_argument("--exact-weight", type=float, default=1.0, help="loss weight of the pairs given the exact map")
    ap.add_argument("--choice-weight", type=float, default=0.0,
                    help="weight of the cross-entropy against the oracle's choice in the band (0: the error alone)")
    ap.add_argument("--alignment", action="store_true",
                    help="give the chooser each candidate map's edge alignment with the photo (edge_alignment)")
    ap.add_argument("--bank", default=None, help="cache of the training inputs (.npz): read if present, else written")
    ap.add_argument("--threads", type=int, default=None, help="torch threads")
    ap.add_argument("--save", default=None, help="write the trained chooser's state_dict here (torch.save)")
    ap.add_argument("--checkpoint", default=None,
                    help="the training state, written every --checkpoint-every steps; an existing one is resumed")
    ap.add_argument("--checkpoint-every", type=int, default=500)
    ap.add_argument("--context", type=int, default=0,
                    help="frame around each training crop the chooser sees and the loss does not count [px]")
    ap.add_argument("--load", default=None, help="score this saved chooser (--save) instead of training one")
    ap.add_argument("--out", default=str(REPO / "research/refiner_choice/results/refiner_choice.json"))
    args = ap.parse_args()

    import torch
    from bokehray_refiner.refine import RefineOptions

    if args.threads:
        torch.set_num_threads(args.threads)
    opts = RefineOptions()
    t = time.perf_counter()
    entries = [] if args.load else training_bank(args, opts)  # nothing to train on when loading
    t_bank = time.perf_counter() - t
    print(f"bank: {len(entries)} pairs in {t_bank:.0f} s", flush=True)
    t = time.perf_counter()
    if args.load:
        model, losses = make_chooser(alignment=args.alignment), []
        model.load_state_dict(torch.load(args.load))
    else:
        model, losses = train(entries, args.steps, args.batch, args.crop, args.seed, args.exact_weight,
                              args.choice_weight, args.alignment, checkpoint=args.checkpoint,
                              checkpoint_every=args.checkpoint_every, context=args.context)
    t_train = time.perf_counter() - t
    model.eval()
    if args.save:
        torch.save(model.state_dict(), args.save)
    result = {"machine": machine_info(), "train": args.train, "pairs": len(entries), "steps": args.steps,
              "batch": args.batch, "crop": args.crop, "seed": args.seed, "exact_share": args.exact_share,
              "exact_weight": args.exact_weight, "choice_weight": args.choice_weight,
              "alignment": args.alignment, "context": args.context, "keep_logit": KEEP_LOGIT, "bank_s": t_bank,
              "train_s": t_train,
              "parameters": sum(p.numel() for p in model.parameters()), "loss": losses}
    for split, samples in (("devset", devset_samples(Path(args.devset)) if args.devset else None),
                           ("heldout", synth_samples(args.heldout, args.pairs) if args.heldout else None)):
        if samples is None:
            continue
        rows, summary = score(model, samples, opts)
        result[split] = {"rows": rows, "summary": summary}
        print(f"{split}: band PSNR dB, mean over renders (gain over the depth fix)")
        for s in summary:
            print(f"  {s['corruption'] + ' ' + str(s['px']):>12} fix {s['fix']:6.2f}  learned {s['learned'] - s['fix']:+.2f}"
                  f" (worst render {s['learned_worst']:+.2f}), behind the gate {s['learned_gated'] - s['fix']:+.2f}"
                  f" (worst {s['learned_gated_worst']:+.2f})  oracle {s['oracle'] - s['fix']:+.2f}")
    write_json(args.out, result)


if __name__ == "__main__":
    main()
