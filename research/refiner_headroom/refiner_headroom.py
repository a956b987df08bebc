"""How much could any network gain behind refine's band and gate? The error a perfect network may reach.

``refine()`` blends the network's output into the classical render (after the depth fix) with a weight ``w``: the
edge band times the confidence gate (``bokehray_refiner.refine.blend_weight``). Whatever the network predicts, a
pixel's sRGB error can fall at best to ``(1 - w)^2`` of the depth fix's error there (the network predicting the
exact target). This script scores that best case on the path-traced dev set (or a synthetic split) for the
network's own target conditions (``bench_refiner.NET_CONDITIONS``), in the score band of the true depth (as
``bench_refiner.py``), three ways:

* ``fix``: the depth fix's render (what the network starts from);
* ``gated``: a perfect network behind the band and the gate (the most refine can gain today);
* ``band``: a perfect network behind the band alone, the gate open everywhere (often the whole score band: its
  PSNR is then infinite, counted as 99 dB in the means).

and, per condition, the share of the score band's squared error that a perfect network removes behind the gate and
behind the band alone. A target above the ``gated`` gain cannot be met by training alone: the band or the gate must change.

    python research/refiner_headroom/refiner_headroom.py --devset ../shared/data/pathtraced-dev
    python research/refiner_headroom/refiner_headroom.py --data data/heldout --pairs 24

Writes ``research/refiner_headroom/results/refiner_headroom_{devset,synth}.json``.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "research" / "refiner_choice"))
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks" / "refiner"))
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

from bench_refiner import NET_CONDITIONS, add_split_args, split_out, split_samples
from common import machine_info, write_json
from refiner_choice import blend, candidate_maps, oracle_pick, other_renders


def _psnr(mse: float) -> float:
    return 10.0 * math.log10(1.0 / mse) if mse > 0 else math.inf


def _best_choice(image, used, blur, render, t_srgb, band, m) -> float:
    """Band PSNR of the best per-pixel choice (each pixel takes the render whose 5 x 5 px mean error is least) among
    the level rendered on ``used`` and on it with near regions grown / shrunk by 3, 6 and 12 px, blended by the band."""
    from bokehray.colour import linear_to_srgb

    renders = [render, *other_renders(image, candidate_maps(used), blur)]
    srgb = np.stack([linear_to_srgb(np.clip(x[..., :3], 0.0, 1.0)) for x in renders])
    out = blend(srgb[0], band[..., None], oracle_pick(srgb, t_srgb))
    return _psnr(float(((out - t_srgb) ** 2).mean(-1)[m].mean()))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_split_args(ap, "research/refiner_headroom/results/refiner_headroom")
    ap.add_argument("--choices", action="store_true",
                    help="also: a perfect per-pixel choice (smoothed over 5 x 5 px) within the band among the level "
                    "rendered on the map and on it with near regions grown and shrunk by 3, 6 and 12 px (6 renders more)")
    args = ap.parse_args()
    args.out = split_out(args, "research/refiner_headroom/results/refiner_headroom")

    from bokehray_refiner.refine import RefineOptions, blend_weight, correct_and_render
    from bokehray_refiner.training.data import corrupt_disparity

    import bokehray as br
    from bokehray.colour import linear_to_srgb

    opts = RefineOptions()
    samples = split_samples(args)
    rows = []
    for name, image, disparity, blur, target, score_band in samples:
        t_srgb = linear_to_srgb(np.clip(target[..., :3], 0.0, 1.0))
        focus_srgb = linear_to_srgb(np.clip(image[..., :3], 0.0, 1.0))
        m = np.asarray(score_band, bool)
        for kind, amount in NET_CONDITIONS:
            d = np.clip(corrupt_disparity(disparity, kind, amount), 0.0, 1.0)
            render, used = correct_and_render(image, d, blur, lambda dd, im=image, bl=blur: br.render(im, dd, bl), opts)
            coc = blur.signed_coc(used).astype(np.float32)
            band, weight = blend_weight(image, focus_srgb, used, render, coc, opts)
            err2 = ((linear_to_srgb(np.clip(render[..., :3], 0.0, 1.0)) - t_srgb) ** 2).mean(-1)[m]
            total = float(err2.sum())
            if args.choices:
                extra = {"choice": _best_choice(image, used, blur, render, t_srgb, band, m)}
            else:
                extra = {}
            rows.append(extra | {"pair": name, "corruption": kind, "px": amount,
                         "fix": _psnr(float(err2.mean())),
                         "gated": _psnr(float(((1 - weight[m]) ** 2 * err2).mean())),
                         "band": _psnr(float(((1 - band[m]) ** 2 * err2).mean())),
                         "error_share_gated": float((err2 * (1 - (1 - weight[m]) ** 2)).sum() / total) if total else 0.0,
                         "error_share_band": float((err2 * (1 - (1 - band[m]) ** 2)).sum() / total) if total else 0.0})
        print(name, flush=True)
    summary = []
    for kind, amount in NET_CONDITIONS:
        sel = [r for r in rows if (r["corruption"], r["px"]) == (kind, amount)]
        cap = lambda key, sel=sel: float(np.mean([min(r[key], 99.0) for r in sel]))  # noqa: E731  (inf: capped)
        summary.append({"corruption": kind, "px": amount, "fix": cap("fix"), "gated": cap("gated"),
                        **({"choice": cap("choice")} if args.choices else {}),
                        "band": cap("band"),
                        "error_share_gated": float(np.mean([r["error_share_gated"] for r in sel])),
                        "error_share_band": float(np.mean([r["error_share_band"] for r in sel]))})
    print(f"{'depth':>12} {'fix':>6} {'perfect, gated':>15} {'error reachable: gated':>23} {'band':>6}")
    for s in summary:
        print(f"{s['corruption'] + ' ' + str(s['px']):>12} {s['fix']:6.2f} {s['gated'] - s['fix']:+15.2f} "
              f"{100 * s['error_share_gated']:22.0f}% {100 * s['error_share_band']:5.0f}%"
              + (f"  perfect choice among renders: {s['choice'] - s['fix']:+.2f}" if "choice" in s else ""))
    print("(band PSNR in dB, mean over renders; a perfect network's gain behind the gate; the share of the score "
          "band's squared error a perfect network removes behind the gate, and behind the band alone)")
    write_json(args.out, {"machine": machine_info(), "data": str(args.devset or args.data),
                          "refine_options": repr(opts), "summary": summary, "rows": rows})


if __name__ == "__main__":
    main()
