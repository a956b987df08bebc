"""Clipped highlights: the path-traced dev set rendered from its clipped 8-bit sRGB versions, scored against the
HDR truth.

Each scene's linear ``image.exr`` is clipped to [0, 1], written as an 8-bit sRGB PNG and read back through
``bokehray.read_image`` (what a user's JPEG/PNG gives the renderer); every (focus, K) render of the set is made
with the preview at its defaults and scored by the dev set's own ``score.py`` (PSNR / SSIM in clipped sRGB,
whole image and the depth-edge band), per scene group:

* ``highlights``: the scenes whose HDR image exceeds 1 (``has_highlights`` in info.json: d3, lamps of radiance 3-8);
* ``no highlights``: the others (d1, d2), where a reconstruction must not lose anything.

Variants: no reconstruction (bokehray's behaviour before highlight reconstruction), ``--highlight-boost 4`` (the old opt-in
boost), the reconstruction that is now the default for display-referred inputs
(``bokehray.photo.highlights.reconstruct_highlights``), and the HDR input itself (the ceiling: what the 8-bit file lost).

Usage (from the repository root)::

    python benchmarks/renderer/bench_highlights.py                    # JSON to benchmarks/results/highlights.json
    python benchmarks/renderer/bench_highlights.py --figure docs/img/highlights.png
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import numpy as np

import bokehray as br
from bokehray.photo import highlights

ROOT = Path(__file__).resolve().parents[2]
VARIANTS = {
    "8-bit, no reconstruction (before)": lambda img: img,
    "8-bit, --highlight-boost 4": lambda img: br.boost_highlights(img, 4.0),
    "8-bit, reconstruction (new default)": lambda img: highlights.reconstruct_highlights(img)[0],
    "HDR input (ceiling)": None,
}


def clipped_8bit(data: Path, scene: str, tmp: Path) -> np.ndarray:
    hdr = br.read_image(data / scene / "image.exr")
    path = br.write_image(tmp / f"{scene}.png", np.clip(hdr, 0.0, 1.0))  # 8-bit sRGB, as a camera JPEG/PNG holds it
    return br.read_image(path)


def render_group(data: Path, scenes: list[str], variant, out: Path, tmp: Path) -> None:
    for scene in scenes:
        info = json.loads((data / scene / "info.json").read_text())
        image = br.read_image(data / scene / "image.exr") if variant is None else variant(clipped_8bit(data, scene,
                                                                                                        tmp))
        disparity = br.read_disparity(data / scene / "disparity.exr")
        for r in info["renders"]:
            blur = br.BlurParams(r["K"], min(1.0, max(0.0, r["focus_disparity"])))
            br.write_image(out / scene / f"{r['file']}.exr", br.render(image, disparity, blur))


def score(data: Path, scenes: list[str], pred: Path, tmp: Path) -> dict:
    """score.py over ``scenes`` only: a ground-truth folder of links to those scenes."""
    gt = tmp / "gt"
    shutil.rmtree(gt, ignore_errors=True)
    gt.mkdir()
    for scene in scenes:
        (gt / scene).symlink_to(data / scene)
    text = subprocess.run([sys.executable, str(data / "score.py"), str(pred), "--gt", str(gt)], capture_output=True,
                          text=True, check=True).stdout
    m = re.search(r"mean over \d+ renders\s+([\d.]+)\s+([\d.]+)\s+([\d.]+)\s+([\d.]+)", text)
    return dict(zip(("psnr", "ssim", "band_psnr", "band_ssim"), map(float, m.groups()))) | {"table": text}


def figure(data: Path, path: Path, scene="d3_lamps_ring_writing", name="bokeh_f0_k1", box=(20, 150, 150)) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    info = json.loads((data / scene / "info.json").read_text())
    r = next(r for r in info["renders"] if r["file"] == name)
    disparity = br.read_disparity(data / scene / "disparity.exr")
    blur = br.BlurParams(r["K"], min(1.0, r["focus_disparity"]))
    with tempfile.TemporaryDirectory() as tmp:
        img8 = clipped_8bit(data, scene, Path(tmp))
    shots = {"8-bit, before": br.render(img8, disparity, blur),
             "8-bit, --highlight-boost 4": br.render(br.boost_highlights(img8, 4.0), disparity, blur),
             "8-bit, reconstructed (default)": br.render(highlights.reconstruct_highlights(img8)[0], disparity, blur),
             "path-traced HDR truth": br.read_image(data / scene / f"{name}.exr")}
    y, x, size = box
    fig, axes = plt.subplots(1, len(shots), figsize=(3.2 * len(shots), 3.4))
    for ax, (title, img) in zip(axes, shots.items()):
        ax.imshow(br.colour.linear_to_srgb(np.clip(img[y:y + size, x:x + size], 0, 1)))
        ax.set_title(title, fontsize=9)
        ax.set_xticks([]), ax.set_yticks([])
    fig.suptitle(f"{scene} {name} (K = {r['K']:g}): bokeh of lamps of radiance 3-8 stored clipped at 1", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=90)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data" / "pathtraced-dev")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results")
    ap.add_argument("--figure", type=Path, help="also save crops of a highlight scene (PNG)")
    args = ap.parse_args()
    if not (args.data / "score.py").exists():
        print(f"dev set not found at {args.data}: skipped (pass --data DIR)")
        return 0
    infos = {p.parent.name: json.loads(p.read_text()) for p in sorted(args.data.glob("*/info.json"))}
    groups = {"highlights": [s for s, i in infos.items() if i.get("has_highlights")],
              "no highlights": [s for s, i in infos.items() if not i.get("has_highlights")]}
    results: dict = {"groups": groups, "variants": {}}
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        for vname, variant in VARIANTS.items():
            results["variants"][vname] = {}
            for gname, scenes in groups.items():
                pred = tmp / re.sub(r"\W+", "_", vname) / gname.replace(" ", "_")
                render_group(args.data, scenes, variant, pred, tmp)
                results["variants"][vname][gname] = score(args.data, scenes, pred, tmp)
    before = results["variants"]["8-bit, no reconstruction (before)"]
    new = results["variants"]["8-bit, reconstruction (new default)"]
    results["gain_db"] = {g: round(new[g]["psnr"] - before[g]["psnr"], 2) for g in groups}
    results["target"] = {"highlights gain >= 2.5 dB": results["gain_db"]["highlights"] >= 2.5,
                         "no loss without highlights": results["gain_db"]["no highlights"] >= 0.0}
    print("| variant | highlights PSNR | band PSNR | SSIM | no highlights PSNR | band PSNR | SSIM |")
    print("|---|---|---|---|---|---|---|")
    for vname, r in results["variants"].items():
        h, n = r["highlights"], r["no highlights"]
        print(f"| {vname} | {h['psnr']:.2f} | {h['band_psnr']:.2f} | {h['ssim']:.4f} | {n['psnr']:.2f} | "
              f"{n['band_psnr']:.2f} | {n['ssim']:.4f} |")
    print(f"gain of the new default over before: {results['gain_db']}  targets met: {results['target']}")
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "highlights.json").write_text(json.dumps(results, indent=1))
    if args.figure:
        figure(args.data, args.figure)
    return 0


if __name__ == "__main__":
    sys.exit(main())
