"""Strands broken in the map: the demo's dashed blades focused far, with and without their gaps bridged.

The demo scene (``bokehray.app.demo``, 1536 x 1024) paints grass blades and stems 0.4 - 3 px wide; a blade thinner
than about a pixel gets its depth only where it covers half a pixel or more, so its map is a row of dashes. Focused
far, the blade blurs in front, and each gap's share of the blade stayed sharp: a column of specks.

The scene is built with its layers recorded, so each blade's coverage is known. A blade is *dashed* when its
alpha >= 0.5 pixels fall into more than 3 pieces (8-connected). The reference is the same render (defaults) with
every dashed blade's map made whole (each row's most covered pixel given the blade's depth too, the rest split by
the matting as usual), so that it differs from the render only by the map's breaks (a light a blade hides, which
``bokehray.strands.hidden_lights`` shows behind it, is in both). The **speck** of a render over a blade is the largest, over the blade's pixels (coverage >= 0.05), of
the render minus the reference, in 8-bit sRGB (largest channel), less that difference's median over 9 x 9 px (a
broad difference is the blur's level, not a speck).

It also times :func:`bokehray.strands.bridge_strands` on the demo's map focused far (CPU seconds of this process
and wall seconds, medians of warm runs) against the whole render, and writes a 100 % crop figure (photo, map,
bridged map, before, after, reference; 80 x 48 px around the worst speck, enlarged x4).

Usage (from the repository root)::

    python benchmarks/renderer/bench_strands.py                    # prints; JSON in benchmarks/results/strands.json
    python benchmarks/renderer/bench_strands.py --figure docs/img/strand_gaps_demo.png
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np
from scipy import ndimage

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/common.py

from common import REPO, machine_info

import bokehray as br
import bokehray.app.demo as demo
from bokehray.colour import linear_to_srgb
from bokehray.scene import cap_coc
from bokehray.strands import bridge_strands

W, H = 1536, 1024


def demo_with_blades() -> tuple[demo.DemoScene, list[dict]]:
    """The demo scene and its dashed blades: index, depth, coverage box and coverage."""
    painted = []
    over = demo._over

    def recording(img, disp, sl, alpha, rgb, d):
        painted.append((sl, alpha.copy(), d))
        return over(img, disp, sl, alpha, rgb, d)

    demo._over = recording
    try:
        scene = demo.build_demo_scene(W, H)
    finally:
        demo._over = over
    blades = []
    for i, (sl, a, d) in enumerate(painted):
        if np.ndim(d) != 0 or (a > 0.05).sum() < 50:
            continue  # the background, the panel and the cat carry a map of depths; lights are tiny
        pieces = ndimage.label(a >= 0.5, np.ones((3, 3)))[1]
        if pieces > 3:
            blades.append({"layer": i, "d": float(d), "slice": sl, "alpha": a, "pieces": int(pieces)})
    return scene, blades


def whole_map(scene: demo.DemoScene, blades: list[dict]) -> np.ndarray:
    disp = scene.disparity.copy()
    for b in blades:
        a = b["alpha"]
        line = a >= 0.5
        rows = np.flatnonzero(a.max(1) > 0.1)
        line[rows, a[rows].argmax(1)] = True
        sub = disp[b["slice"]]
        sub[:] = np.where(line, np.maximum(sub, b["d"]), sub)
    return disp


def speck_map(render: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Per pixel: ``render - ref`` in 8-bit sRGB (largest channel) less its median over 9 x 9 px."""
    d = (linear_to_srgb(np.clip(render, 0, 1)) - linear_to_srgb(np.clip(ref, 0, 1))) * 255
    local = np.stack([ndimage.median_filter(d[..., c], size=9) for c in range(3)], -1)
    return (d - local).max(2)


def speck(render: np.ndarray, ref: np.ndarray, where: np.ndarray) -> float:
    return float(speck_map(render, ref)[where].max())


def timed(fn, runs: int) -> dict:
    fn()
    wall, cpu = [], []
    for _ in range(runs):
        t, c = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
    return {"wall_median": statistics.median(wall), "cpu_median": statistics.median(cpu), "wall": wall, "cpu": cpu}


def figure(path: Path, scene, s, bridged, renders: dict, blade: dict) -> None:
    from PIL import Image

    where = np.zeros((H, W), bool)
    where[blade["slice"]] = blade["alpha"] >= 0.05
    sp = np.where(where, speck_map(renders["before"], renders["reference"]), -np.inf)
    cy, cx = np.unravel_index(int(np.argmax(sp)), sp.shape)  # the blade's worst speck before
    y0, x0 = int(np.clip(cy - 40, 0, H - 80)), int(np.clip(cx - 24, 0, W - 48))
    sl = np.s_[y0:y0 + 80, x0:x0 + 48]
    lo, hi = float(s.min()), float(s.max())
    maps = [np.repeat(((m[sl] - lo) / (hi - lo))[..., None], 3, 2) for m in (s, bridged)]
    tiles = [linear_to_srgb(np.clip(scene.image[sl], 0, 1)), *maps,
             *(linear_to_srgb(np.clip(renders[k][sl], 0, 1)) for k in ("before", "after", "reference"))]
    row = np.concatenate([np.pad(t, ((0, 0), (0, 3), (0, 0)), constant_values=1.0) for t in tiles], 1)
    im = (np.clip(row, 0, 1) * 255 + 0.5).astype(np.uint8)
    Image.fromarray(im).resize((im.shape[1] * 4, im.shape[0] * 4), Image.NEAREST).save(path)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=5, help="warm runs of the timing (0: none)")
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "strands.json")
    ap.add_argument("--figure", type=Path, help="write the crop figure here (PNG)")
    args = ap.parse_args(argv)
    scene, blades = demo_with_blades()
    blur = br.BlurParams(scene.k_px, scene.focus_far)
    renders = {"before": br.render(scene.image, scene.disparity, blur, layers=br.LayerOptions(strand_gaps=False)),
               "after": br.render(scene.image, scene.disparity, blur),
               "reference": br.render(scene.image, whole_map(scene, blades), blur)}
    s = cap_coc(blur.signed_coc(scene.disparity))
    bridged, n = bridge_strands(scene.image, s)
    rows = []
    for b in blades:
        where = np.zeros((H, W), bool)
        where[b["slice"]] = b["alpha"] >= 0.05
        row = {"layer": b["layer"], "d": b["d"], "pieces": b["pieces"],
               "speck_before": speck(renders["before"], renders["reference"], where),
               "speck_after": speck(renders["after"], renders["reference"], where)}
        rows.append(row)
        print(f"blade {row['layer']:3d} d={row['d']:.3f} {row['pieces']:3d} dashes: speck "
              f"{row['speck_before']:5.1f} -> {row['speck_after']:5.1f} (8-bit sRGB)")
    result = {"machine": machine_info(), "size": [W, H], "k_px": scene.k_px, "focus": scene.focus_far,
              "bridged_pixels": n, "blades": rows}
    if args.runs > 0:
        result["bridge_strands"] = timed(lambda: bridge_strands(scene.image, s), args.runs)
        result["render"] = timed(lambda: br.render(scene.image, scene.disparity, blur), max(1, args.runs // 2))
        t, r = result["bridge_strands"], result["render"]
        print(f"bridge_strands {t['cpu_median']:.3f} CPU-s ({t['wall_median']:.3f} s wall), "
              f"{n} pixels bridged; the render {r['cpu_median']:.2f} CPU-s ({r['wall_median']:.2f} s wall)")
    if args.figure:
        worst = max(rows, key=lambda r: r["speck_before"])
        figure(args.figure, scene, s, bridged, renders, next(b for b in blades if b["layer"] == worst["layer"]))
        print(f"wrote {args.figure}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1, default=float))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
