"""Crops for docs/refiner.md: a 2 px misregistered disparity map and the depth fix that shifts it back.

Columns: all-in-focus input, preview on the shifted map, refine (depth fix + gated residual), path-traced truth,
then the exact, the shifted and the corrected disparity (grey). Two dev-set renders, a 120 px crop around the
median of each one's edge band, shown at 2x.

    python research/refiner_crops/refiner_shift_crops.py [--devset DIR]     # writes docs/img/refiner_shift_crops.png
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

RENDERS = ("d2_leafy_twig/bokeh_f1_k2", "d3_lamps_ring_writing/bokeh_f1_k1")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--devset", default=str(REPO.parent / "shared/data/pathtraced-dev"))
    ap.add_argument("--out", default=str(REPO / "docs/img/refiner_shift_crops.png"))
    args = ap.parse_args()
    from bokehray_refiner.refine import load_refiner, refine
    from bokehray_refiner.training.data import corrupt_disparity
    from PIL import Image

    import bokehray as br
    from bokehray.colour import linear_to_srgb

    model = load_refiner(None)
    strips = []
    for name, img, disp, bl, tgt, band in devset_samples(Path(args.devset)):
        if name not in RENDERS:
            continue
        d = np.clip(corrupt_disparity(disp, "shift", 2), 0, 1)
        pre = br.render(img, d, bl)
        out, st = refine(img, d, bl, None, model=model, rerender=lambda dd, im=img, b=bl: br.render(im, dd, b))
        ys, xs = np.nonzero(band)
        y0, x0 = max(0, int(np.median(ys)) - 60), max(0, int(np.median(xs)) - 60)
        sl = (slice(y0, y0 + 120), slice(x0, x0 + 120))
        fixed = st.disparity if st.disparity is not None else d
        tiles = [linear_to_srgb(np.clip(x[sl][..., :3], 0, 1)) for x in (img, pre, out, tgt)]
        tiles += [np.repeat(x[sl][..., None], 3, 2) for x in (disp, d, fixed)]
        strips.append(np.concatenate(tiles, 1))
    a = (np.concatenate(strips, 0) * 255 + 0.5).clip(0, 255).astype(np.uint8)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(a).resize((a.shape[1] * 2, a.shape[0] * 2), Image.NEAREST).save(args.out)
    print(args.out)


if __name__ == "__main__":
    main()
