"""Does the refiner fix what wrong depth breaks? Preview, raytrace and refine on a held-out synthetic split.

The disparity handed to every method is the true one eroded or dilated by 0-5 px
(paper fig. 7); the target is the exact render of the true scene. Scores are
PSNR/SSIM in sRGB after clipping (``bokehray.metrics``), over the whole image
and within 8 px of a depth discontinuity of the *true* disparity.

    bokehray synth -n 24 -o /tmp/refiner-test --seed 9000 --size 256 --blur-levels 8,16,24
    python benchmarks/bench_refiner.py --data /tmp/refiner-test --pairs 48
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import REPO, machine_info, write_json  # noqa: E402

CONDITIONS = [("none", 0), ("erode", 1), ("erode", 3), ("erode", 5), ("dilate", 1), ("dilate", 3), ("dilate", 5)]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True, help="held-out BLB-layout folder (never used for training)")
    ap.add_argument("--pairs", type=int, default=48, help="pairs to score (every k-th pair of the folder)")
    ap.add_argument("--weights", help="refiner weights (default: the shipped ones)")
    ap.add_argument("--max-spp", type=int, default=64, help="raytrace rays per pixel cap")
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--band-margin", type=float, default=None,
                    help="RefineOptions.band_margin_px (inf: no band restriction); default: the option's default")
    ap.add_argument("--no-raytrace", action="store_true", help="skip the raytrace level (for quick sweeps)")
    ap.add_argument("--out", default=str(REPO / "benchmarks/results/refiner.json"))
    ap.add_argument("--plot", default=str(REPO / "docs/img/refiner_robustness.png"))
    args = ap.parse_args()

    import torch

    if args.threads:
        torch.set_num_threads(args.threads)
    import bokehray as br
    from bokehray.datasets import BLBDataset
    from bokehray.metrics import discontinuity_band, score
    from bokehray_refiner.data import corrupt_disparity
    from bokehray_refiner.refine import RefineOptions, load_refiner, refine

    ropts = RefineOptions() if args.band_margin is None else RefineOptions(band_margin_px=args.band_margin)

    model = load_refiner(args.weights)
    ds = BLBDataset(args.data)
    step = max(1, len(ds) // args.pairs)
    idx = list(range(0, len(ds), step))[: args.pairs]
    rows = []
    for n, i in enumerate(idx):
        s = ds[i]
        blur = br.BlurParams(s.k_px, s.focus_disparity)
        band = discontinuity_band(s.disparity)
        for kind, amount in CONDITIONS:
            d = np.clip(corrupt_disparity(s.disparity, kind, amount), 0.0, 1.0)
            t0 = time.perf_counter()
            preview = br.render(s.image, d, blur)
            t_preview = time.perf_counter() - t0
            t0 = time.perf_counter()
            ray = preview if args.no_raytrace else br.render(
                s.image, d, blur, quality="raytrace", options=br.RaytraceOptions(max_spp=args.max_spp))
            t_ray = time.perf_counter() - t0
            refined, st = refine(s.image, d, blur, preview, model=model, options=ropts)
            for method, img, t in (("preview", preview, t_preview), ("raytrace", ray, t_ray),
                                   ("refine", refined, t_preview + st.seconds)):
                rows.append({"pair": s.name, "k_px": s.k_px, "corruption": kind, "px": amount, "method": method,
                             "seconds": t, "share_refined": st.share_refined if method == "refine" else None}
                            | score(img, s.target, band))
        print(f"{n + 1}/{len(idx)} {s.name}", flush=True)
    summary = summarise(rows)
    write_json(args.out, {"machine": machine_info(), "data": str(args.data), "pairs": len(idx),
                          "weights": str(args.weights or "shipped"), "refine_options": ropts.__dict__,
                          "summary": summary, "rows": rows})
    print_table(summary)
    plot(summary, args.plot)


def summarise(rows: list[dict]) -> list[dict]:
    out = []
    for kind, amount in CONDITIONS:
        for method in ("preview", "raytrace", "refine"):
            sel = [r for r in rows if r["corruption"] == kind and r["px"] == amount and r["method"] == method]
            band = [r["band_psnr"] for r in sel if not math.isnan(r["band_psnr"])]
            out.append({"corruption": kind, "px": amount, "method": method,
                        "psnr": float(np.mean([r["psnr"] for r in sel])),
                        "ssim": float(np.mean([r["ssim"] for r in sel])),
                        "band_psnr": float(np.mean(band)) if band else math.nan,
                        "band_ssim": float(np.nanmean([r["band_ssim"] for r in sel])),
                        "seconds": float(np.median([r["seconds"] for r in sel])),
                        "share_refined": float(np.mean([r["share_refined"] for r in sel])) if method == "refine"
                        else None})
    return out


def print_table(summary: list[dict]) -> None:
    print(f"{'depth':>10} {'method':>9} {'PSNR':>7} {'band':>7} {'SSIM':>6} {'bSSIM':>6} {'time s':>7}")
    for r in summary:
        print(f"{r['corruption'] + ' ' + str(r['px']):>10} {r['method']:>9} {r['psnr']:7.2f} {r['band_psnr']:7.2f} "
              f"{r['ssim']:6.3f} {r['band_ssim']:6.3f} {r['seconds']:7.3f}")


def plot(summary: list[dict], path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    xs = [-5, -3, -1, 0, 1, 3, 5]  # erosion negative, dilation positive

    def key(x):
        return ("none", 0) if x == 0 else (("erode", -x) if x < 0 else ("dilate", x))

    fig, axes = plt.subplots(1, 2, figsize=(9, 3.6), dpi=120)
    for method, style in (("preview", "o-"), ("raytrace", "s-"), ("refine", "^-")):
        for ax, metric in zip(axes, ("psnr", "band_psnr")):
            ys = [next(r[metric] for r in summary if (r["corruption"], r["px"]) == key(x) and r["method"] == method)
                  for x in xs]
            ax.plot(xs, ys, style, label=method)
    for ax, title in zip(axes, ("whole image", "within 8 px of depth edges")):
        ax.set_xlabel("disparity error: erosion (-) / dilation (+), px")
        ax.set_ylabel("PSNR (dB)")
        ax.set_title(title)
        ax.grid(alpha=0.3)
        ax.legend()
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)


if __name__ == "__main__":
    main()
