"""Soft depth maps against exact references: the path-traced dev set with its maps made soft the ways people's maps
are, and the analytic two-plane scene (docs/soft-scene.md, "Soft maps").

Map kinds: ``exact`` (the dev set's own), ``gauss2`` / ``gauss4`` / ``gauss8`` (a Gaussian of that sigma in px),
``down4`` (downsampled 4x by block means and upsampled bilinearly: a model's resolution), ``halo`` (a Gaussian of
4 px after a 2 px dilation: a model's halo around the subject). Each is rendered by the preview with ramps read as
edges (the default, ``LayerOptions(soft_maps=True)``), as edges after the thin structures' depth is restored from
the photo (``thin_depth=True``) and as surfaces (``soft_maps=False``), and scored by the dev
set's own PSNR (whole frame and the band within 8 px of a depth edge of the exact depth) against the exact renders.
The two-plane scene (``tests/reference/two_planes_ref.py``: a textured disc at disparity 1 over a textured plane at
0, float64 thin-lens reference) is scored in the band within R + 4 px of the rim, with the hard map and with it
blurred by a Gaussian of 4 px, K = 24, focus 0.15 / 0.5 / 0.85.

Usage (from the repository root)::

    python benchmarks/renderer/bench_soft_maps.py               # prints the tables (about 2 minutes on 2 cores)
    python benchmarks/renderer/bench_soft_maps.py --out benchmarks/results
    python benchmarks/renderer/bench_soft_maps.py --figure docs/img/soft_maps_crops.png
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import numpy as np
from scipy import ndimage

import bokehray as br
from benchmarks import common

ROOT = Path(__file__).resolve().parents[2]
KINDS = ("exact", "gauss2", "gauss4", "gauss8", "down4", "halo")
VARIANTS = (("edges", br.LayerOptions()), ("edges + thin depth", br.LayerOptions(thin_depth=True)),
            ("surfaces", br.LayerOptions(soft_maps=False)))


def soften(d: np.ndarray, kind: str) -> np.ndarray:
    """The map ``d`` made soft as ``kind`` (see the module's docstring), clipped to [0, 1]."""
    if kind == "exact":
        out = d
    elif kind.startswith("gauss"):
        out = ndimage.gaussian_filter(d, float(kind[5:]), mode="nearest")
    elif kind == "down4":
        h, w = d.shape
        small = d[: h // 4 * 4, : w // 4 * 4].reshape(h // 4, 4, w // 4, 4).mean((1, 3))
        out = ndimage.zoom(small, 4, order=1, mode="nearest", grid_mode=True)
        out = np.pad(out, ((0, h - out.shape[0]), (0, w - out.shape[1])), mode="edge")
    elif kind == "halo":
        out = ndimage.gaussian_filter(ndimage.grey_dilation(d, size=5), 4.0, mode="nearest")
    else:
        raise ValueError(f"unknown map kind {kind!r}")
    return np.clip(out, 0.0, 1.0).astype(np.float32)


def _scorer(data: Path):
    spec = importlib.util.spec_from_file_location("devset_score", data / "score.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def load_devset(data: Path):
    """The set's scorer and its scenes: (folder, info, image, exact disparity, the 8 px band at depth edges)."""
    sc = _scorer(data)
    scenes = []
    for info_path in sorted(data.glob("*/info.json")):
        sd = info_path.parent
        scenes.append((sd, json.loads(info_path.read_text()), br.read_image(sd / "image.exr"),
                       br.read_disparity(sd / "disparity.exr"),
                       sc.discontinuity_band(sc.read_exr(str(sd / "depth.exr")), 8.0)))
    return sc, scenes


def devset(data: Path, kinds=KINDS) -> dict:
    """Mean whole and band PSNR over the 18 renders, per map kind and variant."""
    sc, scenes = load_devset(data)
    out = {}
    for kind in kinds:
        for variant, layers in VARIANTS:
            whole, band, seconds = [], [], 0.0
            for sd, info, image, disp, edge_band in scenes:
                d = soften(disp, kind)
                for r in info["renders"]:
                    gt = sc.to_srgb(sc.read_exr(str(sd / (r["file"] + ".exr"))))
                    blur = br.BlurParams(r["K"], min(1.0, max(0.0, r["focus_disparity"])))
                    t = time.perf_counter()
                    pred = br.render(image, d, blur, layers=layers)
                    seconds += time.perf_counter() - t
                    p = sc.to_srgb(pred)
                    whole.append(sc.psnr(gt, p))
                    band.append(sc.psnr(gt, p, edge_band))
            out[f"{kind} {variant}"] = {"psnr": float(np.mean(whole)), "band_psnr": float(np.mean(band)),
                                        "worst_psnr": float(np.min(whole)), "seconds_18": seconds}
            print(f"  dev set {kind:7s} ramps as {variant:22s}: PSNR {np.mean(whole):6.2f}  band {np.mean(band):6.2f}",
                  flush=True)
    return out


def two_planes(foci=(0.15, 0.5, 0.85), k: float = 24.0, sigma: float = 4.0) -> dict:
    """Band PSNR of the two-plane scene: the hard map, the soft map as edges and as surfaces."""
    from tests.reference.two_planes_ref import TwoPlanes

    scene = TwoPlanes()
    photo, hard = scene.photo().astype(np.float32), scene.hard_map().astype(np.float32)
    soft = ndimage.gaussian_filter(hard, sigma, mode="nearest").astype(np.float32)
    yy, xx = np.mgrid[0 : scene.n, 0 : scene.n] + 0.5
    rim = np.abs(np.hypot(yy - scene.c, xx - scene.c) - scene.radius)

    def band_psnr(a, b, m):
        s = lambda x: np.where((x := np.clip(x, 0, 1)) <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)  # noqa: E731
        return float(10 * np.log10(1.0 / ((s(a) - s(b)) ** 2)[m].mean()))

    out = {}
    for f in foci:
        ref = scene.bokeh(k, f)
        band = rim <= k * max(f, 1 - f) + 4
        blur = br.BlurParams(k, f)
        row = {"hard": band_psnr(br.render(photo, hard, blur), ref, band),
               "soft, ramps as edges": band_psnr(br.render(photo, soft, blur), ref, band),
               "soft, ramps as edges + thin depth": band_psnr(
                   br.render(photo, soft, blur, layers=br.LayerOptions(thin_depth=True)), ref, band),
               "soft, ramps as surfaces": band_psnr(br.render(photo, soft, blur,
                                                              layers=br.LayerOptions(soft_maps=False)), ref, band)}
        out[f"focus {f}"] = row
        print(f"  two planes, focus {f}: " + ", ".join(f"{k} {v:.2f}" for k, v in row.items()), flush=True)
    return out


def figure(path: Path) -> None:
    """100 % crops of the demo at 1536 x 1024 with its map blurred by 4 px, focused on the subject and far: the exact
    map's render, the soft map's with ramps as edges, and as surfaces."""
    from PIL import Image

    from bokehray.app.demo import build_demo_scene
    from bokehray.colour import linear_to_srgb
    from bokehray.photo.subject import k_from_amount, subject_focus

    sc = build_demo_scene(1536, 1024)
    soft = soften(sc.disparity, "gauss4")
    k = k_from_amount(50.0, 1024, 1536)
    rows = []
    for focus, (y0, x0) in ((subject_focus(soft).d_f, (420, 740)), (0.1, (420, 740))):
        blur = br.BlurParams(k, focus)
        tiles = [br.render(sc.image, sc.disparity, blur), br.render(sc.image, soft, blur),
                 br.render(sc.image, soft, blur, layers=br.LayerOptions(soft_maps=False))]
        rows.append(np.concatenate([t[y0 : y0 + 240, x0 : x0 + 320] for t in tiles], 1))
    img = (np.clip(linear_to_srgb(np.clip(np.concatenate(rows, 0), 0, 1)), 0, 1) * 255 + 0.5).astype(np.uint8)
    Image.fromarray(img).save(path)
    print(f"wrote {path}: columns exact map | soft map, ramps as edges | ramps as surfaces; rows focus subject, far")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data" / "pathtraced-dev")
    ap.add_argument("--out", type=Path, help="folder for soft-maps.json (default: print only)")
    ap.add_argument("--figure", type=Path, help="only draw the demo's 100 %% crops into this PNG")
    args = ap.parse_args()
    if args.figure:
        figure(args.figure)
        return 0
    results = {"machine": common.machine_info(), "two_planes": two_planes()}
    if (args.data / "score.py").exists():
        results["devset"] = devset(args.data)
    else:
        print(f"dev set not found at {args.data}: its part skipped (pass --data DIR)")
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "soft-maps.json").write_text(json.dumps(results, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
