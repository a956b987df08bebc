"""Score the preview renderer against the path-traced thin-lens dev set (shared/data/pathtraced-dev).

The dev set's own ``score.py`` is the referee: this script renders every
(scene, focus, K) of the set with each variant, writes the predictions as
linear EXR, and runs ``score.py`` on them (whole image and the band within
8 px of a depth discontinuity).

Usage (from the repository root)::

    python benchmarks/renderer/bench_devset.py                   # data in ../shared/data/pathtraced-dev
    python benchmarks/renderer/bench_devset.py --data DIR --out benchmarks/results
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import bokehray as br

ROOT = Path(__file__).resolve().parents[2]
VARIANTS = {
    "raytrace (photo mode, defaults)": "raytrace",
    "preview (default)": br.LayerOptions(),
    "preview, no hidden-region fill": br.LayerOptions(fill=False),
    "plain scatter (one layer, no occlusion)": br.LayerOptions(max_layers=1, fill=False),
}


def render_set(data: Path, out: Path, options: br.LayerOptions | str) -> float:
    """Render all dev-set pairs into ``out``; returns the total render time in seconds."""
    total = 0.0
    for info_path in sorted(data.glob("*/info.json")):
        scene = info_path.parent
        info = json.loads(info_path.read_text())
        image = br.read_image(scene / "image.exr")
        disparity = br.read_disparity(scene / "disparity.exr")
        for r in info["renders"]:
            blur = br.BlurParams(r["K"], min(1.0, max(0.0, r["focus_disparity"])))
            t = time.perf_counter()
            if options == "raytrace":
                pred = br.render(image, disparity, blur, quality="raytrace")
            else:
                pred = br.render(image, disparity, blur, layers=options)
            total += time.perf_counter() - t
            br.write_image(out / scene.name / f"{r['file']}.exr", pred)
    return total


def score(data: Path, pred: Path) -> dict:
    text = subprocess.run([sys.executable, str(data / "score.py"), str(pred)], capture_output=True, text=True,
                          check=True).stdout
    rows = {}
    for line in text.splitlines():
        m = re.match(r"\s*(mean over 18 renders|K=\d+)\s+([\d.]+)\s+([\d.]+)\s+([\d.]+)\s+([\d.]+)", line)
        if m:
            rows[m.group(1)] = dict(zip(("psnr", "ssim", "band_psnr", "band_ssim"), map(float, m.groups()[1:])))
    return {"summary": rows, "table": text}


def crops_figure(data: Path, path: Path, cases=(("d3_lamps_ring_writing", "bokeh_f0_k1", (60, 40, 200)),
                                                  ("d2_leafy_twig", "bokeh_f1_k2", (40, 60, 200)),
                                                  ("d1_wire_mesh", "bokeh_f1_k1", (100, 100, 160)))) -> None:
    """Side-by-side crops at depth edges: input, plain scatter, preview, path-traced truth."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    cols = ("all-in-focus input", "plain scatter", "bokehray preview", "bokehray raytrace", "path-traced truth")
    fig, axes = plt.subplots(len(cases), 5, figsize=(15, 3.1 * len(cases)))
    for row, (scene, name, (y, x, size)) in enumerate(cases):
        info = json.loads((data / scene / "info.json").read_text())
        r = next(r for r in info["renders"] if r["file"] == name)
        image = br.read_image(data / scene / "image.exr")
        disparity = br.read_disparity(data / scene / "disparity.exr")
        blur = br.BlurParams(r["K"], min(1.0, r["focus_disparity"]))
        shots = (image, br.render(image, disparity, blur, layers=VARIANTS["plain scatter (one layer, no occlusion)"]),
                 br.render(image, disparity, blur), br.render(image, disparity, blur, quality="raytrace"),
                 br.read_image(data / scene / f"{name}.exr"))
        for col, img in enumerate(shots):
            ax = axes[row, col]
            ax.imshow(br.colour.linear_to_srgb(np.clip(img[y:y + size, x:x + size], 0, 1)))
            ax.set_xticks([]), ax.set_yticks([])
            if row == 0:
                ax.set_title(cols[col])
            if col == 0:
                ax.set_ylabel(f"{scene}\n{name} (K={r['K']:g})", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=90)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data" / "pathtraced-dev")
    ap.add_argument("--out", type=Path, help="folder for devset--preview.json (default: print only)")
    ap.add_argument("--figure", type=Path, help="also save side-by-side crops at depth edges (PNG)")
    args = ap.parse_args()
    if not (args.data / "score.py").exists():
        print(f"dev set not found at {args.data}: skipped (pass --data DIR)")
        return 0
    results = {}
    for name, opts in VARIANTS.items():
        with tempfile.TemporaryDirectory() as tmp:
            render_set(args.data, Path(tmp), opts)  # warm-up: kernels compile on first use
            seconds = render_set(args.data, Path(tmp), opts)
            results[name] = score(args.data, Path(tmp)) | {"render_seconds_18": round(seconds, 3)}
    print("| variant | PSNR | SSIM | band PSNR | band SSIM | K=8 PSNR | K=16 PSNR | K=32 PSNR | time for 18 (s) |")
    print("|---|---|---|---|---|---|---|---|---|")
    for name, r in results.items():
        m, s = r["summary"]["mean over 18 renders"], r["summary"]
        print(f"| {name} | {m['psnr']:.2f} | {m['ssim']:.4f} | {m['band_psnr']:.2f} | {m['band_ssim']:.4f} | "
              f"{s['K=8']['psnr']:.2f} | {s['K=16']['psnr']:.2f} | {s['K=32']['psnr']:.2f} | "
              f"{r['render_seconds_18']:.2f} |")
    print("\nPer render (default variant):\n" + results["preview (default)"]["table"])
    if args.figure:
        crops_figure(args.data, args.figure)
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "devset--preview.json").write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
