"""Train and score the learned edge placement (``bokehray_refiner.edges``): refine's first network.

Training pairs come from a BLB folder (``bokehray synth``). Each pair's map is corrupted ``--variants`` ways as real
maps are wrong (the exact map; edges misplaced locally by 5-20 px; a monocular estimator's map at 1/3 to 1/8
resolution; a grey opening of radius 1-3 px, so that strands narrower than 3-7 px go missing; near regions grown or
shrunk by 2-6 px), each with its own random draw, then put through the colour-guided depth correction as refine does.
The network learns, per pixel of the edge band, which side of the edge the pixel is on: the side (near or far
candidate) whose CoC is nearer the true map's. Its loss is the binary cross-entropy against that side, each pixel
weighted by the band, by the CoC span between the candidates (0 to 1 at 4 px) and ``--exact-weight`` on the exact
maps; with ``--price``, also by what a wrong side costs the render (:func:`render_price`; measured and not used by the
shipped weights, README.md here). ``--runs-only`` trains only on the maps refine would run the
network on, ``--keep-margin`` labels a third layer between the candidates with the map's own side, ``--init``
fine-tunes given weights (measured, not used by the shipped weights).

Scored on the path-traced dev set and a held-out synthetic split in the true depth's band, per corruption of
``bench_refiner.NET_CONDITIONS``, as ``bench_refiner.py --network-conditions``: ``fix`` is the depth fix's render
(refine without networks), ``edges`` the level on the map the edge network moved, at each ``--thresholds``
(``gated``: only where refine's confidence gate opens), ``oracle`` the level on the map a perfect network would make
(:func:`oracle_map`). As in refine, the network runs only on maps the depth fix found wrong (``--min-fixed-share``,
refine's ``min_fixed_share``; 0: every map); ``--veto`` adds columns with the colour veto. Clipped lights are
not held back here (refine holds them).

    bokehray synth -n 80 -o data/train --seed 2000 --size 256 --blur-levels 8,16,24 --depth-rule half \\
        --kinds strands=3,fur=2,whiskers=1,foliage=2,mesh=1,softcut=1.5,cutout=1,lights=1
    python research/refiner_edges/refiner_edges.py --train data/train --heldout data/heldout --devset ../shared/data/pathtraced-dev \\
        --bank data/edges_bank.npz --checkpoint data/edges_run.pt --export data/edges.safetensors
    python research/refiner_edges/refiner_edges.py --load data/edges.safetensors --devset ... --heldout ... --gate --attached

Writes ``research/refiner_edges/results/refiner_edges.json``.
"""

from __future__ import annotations

import argparse
import sys
import time
from functools import partial
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "research" / "refiner_choice"))
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks" / "refiner"))
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

from bench_refiner import NET_CONDITIONS, devset_samples, synth_samples
from bokehray_refiner.training.common import srgb_photo as _srgb
from bokehray_refiner.training.edges import (
    EdgeRecipe,
    _bank_maps,
    _save_bank,
    bank,
    fix,
    network_runs,
    train,
    used_map,
)
from common import REPO, machine_info, write_json
from refiner_choice import _psnr


def run_flags(root: str, variants: int, seed: int, opts) -> np.ndarray:
    """Whether refine would run the network on each of the bank's maps, for a bank written before it kept this
    (the maps are drawn again, as :func:`bank` drew them)."""
    return np.array([network_runs(fix(s.image, d, blur, opts, focus), focus, blur, opts)[0]
                     for s, blur, focus, _, d in _bank_maps(root, variants, seed)])


def score(model, samples, opts, thresholds, gate: bool = False, min_region: int = 0, attached: bool = False,
          margins: tuple[float, ...] = (), passes: int = 1) -> tuple[list[dict], list[dict]]:
    """Band PSNR of the depth fix's render and of the level on the edge network's map (``edges``; with ``gate``
    also behind refine's confidence gate, ``gated``), per render and condition; each also with the colour veto at
    each of ``margins`` (``_v<margin>``, ``Placement(colour_margin=)``), the oracle too; the network makes
    ``passes`` passes (``Placement(passes=)``)."""
    from bokehray_refiner.edges import Placement, edge_features, place_edges
    from bokehray_refiner.training.data import corrupt_disparity

    import bokehray as br

    rows = []
    config = model.config
    for name, image, disparity, blur, target, score_band in samples:
        focus = _srgb(image)

        band_psnr = partial(_band_psnr, image, blur, _srgb(target), np.asarray(score_band, bool))
        for kind, amount in NET_CONDITIONS:
            d = np.clip(corrupt_disparity(disparity, kind, amount), 0.0, 1.0)
            c = fix(image, d, blur, opts, focus)
            used, band, _ = used_map(c, blur, opts)
            runs, share = network_runs(c, focus, blur, opts, used, band)  # else refine leaves the map as it is
            render = br.render(image, used, blur)
            row = {"pair": name, "corruption": kind, "px": amount, "fix": band_psnr(used, render), "runs": runs,
                   "fixed_share": share,
                   "oracle": band_psnr(oracle_map(used, disparity, band, config))}
            feats = edge_features(focus, used, blur, band, config) if margins else None
            for margin in margins:
                row[f"oracle_v{margin:g}"] = band_psnr(oracle_map(used, disparity, band, config, feats, margin))
            gated = None
            if gate:  # refine's confidence gate on the depth fix's render: where it closes, no edge moves
                from bokehray_refiner.refine import blend_weight

                _, gated = blend_weight(image, focus, used, render, blur.signed_coc(used).astype(np.float32), opts)
            for th in thresholds:
                # the network always sees the band it was trained with; the gate only holds pixels back
                for tag, hold in (("edges", None), ("gated", None if gated is None else gated <= 0)):
                    if tag == "gated" and hold is None:
                        continue
                    for margin in (None, *margins):
                        key = f"{tag}_{th:g}" + ("" if margin is None else f"_v{margin:g}")
                        if not runs:
                            row[key], row[key.replace("_", "_moved_", 1)] = row["fix"], 0
                            continue
                        placement = Placement(th, min_region_px=min_region, attached=attached,
                                              colour_margin=margin, passes=passes)
                        moved = place_edges(model, focus, used, blur, band, keep=hold, placement=placement)
                        row[key] = band_psnr(moved)
                        row[key.replace("_", "_moved_", 1)] = int((moved != used).sum())
            rows.append(row)
        print(name, flush=True)
    return rows, summarise(rows)


def _band_psnr(image, blur, target_srgb, score_band, disparity, render=None) -> float:
    """PSNR in ``score_band`` of the level's render on ``disparity`` (``render``, when already made)."""
    import bokehray as br

    render = br.render(image, disparity, blur) if render is None else render
    return _psnr(((_srgb(render) - target_srgb) ** 2).mean(-1)[score_band])


def oracle_map(used: np.ndarray, truth: np.ndarray, band: np.ndarray, config, features: np.ndarray | None = None,
               margin: float | None = None) -> np.ndarray:
    """What a perfect edge network would make of ``used``: every pixel of the band with an edge in reach that ``used``
    puts on the wrong side (its true side: the candidate nearer the true disparity) moves to the other side's value;
    with ``margin``, only where the colour veto lets it (``colour_allows`` of ``features``)."""
    from bokehray_refiner.edges import candidates, colour_allows, map_sides

    near, far = candidates(used, config.radius_px)
    reach, on_near = map_sides(used, near, far)
    true_near = truth - far > near - truth
    move = (band > 0) & reach & (true_near != on_near)
    if margin is not None:
        near_ok, far_ok = colour_allows(features, margin)
        move &= np.where(true_near, near_ok, far_ok)
    return np.where(move, np.where(true_near, near, far), used)


def summarise(rows: list[dict]) -> list[dict]:
    """Per condition: the mean band PSNR of each column, and each column's worst render against the depth fix."""
    summary = []
    for kind, amount in NET_CONDITIONS:
        sel = [r for r in rows if (r["corruption"], r["px"]) == (kind, amount)]
        s = {"corruption": kind, "px": amount, "fix": float(np.mean([r["fix"] for r in sel]))}
        for k in sel[0]:
            if k.startswith(("edges_", "gated_", "oracle")) and "_moved_" not in k:
                s[k] = float(np.mean([r[k] for r in sel]))
                s[f"{k}_worst"] = float(min(r[k] - r["fix"] for r in sel))
        summary.append(s)
    return summary


def _entries(args, opts, config) -> list[dict]:
    """The training maps: the bank ``--bank`` if written, else made (and written there); with ``--runs-only``, only
    the maps refine would run the network on (and with ``--with-exact`` every exact map too)."""
    if args.bank and Path(args.bank).is_file():
        with np.load(args.bank) as z:
            entries = [{k: z[f"{i}_{k}"] for k in ("x", "cost", "exact", "runs") if f"{i}_{k}" in z}
                       for i in range(int(z["n"]))]
        if args.runs_only and "runs" not in entries[0]:  # a bank written before it kept the flag
            for e, runs in zip(entries, run_flags(args.train, args.variants, args.seed, opts), strict=True):
                e["runs"] = runs
            _save_bank(args.bank, entries)
    else:
        entries = bank(args.train, args.variants, args.seed, opts, config)
        if args.bank:
            _save_bank(args.bank, entries)
    if not args.runs_only:
        return entries
    return [e for e in entries if e["runs"] or (args.with_exact and e["exact"])]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--train", help="BLB folder to train on (bokehray synth)")
    ap.add_argument("--heldout", help="held-out BLB folder to score on")
    ap.add_argument("--devset", help="the path-traced dev set folder (with score.py) to score on")
    ap.add_argument("--pairs", type=int, default=24, help="--heldout: pairs to score")
    ap.add_argument("--variants", type=int, default=5, help="corrupted maps per training pair (the first exact)")
    ap.add_argument("--steps", type=int, default=4000)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--crop", type=int, default=64,
                    help="side of the crop the loss counts (the network sees its receptive field around it too)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--exact-weight", type=float, default=2.0, help="loss weight of the exact maps")
    ap.add_argument("--runs-only", action="store_true",
                    help="train only on the maps refine would run the network on (network_runs), as at inference")
    ap.add_argument("--price", type=float, default=0.0,
                    help="weight the loss by the render price of a wrong side: the squared colour step across the "
                         "edge over this squared (sRGB; 0: off)")
    ap.add_argument("--with-exact", action="store_true",
                    help="with --runs-only, train on every exact map too (to learn to leave right edges alone)")
    ap.add_argument("--keep-margin", type=float, default=None,
                    help="label a pixel with the map's own side where keeping its value is nearer the true CoC than "
                         "either candidate by this much (CoC px; default: the nearer candidate's side everywhere)")
    ap.add_argument("--lr", type=float, default=2e-3, help="the learning rate's peak (one cycle)")
    ap.add_argument("--init", default=None,
                    help="start from these weights (safetensors; their config, not --width/--dilations)")
    ap.add_argument("--width", type=int, default=32)
    ap.add_argument("--dilations", default="2,4,8,1", help="the hidden 3 x 3 convolutions' dilations")
    ap.add_argument("--bank", default=None, help="cache of the training inputs (.npz): read if present, else written")
    ap.add_argument("--checkpoint", default=None,
                    help="the training state, written every --checkpoint-every steps; an existing one is resumed")
    ap.add_argument("--checkpoint-every", type=int, default=500)
    ap.add_argument("--export", default=None, help="write the trained network here (safetensors)")
    ap.add_argument("--load", default=None, help="score these weights (safetensors) instead of training")
    ap.add_argument("--thresholds", default="0.7,0.8,0.9")
    ap.add_argument("--gate", action="store_true", help="score behind refine's confidence gate as well")
    ap.add_argument("--min-region", type=int, default=0, help="place_edges' min_region_px")
    ap.add_argument("--passes", type=int, default=None,
                    help="place_edges' passes (default: refine's edge_passes)")
    ap.add_argument("--attached", action="store_true", help="place_edges' attached: no islands, no holes")
    ap.add_argument("--min-fixed-share", type=float, default=None,
                    help="the network runs only on maps the depth fix moved at least this share of the band of "
                         "(refine's min_fixed_share, whose default is the default; 0: on every map)")
    ap.add_argument("--veto", default="",
                    help="score with the colour veto too, at each of these margins (sRGB; place_edges' colour_margin)")
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--out", default=str(REPO / "research/refiner_edges/results/refiner_edges.json"))
    args = ap.parse_args()
    if args.with_exact and not args.runs_only:
        ap.error("--with-exact adds the exact maps to --runs-only's; without --runs-only every map is used anyway")

    import torch
    from bokehray_refiner.edges import EdgeConfig, colour_features, load_edge_net, save_edge_net
    from bokehray_refiner.refine import RefineOptions

    if args.threads:
        torch.set_num_threads(args.threads)
    torch.set_flush_denormal(True)
    opts = RefineOptions() if args.min_fixed_share is None else RefineOptions(min_fixed_share=args.min_fixed_share)
    result = {"machine": machine_info(), "args": vars(args)}
    if args.load:
        model = load_edge_net(args.load)
    else:
        init = load_edge_net(args.init) if args.init else None
        config = init.config if init else EdgeConfig(width=args.width,
                                                     dilations=tuple(int(v) for v in args.dilations.split(",")))
        t = time.perf_counter()
        entries = _entries(args, opts, config)
        for e in entries:  # the bank keeps the first channels; the colour models are made from them
            e["x"] = np.concatenate([e["x"], colour_features(e["x"].astype(np.float32)).astype(np.float16)])
        result["bank_s"] = time.perf_counter() - t
        print(f"bank: {len(entries)} maps in {result['bank_s']:.0f} s", flush=True)
        t = time.perf_counter()
        recipe = EdgeRecipe(steps=args.steps, batch=args.batch, crop=args.crop, seed=args.seed,
                            exact_weight=args.exact_weight, lr=args.lr, price=args.price, keep_margin=args.keep_margin)
        model, losses = train(entries, config, recipe, args.checkpoint, args.checkpoint_every, init=init)
        del entries
        result |= {"train_s": time.perf_counter() - t, "loss": losses}
        model.eval()
        if args.export:
            save_edge_net(model, args.export, steps=str(args.steps), seed=str(args.seed))
    result["parameters"] = sum(p.numel() for p in model.parameters())
    thresholds = [float(v) for v in args.thresholds.split(",")]
    margins = tuple(float(v) for v in args.veto.split(",")) if args.veto else ()
    for split, samples in (("devset", devset_samples(Path(args.devset)) if args.devset else None),
                           ("heldout", synth_samples(args.heldout, args.pairs) if args.heldout else None)):
        if samples is None:
            continue
        rows, summary = score(model, samples, opts, thresholds, args.gate, args.min_region, args.attached, margins,
                              opts.edge_passes if args.passes is None else args.passes)
        result[split] = {"rows": rows, "summary": summary}
        print(f"{split}: band PSNR dB, mean over renders (gain over the depth fix; worst render)")
        for s in summary:
            gains = "  ".join(f"{k}: {s[k] - s['fix']:+.2f} ({s[k + '_worst']:+.2f})"
                              for k in s if k.startswith(("edges_", "gated_", "oracle")) and "_worst" not in k)
            print(f"  {s['corruption'] + ' ' + str(s['px']):>12} fix {s['fix']:6.2f}  {gains}", flush=True)
    write_json(args.out, result)


if __name__ == "__main__":
    main()
