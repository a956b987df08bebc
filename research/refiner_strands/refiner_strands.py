"""Strands missing from the map: how much of their error could any depth taken from the map undo?

The ``missing`` corruption (``bokehray_refiner.training.data.corrupt_disparity``) erases near structures narrower than
``2 amount + 1`` px: strands, wires, stems and writing take the depth of what is behind them. Undoing it takes two
things, *where* (which pixels lost a strand) and *what depth* (the strand's). This script gives the first for free
(an oracle: the pixels whose disparity the corruption lowered) and measures the second: the level rendered on the
depth fix's map with those pixels set to

* ``exact``: their true disparity (the bound: the exact map there);
* ``near R``: the nearest disparity of the map within R px (a grey dilation; right where the strand grows out of a
  body the map kept, such as hair from a head or a stem from a leaf);
* ``nearest``: the map's nearest disparity anywhere;
* ``focus``: the focus disparity (right where the strands are what the photographer focused on);
* ``best of the map's``: per pixel, whichever of ``near R`` and ``nearest`` is nearest the truth (the most a network
  that finds the lost pixels and picks among the map's candidates could reach).

Band PSNR (the true depth's score band, as ``bench_refiner.py``) over the depth fix's render, per render, and the
mean absolute disparity error of each candidate on the lost pixels. A gain that only ``exact`` reaches needs the
strand's depth from the photo alone: a monocular prior, not a map-conditioned network.

    python research/refiner_strands/refiner_strands.py --devset ../shared/data/pathtraced-dev
    python research/refiner_strands/refiner_strands.py --data data/heldout --pairs 24

Writes ``research/refiner_strands/results/refiner_strands_{devset,synth}.json``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "research" / "refiner_choice"))
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks" / "refiner"))
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

from bench_refiner import add_split_args, split_out, split_samples
from common import machine_info, write_json

RADII = (3, 6, 12, 24, 48)
LOST_MIN = 0.02
"""A pixel lost a strand where the corruption lowered its disparity by more than this (of the [0, 1] range)."""


def lost_pixels(true: np.ndarray, given: np.ndarray, min_drop: float = LOST_MIN) -> np.ndarray:
    """Where ``given`` puts a pixel farther than ``true`` by more than ``min_drop`` (what the corruption erased)."""
    return (np.asarray(true, np.float32) - np.asarray(given, np.float32)) > min_drop


def strand_candidates(given: np.ndarray, true: np.ndarray, focus: float, radii=RADII) -> dict[str, np.ndarray]:
    """Per candidate, a disparity for every pixel (only the lost pixels' values are used)."""
    from scipy import ndimage
    from skimage.morphology import disk

    given = np.asarray(given, np.float32)
    out = {"exact": np.asarray(true, np.float32)}
    for r in radii:
        out[f"near {r}"] = ndimage.grey_dilation(given, footprint=disk(r), mode="nearest")
    out["nearest"] = np.full_like(given, given.max())
    from_map = np.stack([out[f"near {r}"] for r in radii] + [out["nearest"]])
    pick = np.abs(from_map - out["exact"]).argmin(0)
    out["focus"] = np.full_like(given, np.float32(focus))
    out["best of the map's"] = np.take_along_axis(from_map, pick[None], 0)[0]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_split_args(ap, "research/refiner_strands/results/refiner_strands")
    ap.add_argument("--amount", type=int, default=2, help="the missing corruption's disc radius (px)")
    args = ap.parse_args()
    args.out = split_out(args, "research/refiner_strands/results/refiner_strands")

    from bokehray_refiner.refine import RefineOptions, correct_and_render
    from bokehray_refiner.training.data import corrupt_disparity

    import bokehray as br
    from bokehray.data.metrics import score

    opts = RefineOptions()
    samples = split_samples(args)
    rows = []
    for name, image, disparity, blur, target, band in samples:
        d = np.clip(corrupt_disparity(disparity, "missing", args.amount), 0.0, 1.0)
        render, used = correct_and_render(image, d, blur, lambda dd, im=image, bl=blur: br.render(im, dd, bl), opts)
        base = score(render, target, band)["band_psnr"]
        lost = lost_pixels(disparity, used)
        row = {"pair": name, "k_px": blur.k_px, "focus_disparity": blur.focus_disparity, "fix": base,
               "lost_px": int(lost.sum()), "gain": {}, "disparity_error": {}}
        for cname, cand in strand_candidates(used, disparity, blur.focus_disparity).items():
            fixed = np.where(lost, np.maximum(cand, used), used)  # a strand is never behind the map's value
            row["gain"][cname] = score(br.render(image, fixed, blur), target, band)["band_psnr"] - base
            row["disparity_error"][cname] = float(np.abs(fixed - disparity)[lost].mean()) if lost.any() else 0.0
        rows.append(row)
        print(name, " ".join(f"{k} {v:+.2f}" for k, v in row["gain"].items()), flush=True)
    names = list(rows[0]["gain"])
    with_lost = [r for r in rows if r["lost_px"]]
    summary = {c: {"gain": float(np.mean([r["gain"][c] for r in rows])),
                   "worst": float(min(r["gain"][c] for r in rows)),
                   "disparity_error": float(np.mean([r["disparity_error"][c] for r in with_lost])) if with_lost else 0.0}
               for c in names}
    print(f"{'depth of the lost pixels':>26} {'band dB over the fix':>21} {'worst':>7} {'|disparity error|':>18}")
    for c, s in summary.items():
        print(f"{c:>26} {s['gain']:+21.2f} {s['worst']:+7.2f} {s['disparity_error']:18.3f}")
    write_json(args.out, {"machine": machine_info(), "data": str(args.devset or args.data), "amount": args.amount,
                          "lost_min": LOST_MIN, "summary": summary, "rows": rows})


if __name__ == "__main__":
    main()
