"""Peak memory and time of large renders, untiled and tiled, up to 24 megapixels (CPU).

Each configuration runs in a fresh process (so one render's memory cannot hide another's):
the child loads the demo scene from an .npz, renders a 256 x 256 crop (Warp's kernels loaded: code, not
arrays), reports its RSS, renders once and reports its peak RSS (VmHWM) and the render's own memory estimate. Blur: focused near, K chosen so the
largest CoC radius is ``R`` px. Results go to ``benchmarks/results/memory--<machine>.json``
and a markdown table is printed (docs/robustness.md).

Usage (from the repository root)::

    python benchmarks/photo/bench_memory.py              # the full sweep (about 15 minutes on 2 cores)
    python benchmarks/photo/bench_memory.py --quick      # 1.5 MP only, a smoke test
    python benchmarks/photo/bench_memory.py --model      # the preview's memory model against peaks, 1.5 to 24 MP
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import numpy as np

from benchmarks import common

SIZES = {1.5: (1500, 1000), 6: (3000, 2000), 12: (4242, 2828), 24: (6000, 4000)}
# (megapixels, quality, R, tile_size, memory_limit_mb, max_spp)
FULL = [
    (1.5, "preview", 64, None, None, None),
    (6, "preview", 64, None, None, None),
    (12, "preview", 64, None, None, None),
    (24, "preview", 64, None, None, None),
    (24, "preview", 16, None, None, None),
    (24, "preview", 16, 1024, None, None),
    (24, "preview", 64, 2048, None, None),
    (24, "preview", 16, None, 3000, None),  # a budget below the untiled need: tiles chosen automatically
    (24, "preview", 64, None, 500, None),  # cannot fit: refused before allocating
    (1.5, "raytrace", 16, None, None, 4),
    (6, "raytrace", 16, None, None, 4),
    (6, "raytrace", 16, 1024, None, 4),
    (24, "raytrace", 16, 2048, None, 4),
]
# the preview's memory model (``bokehray.levels.preview``): untiled at R = 64, and 12 MP under a budget that holds
# one layer a worker untiled for one worker only (fewer workers instead of tiles)
MODEL = [(1.5, "preview", 64, None, None, None), (6, "preview", 64, None, None, None),
         (12, "preview", 64, None, None, None), (24, "preview", 64, None, None, None),
         (12, "preview", 64, None, 950, None)]
QUICK = [(1.5, "preview", 64, None, None, None), (1.5, "preview", 16, 512, None, None),
         (1.5, "raytrace", 16, None, None, 4), (1.5, "preview", 64, None, 50, None)]


def child(npz: str, quality: str, radius: str, tile: str, limit: str, spp: str) -> None:
    """Fresh process: load, report RSS, render once, report peak RSS and what the render did."""
    import warp

    warp.config.log_level = warp.LOG_WARNING
    import bokehray as br

    with np.load(npz) as f:
        image, disparity, focus = f["image"], f["disparity"], float(f["focus"])
    blur = br.BlurParams(float(radius) / max(float(np.abs(disparity - focus).max()), 1e-6), focus)
    memory = br.MemoryOptions(tile_size=None if tile == "-" else int(tile),
                              memory_limit_mb=None if limit == "-" else float(limit))
    rays = br.RaytraceOptions(max_spp=int(spp)) if spp != "-" else None
    # a small render first: Warp's kernel modules and the worker pool are code, not the arrays the estimate counts,
    # so "before" is taken with them loaded (the growth beyond it is what the estimate is compared with)
    br.render(np.ascontiguousarray(image[:256, :256]), np.ascontiguousarray(disparity[:256, :256]), blur,
              quality=quality, options=rays)
    common.report_rss(peak=False)
    t = time.perf_counter()
    try:
        _, stats = br.render_with_stats(image, disparity, blur, quality=quality, options=rays, memory=memory)
        info = {"seconds": time.perf_counter() - t, "image_tiles": stats.image_tiles,
                "memory_estimate_mb": getattr(stats, "memory_estimate_mb", None), "layers": stats.layers,
                "threads": getattr(stats, "threads", None)}
    except br.ResourceError as e:
        info = {"seconds": time.perf_counter() - t, "refused": str(e)}
    print("INFO=" + json.dumps(info), flush=True)
    common.report_rss(peak=True)


def run(plan: list, tmp: str) -> list[dict]:
    from bokehray.app.demo import build_demo_scene

    rows, built = [], {}
    for mp, quality, radius, tile, limit, spp in plan:
        w, h = SIZES[mp]
        npz = f"{tmp}/demo-{w}x{h}.npz"
        if npz not in built:
            scene = build_demo_scene(w, h)
            np.savez(npz, image=scene.image, disparity=scene.disparity, focus=scene.focus_near)
            built[npz] = True
            del scene
        args = [__file__, "--child", npz, quality, str(radius), str(tile or "-"), str(limit or "-"), str(spp or "-")]
        import subprocess

        p = subprocess.run([sys.executable, *args], cwd=common.REPO, capture_output=True, text=True, timeout=1800)
        kv = dict(ln.partition("=")[::2] for ln in p.stdout.splitlines() if "=" in ln)
        row = {"megapixels": mp, "width": w, "height": h, "quality": quality, "radius": radius,
               "tile_size": tile, "memory_limit_mb": limit, "max_spp": spp}
        if p.returncode != 0 or "PEAK_KB" not in kv:
            row["error"] = (p.stderr.strip().splitlines() or [f"exit code {p.returncode}"])[-1]
        else:
            row.update(json.loads(kv["INFO"]))
            row["before_mb"] = int(kv["RSS_KB"]) / 1024
            row["peak_mb"] = int(kv["PEAK_KB"]) / 1024
        print("  " + json.dumps(row), file=sys.stderr, flush=True)
        rows.append(row)
    return rows


def table(rows: list[dict]) -> str:
    out = ["| size | quality | R (px) | tile | budget (MB) | tiles | time (s) | peak RSS (MB) | of which before render | "
           "estimate (MB) | estimate / growth | workers |", "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        size = f"{r['width']}x{r['height']} ({r['megapixels']:g} MP)"
        rays = f" ({r['max_spp']} rays)" if r["max_spp"] else ""
        if "error" in r:
            out.append(f"| {size} | {r['quality']}{rays} | {r['radius']} | | | | | error: {r['error']} | | | | |")
            continue
        tiles = "refused" if "refused" in r else r["image_tiles"]
        est = r.get("memory_estimate_mb")
        ratio = f"{est / (r['peak_mb'] - r['before_mb']):.2f}" if est else ""
        out.append(f"| {size} | {r['quality']}{rays} | {r['radius']} | {r['tile_size'] or 'auto'} | "
                   f"{r['memory_limit_mb'] or 'auto'} | {tiles} | {r['seconds']:.1f} | {r['peak_mb']:.0f} | "
                   f"{r['before_mb']:.0f} | {f'{est:.0f}' if est else ''} | {ratio} | {r.get('threads') or ''} |")
    return "\n".join(out)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="1.5 MP only")
    ap.add_argument("--model", action="store_true", help="the preview's memory model: estimate against growth")
    ap.add_argument("--out", type=Path, default=common.REPO / "benchmarks" / "results")
    ap.add_argument("--child", nargs=6, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        child(*args.child)
        return 0
    machine = common.machine_info()
    with tempfile.TemporaryDirectory(prefix="bokehray-mem-") as tmp:
        rows = run(QUICK if args.quick else MODEL if args.model else FULL, tmp)
    print(table(rows))
    if args.model:
        for r in rows:
            if "peak_mb" in r and r.get("memory_estimate_mb"):
                r["growth_mb"] = r["peak_mb"] - r["before_mb"]
                r["estimate_over_growth"] = r["memory_estimate_mb"] / r["growth_mb"]
        path = common.write_json(args.out / f"memory-model--{common.machine_tag(machine)}.json",
                                 {"what": "demo scene, focused near, K such that the largest CoC is R px, untiled; "
                                          "one fresh process a row; growth = peak (VmHWM) - RSS after a 256 x 256 "
                                          "warm-up render; estimate = the render's memory_estimate_mb",
                                  "machine": machine, "rows": rows})
        print("wrote", path)
    elif not args.quick:
        path = common.write_json(args.out / f"memory--{common.machine_tag(machine)}.json",
                                 {"machine": machine, "rows": rows})
        print("wrote", path)
    return 0 if all("error" not in r for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
