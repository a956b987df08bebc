"""Score a map restoration on the dev set: the map's error against the exact disparity, and the preview's PSNR
(whole / band) against the path-traced renders, per soft-map kind.

    python research/soft_thin/evaluate.py [--kinds exact gauss2 ...] [--maps-only] [--set key=value ...]
"""

from __future__ import annotations

import argparse
import ast
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np  # noqa: E402

import bokehray as br  # noqa: E402
from benchmarks.renderer.bench_soft_maps import KINDS, load_devset, soften  # noqa: E402

DATA = ROOT.parent / "shared" / "data" / "pathtraced-dev"


def run(fix, kinds, maps_only=False, data: Path = DATA, renders=None, layers=None):
    sc, scenes = load_devset(data)
    out = {}
    for kind in kinds:
        whole, band, mae, far, t_fix = [], [], [], [], 0.0
        for sd, info, image, disp, edge_band in scenes:
            d = soften(disp, kind)
            if fix is not None:
                t = time.perf_counter()
                d = np.clip(fix(image, d), 0, 1).astype(np.float32)
                t_fix += time.perf_counter() - t
            err = np.abs(d - disp)
            mae.append(err.mean())
            far.append((err > 0.05).mean())
            if maps_only:
                continue
            for r in info["renders"]:
                if renders and r["file"] not in renders:
                    continue
                gt = sc.to_srgb(sc.read_exr(str(sd / (r["file"] + ".exr"))))
                blur = br.BlurParams(r["K"], min(1.0, max(0.0, r["focus_disparity"])))
                p = sc.to_srgb(br.render(image, d, blur, layers=layers))
                whole.append(sc.psnr(gt, p))
                band.append(sc.psnr(gt, p, edge_band))
        row = {"map_mae": float(np.mean(mae)), "map_off_005": float(np.mean(far)), "fix_s": t_fix}
        if whole:
            row.update(psnr=float(np.mean(whole)), band_psnr=float(np.mean(band)))
        out[kind] = row
        print(f"  {kind:7s} " + "  ".join(f"{k} {v:.4f}" for k, v in row.items())
              + "  per-scene mae " + " ".join(f"{m:.4f}" for m in mae), flush=True)
    return out


def main() -> int:
    import proto

    ap = argparse.ArgumentParser()
    ap.add_argument("--kinds", nargs="+", default=list(KINDS))
    ap.add_argument("--maps-only", action="store_true")
    ap.add_argument("--none", action="store_true", help="no restoration (the baseline)")
    ap.add_argument("--set", nargs="*", default=[], help="proto.restore keyword=value")
    args = ap.parse_args()
    kw = {}
    for s in args.set:
        k, v = s.split("=")
        kw[k] = ast.literal_eval(v)
    fix = None if args.none else (lambda img, d: proto.restore(img, d, **kw))
    print(f"restore {kw}" if fix else "baseline")
    run(fix, args.kinds, args.maps_only)
    return 0


if __name__ == "__main__":
    sys.exit(main())
