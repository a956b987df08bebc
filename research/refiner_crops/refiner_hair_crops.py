"""Crops for docs/refiner.md: a map that misses the hair by 10-20 px, and what refine makes of it.

The scene is exact: a furry body (``bokehray synth``'s ``fur`` kind: strands 4-18 px long around an ellipse) in
front of a photo, both planes, traced by ``bokehray.raytrace_layers``. The map given to every method is the true
one with the fur taken out: a grey opening with a disc of radius 6 px removes every strand (all narrower than
13 px), so the map's outline is the body's and misses the hair by the strands' length, as a hand-painted or
estimated map does. Two focus settings: on the background (the hair should dissolve in front of it) and on the
fur (the background should blur behind the hair without smearing it).

Columns: all-in-focus input, the map given, preview, depth fix alone, refine with each ``--weights`` (default:
the shipped ones), the exact render. Scores (PSNR in sRGB, clipped): the whole image and the band within 8 px of a
depth edge of the *true* map (the fur).

    python research/refiner_crops/refiner_hair_crops.py [--weights A.safetensors B.safetensors] [--labels shipped new] \
        [--edges [E.safetensors] --edge-threshold 0.7 --edge-colour-margin 0.05 --min-fixed-share 0]

``--edges`` adds a column: the depth fix and the learned edge placement (``bokehray_refiner.edges``), no residual.

Writes ``docs/img/refiner_hair_crops.png`` and ``research/refiner_crops/results/refiner_hair.json``.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "research" / "refiner_choice"))
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks" / "refiner"))
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

from common import REPO, machine_info, write_json

SIZE, K, CROP = 320, 24.0, 128


def fur_scene():
    """(layers, all-in-focus image, true disparity): the fur plane at 0.7 over a photo plane at 0.1."""
    from bokehray.data.synth import bundled_photo, fit_crop, pinhole_layers, procedural_layer
    from bokehray.levels.raytrace import Layer

    rng = np.random.default_rng(11)
    fur = procedural_layer("fur", SIZE, rng)
    bg = fit_crop(bundled_photo("coffee"), SIZE, rng)
    layers = [Layer(fur, plane=(0.0, 0.0, 0.7)),
              Layer(np.concatenate([bg, np.ones((SIZE, SIZE, 1), np.float32)], 2), plane=(0.0, 0.0, 0.1))]
    image, disparity = pinhole_layers(layers)
    return layers, image, disparity


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--weights", nargs="*", default=["shipped"],
                    help="refiner weights to compare; 'shipped': the package's own (the default)")
    ap.add_argument("--labels", nargs="*", help="a label for each --weights")
    ap.add_argument("--edges", nargs="?", const="shipped", default=None,
                    help="add the edge placement: the shipped edge network, or these weights (safetensors)")
    ap.add_argument("--edge-threshold", type=float, default=None, help="default: refine's")
    ap.add_argument("--edge-colour-margin", type=float, default=None)
    ap.add_argument("--min-fixed-share", type=float, default=None,
                    help="the edges column's map-level gate (default: refine's; 0: the network runs whatever the "
                         "depth fix found)")
    ap.add_argument("--out", default=str(REPO / "docs/img/refiner_hair_crops.png"))
    ap.add_argument("--json", default=str(REPO / "research/refiner_crops/results/refiner_hair.json"))
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    labels = args.labels or [(w if w == "shipped" else Path(w).parent.name) for w in args.weights]
    import torch

    torch.set_num_threads(args.threads)
    from bokehray_refiner.edges import load_edge_net
    from bokehray_refiner.refine import RefineOptions, load_refiner, refine
    from bokehray_refiner.training.data import corrupt_disparity
    from PIL import Image

    import bokehray as br
    from bokehray.colour import linear_to_srgb
    from bokehray.data.metrics import discontinuity_band, score

    layers, image, truth = fur_scene()
    given = np.clip(corrupt_disparity(truth, "missing", 6), 0, 1)
    band = discontinuity_band(truth)
    ys, xs = np.nonzero(band)
    cy, cx = int(np.percentile(ys, 10)), int(np.median(xs))  # the top of the fur: hair against the photo
    y0, x0 = int(np.clip(cy - CROP // 2, 0, SIZE - CROP)), int(np.clip(cx - CROP // 2, 0, SIZE - CROP))
    sl = (slice(y0, y0 + CROP), slice(x0, x0 + CROP))
    models = [load_refiner(None if w == "shipped" else w) for w in args.weights]
    edge_model = load_edge_net(None if args.edges == "shipped" else args.edges) if args.edges else None
    edges_only = RefineOptions(neural=False, edges=True, edge_colour_margin=args.edge_colour_margin)
    if args.edge_threshold is not None:
        edges_only = replace(edges_only, edge_threshold=args.edge_threshold)
    if args.min_fixed_share is not None:
        edges_only = replace(edges_only, min_fixed_share=args.min_fixed_share)
    rows, strips = [], []
    for focus_name, d_f in (("background", 0.1), ("fur", 0.7)):
        blur = br.BlurParams(K, d_f)
        exact, _ = br.raytrace_layers(layers, blur, options=br.RaytraceOptions(max_spp=128))
        exact = exact[..., :3]
        rer = lambda d, b=blur: br.render(image, d, b)  # noqa: E731
        pre = br.render(image, given, blur)
        fixed, _ = refine(image, given, blur, None, options=RefineOptions(neural=False, edges=False),
                          rerender=rer)
        outs = [("preview", pre), ("depth fix", fixed)]
        if edge_model is not None:
            outs.append(("edges", refine(image, given, blur, None, options=edges_only, rerender=rer,
                                         edge_model=edge_model)[0]))
        for label, model in zip(labels, models):
            outs.append((f"refine ({label})", refine(image, given, blur, None, model=model, rerender=rer)[0]))
        for name, img in outs:
            rows.append({"focus": focus_name, "method": name} | score(img, exact, band))
            print(f"focus on the {focus_name:10s} {name:20s} PSNR {rows[-1]['psnr']:6.2f}  band "
                  f"{rows[-1]['band_psnr']:6.2f}", flush=True)
        tiles = [linear_to_srgb(np.clip(image[sl], 0, 1)), np.repeat(given[sl][..., None], 3, 2)]
        tiles += [linear_to_srgb(np.clip(img[sl][..., :3], 0, 1)) for _, img in outs]
        tiles.append(linear_to_srgb(np.clip(exact[sl], 0, 1)))
        strips.append(np.concatenate([np.pad(t, ((2, 2), (2, 2), (0, 0)), constant_values=1.0) for t in tiles], 1))
    a = (np.concatenate(strips, 0) * 255 + 0.5).clip(0, 255).astype(np.uint8)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(a).resize((a.shape[1] * 2, a.shape[0] * 2), Image.NEAREST).save(args.out)
    write_json(args.json, {"machine": machine_info(), "size": SIZE, "k_px": K, "crop": [y0, x0, CROP],
                           "weights": args.weights, "edges": args.edges,
                           "edge_threshold": edges_only.edge_threshold if args.edges else None,
                           "min_fixed_share": edges_only.min_fixed_share if args.edges else None,
                           "edge_colour_margin": args.edge_colour_margin, "rows": rows})
    print(args.out)


if __name__ == "__main__":
    main()
