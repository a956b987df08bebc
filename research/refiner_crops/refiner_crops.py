"""Crops for docs/refiner.md: input, preview, ungated refine, gated refine, path-traced truth (two dev-set renders).

    python research/refiner_crops/refiner_crops.py [--devset DIR]     # writes docs/img/refiner_gate_crops.png
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "research" / "refiner_choice"))
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks" / "refiner"))
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

from bench_refiner import devset_samples
from common import REPO

CASES = {"d2_leafy_twig/bokeh_f1_k1": ("erode", 3, (60, 100, 128)),
         "d3_lamps_ring_writing/bokeh_f0_k1": ("none", 0, (100, 100, 128))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--devset", default=str(REPO.parent / "shared/data/pathtraced-dev"))
    ap.add_argument("--out", default=str(REPO / "docs/img/refiner_gate_crops.png"))
    args = ap.parse_args()
    from bokehray_refiner.gate import GateOptions
    from bokehray_refiner.refine import RefineOptions, refine
    from bokehray_refiner.training.data import corrupt_disparity
    from PIL import Image

    import bokehray as br
    from bokehray.colour import linear_to_srgb

    rows = []
    for name, image, disp, blur, target, _ in devset_samples(Path(args.devset)):
        if name not in CASES:
            continue
        kind, px, (y, x, s) = CASES[name]
        d = corrupt_disparity(disp, kind, px)
        pre = br.render(image, d, blur)
        gated, _ = refine(image, d, blur, pre)
        raw, _ = refine(image, d, blur, pre, options=RefineOptions(gate=GateOptions(enabled=False)))
        sl = (slice(y, y + s), slice(x, x + s))
        rows.append(np.concatenate([linear_to_srgb(np.clip(a[sl][..., :3], 0, 1))
                                    for a in (image, pre, raw, gated, target)], 1))
    img = (np.concatenate(rows, 0) * 255).astype(np.uint8)
    Image.fromarray(img).resize((img.shape[1] * 2, img.shape[0] * 2), Image.NEAREST).save(args.out)


if __name__ == "__main__":
    main()
