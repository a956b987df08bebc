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
    python benchmarks/photo/bench_memory.py --soft --sizes 1.5,6 --maps exact,gauss4,edges --runs 4 --budget 1500
                                                         # the soft scene (split pixels) in the estimate
    python benchmarks/photo/bench_memory.py --soft --sizes strip --maps noise,checker --runs 1
                                                         # the soak's 20 000 x 2 strips (a frame of lights)

``--soft``: the default blur and focus of the command line (``--amount 50``, the subject's focus) on the demo
scene's map as it is (``exact``), blurred by a Gaussian of 4 or 6 px (``gauss4``, ``gauss6``: soft maps, snapped
to their plateaus) or with every third diagonal of the frame at the nearest disparity (``edges``: a depth edge at
every pixel); soft edges on. The warm-up renders a 256 x 256 crop of the same map (the soft scene's kernels
loaded); the peak is then reset (``VmHWM``), and a sampler thread reads the RSS every 2 ms to tell the peak before
the layers (the soft scene, the plan) from the peak during them. Each row a fresh process; ``--runs`` repeats
each case (median and range reported).
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
         (12, "preview", 64, None, 800, None)]
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


def soft_map(disparity: np.ndarray, kind: str) -> np.ndarray:
    """The demo's map as it is, blurred (``gauss4``, ``gauss6``) or with every third diagonal nearest (``edges``)."""
    if kind == "exact":
        return disparity
    if kind.startswith("gauss"):
        from scipy.ndimage import gaussian_filter

        return gaussian_filter(disparity, float(kind[5:])).astype(np.float32)
    if kind == "edges":
        yy, xx = np.indices(disparity.shape)
        return np.where((yy + xx) % 3 == 0, np.float32(disparity.max()), disparity).astype(np.float32)
    raise SystemExit(f"--maps: unknown map {kind!r} (exact, gauss4, gauss6, edges)")


class _Sampler:
    """The RSS every ``dt`` s in a thread: its peak before the layers (the soft scene, the plan) and after (from the
    estimate's planning on: ``plan`` filled)."""

    def __init__(self, plan: dict, dt: float = 0.002) -> None:
        import threading

        self.plan, self.dt, self.peaks, self.peak_at = plan, dt, {}, {}
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self.loop, daemon=True)
        self.t0 = time.perf_counter()

    def loop(self) -> None:
        import os

        page = os.sysconf("SC_PAGE_SIZE")
        with open("/proc/self/statm") as f:
            while not self.stop.is_set():
                f.seek(0)
                rss = int(f.read().split()[1]) * page
                phase = "layers" if self.plan else "before layers"
                if rss > self.peaks.get(phase, 0):
                    self.peaks[phase], self.peak_at[phase] = rss, time.perf_counter() - self.t0
                time.sleep(self.dt)


def _count_split() -> list[int]:
    """The split pixels' count of the last render (the pipeline's soft scene, wrapped)."""
    from bokehray import pipeline

    seen: list[int] = []
    inner = pipeline._soft_scene

    def wrapped(*a, **k):
        s, soft = inner(*a, **k)
        seen[:] = [0 if soft is None else len(soft)]
        return s, soft

    pipeline._soft_scene = wrapped
    return seen


def _record_plan() -> dict:
    """The estimate's parts of the next preview render: the frame's pixels, the layers' (pixels, bytes a pixel) and
    the workers (``bokehray.levels.preview._region_bytes``'s first call, wrapped)."""
    from bokehray.levels import preview

    plan: dict = {}
    inner = preview._region_bytes

    def wrapped(window_px, layers, threads, lazy_acc=False):
        if not plan:
            plan.update(frame_px=int(window_px), layers=[[int(v) for v in x] for x in layers], threads=int(threads),
                        lazy_acc=bool(lazy_acc))
        return inner(window_px, layers, threads, lazy_acc)

    preview._region_bytes = wrapped
    return plan


def soft_child(npz: str, kind: str, limit: str, heap: str) -> None:
    """Fresh process: the map, a 256 x 256 warm-up of it, the peak reset, one render with soft edges sampled.
    ``heap``: ``bounded`` (as rendered) or ``glibc`` (``bokehray._memory.bound_heap`` not called: glibc's moving
    mapping threshold, the heaps untrimmed; the A/B of docs/design/memory-model.md)."""
    import warp

    warp.config.log_level = warp.LOG_WARNING
    import bokehray as br
    from bokehray.photo.subject import AMOUNT_DEFAULT, default_focus, k_from_amount

    with np.load(npz) as f:
        image, disparity = f["image"], soft_map(f["disparity"], kind)
    h, w = disparity.shape
    blur = br.BlurParams(k_from_amount(AMOUNT_DEFAULT, h, w), float(default_focus(None, disparity).d_f))
    memory = br.MemoryOptions(memory_limit_mb=None if limit == "-" else float(limit))
    split = _count_split()
    plan = _record_plan()
    if heap == "glibc":
        from bokehray import pipeline
        from bokehray.levels import preview

        pipeline.bound_heap = preview.bound_heap = lambda: False
    br.render(np.ascontiguousarray(image[:256, :256]), np.ascontiguousarray(disparity[:256, :256]), blur)
    common.reset_peak_rss()
    common.report_rss(peak=False)
    plan.clear()
    sampler = _Sampler(plan)
    sampler.thread.start()
    t, cpu = time.perf_counter(), time.process_time()
    try:
        _, stats = br.render_with_stats(image, disparity, blur, memory=memory)
        info = {"seconds": time.perf_counter() - t, "memory_estimate_mb": stats.memory_estimate_mb,
                "threads": stats.threads, "layers": stats.layers, "image_tiles": stats.image_tiles,
                "cpu_seconds": time.process_time() - cpu, "split_pixels": split[0] if split else None, "plan": plan}
    except br.ResourceError as e:
        info = {"seconds": time.perf_counter() - t, "refused": str(e)}
    sampler.stop.set()
    sampler.thread.join()
    info["sampled_peak_mb"] = {k: v / (1 << 20) for k, v in sampler.peaks.items()}
    info["sampled_peak_at_s"] = sampler.peak_at
    print("INFO=" + json.dumps(info), flush=True)
    common.report_rss(peak=True)


STRIP_W = 20_000
"""``--sizes strip``: the soak's W x 2 strip (benchmarks/robustness/soak.py), its maps ``noise`` or ``checker``."""


def _soft_cases(mp, maps: list[str], tmp: str):
    """(npz, width, height, map, the child's map) of each case of one size: the demo scene's maps, or a strip's."""
    if mp == "strip":
        w, h = STRIP_W, 2
        image = np.random.default_rng(w).random((h, w, 3)).astype(np.float32)
        for kind in maps:
            if kind not in ("noise", "checker"):
                raise SystemExit(f"--maps: a strip's map is noise or checker, not {kind!r}")
            x = np.indices((h, w)).sum(0)
            d = (x % 2) if kind == "checker" else np.random.default_rng(1).random((h, w))
            npz = f"{tmp}/strip-{w}-{kind}.npz"
            np.savez(npz, image=image, disparity=d.astype(np.float32))
            yield npz, w, h, kind, "exact"
        return
    from bokehray.app.demo import build_demo_scene

    w, h = SIZES[mp]
    npz = f"{tmp}/demo-{w}x{h}.npz"
    scene = build_demo_scene(w, h)
    np.savez(npz, image=scene.image, disparity=scene.disparity)
    del scene
    for kind in maps:
        yield npz, w, h, kind, kind


def run_soft(sizes: list, maps: list[str], runs: int, limit: float | None, heap: str, tmp: str) -> list[dict]:
    """One fresh process a (size, map, run)."""
    import subprocess

    rows = []
    for mp in sizes:
        for npz, w, h, kind, child_kind in _soft_cases(mp, maps, tmp):
            for k in range(runs):
                args = [__file__, "--soft-child", npz, child_kind, str(limit or "-"), heap]
                p = subprocess.run([sys.executable, *args], cwd=common.REPO, capture_output=True, text=True,
                                   timeout=3600)
                row = {"megapixels": mp, "width": w, "height": h, "map": kind, "run": k, "memory_limit_mb": limit,
                       "heap": heap}
                row.update(_parse_child(p))
                print("  " + json.dumps(row), file=sys.stderr, flush=True)
                rows.append(row)
    return rows


def _parse_child(p) -> dict:
    kv = dict(ln.partition("=")[::2] for ln in p.stdout.splitlines() if "=" in ln)
    if p.returncode != 0 or "PEAK_KB" not in kv:
        return {"error": (p.stderr.strip().splitlines() or [f"exit code {p.returncode}"])[-1]}
    row = json.loads(kv["INFO"])
    row["before_mb"] = int(kv["RSS_KB"]) / 1024
    row["peak_mb"] = int(kv["PEAK_KB"]) / 1024
    row["growth_mb"] = row["peak_mb"] - row["before_mb"]
    if row.get("memory_estimate_mb"):
        row["estimate_over_growth"] = row["memory_estimate_mb"] / row["growth_mb"]
    return row


def soft_table(rows: list[dict]) -> str:
    """Per (size, map): growth median and range over the runs, the estimate, estimate / median growth, and the
    share of runs whose peak came before the layers."""
    import statistics

    out = ["| size | map | runs | growth MB, median (range) | estimate MB | estimate / median growth (range) | "
           "split pixels | peak before the layers |", "|---|---|---|---|---|---|---|---|"]
    cases: dict[tuple, list[dict]] = {}
    for r in rows:
        cases.setdefault((r["megapixels"], r["map"]), []).append(r)
    for (mp, kind), rs in cases.items():
        ok = [r for r in rs if "growth_mb" in r and r.get("memory_estimate_mb")]
        size = f"{STRIP_W} x 2" if mp == "strip" else f"{mp:g} MP"
        if not ok:
            out.append(f"| {size} | {kind} | {len(rs)} | error: {rs[0].get('error') or rs[0].get('refused')} "
                       "| | | | |")
            continue
        g = [r["growth_mb"] for r in ok]
        est = statistics.median(r["memory_estimate_mb"] for r in ok)
        ratios = [est / x for x in g]
        before = sum(_peak_before_layers(r) for r in ok)
        out.append(f"| {size} | {kind} | {len(ok)} | {statistics.median(g):.0f} ({min(g):.0f}-{max(g):.0f}) | "
                   f"{est:.0f} | {est / statistics.median(g):.2f} ({min(ratios):.2f}-{max(ratios):.2f}) | "
                   f"{ok[0].get('split_pixels') or ''} | {before} of {len(ok)} |")
    return "\n".join(out)


def _peak_before_layers(r: dict) -> bool:
    peaks = r.get("sampled_peak_mb", {})
    return peaks.get("before layers", 0) > peaks.get("layers", 0)

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


def soft_main(args) -> int:
    machine = common.machine_info()
    with tempfile.TemporaryDirectory(prefix="bokehray-mem-") as tmp:
        rows = run_soft([v if v == "strip" else float(v) for v in args.sizes.split(",")], args.maps.split(","),
                        args.runs, args.budget, args.heap, tmp)
    print(soft_table(rows))
    tag = "-" + args.sizes.replace(",", "-") + ("" if args.sizes == "strip" else "mp") + (
        "" if args.heap == "bounded" else "-glibc-heap")
    path = common.write_json(args.out / f"memory-soft{tag}--{common.machine_tag(machine)}.json",
                             {"what": "demo scene, --amount 50 and the subject's focus, soft edges on; one fresh "
                                      "process a row; growth = peak (VmHWM, reset after a 256 x 256 warm-up of the "
                                      "same map) - RSS after the warm-up; estimate = memory_estimate_mb",
                              "machine": machine, "rows": rows})
    print("wrote", path)
    return 0 if all("error" not in r for r in rows) else 1


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="1.5 MP only")
    ap.add_argument("--model", action="store_true", help="the preview's memory model: estimate against growth")
    ap.add_argument("--out", type=Path, default=common.REPO / "benchmarks" / "results")
    ap.add_argument("--soft", action="store_true", help="the soft scene in the estimate (--sizes, --maps, --runs)")
    ap.add_argument("--sizes", default="1.5,6", help="megapixels for --soft: 1.5, 6, 12, 24; or strip (20 000 x 2)")
    ap.add_argument("--maps", default="exact,gauss4,edges", help="maps for --soft: exact, gauss4, gauss6, edges")
    ap.add_argument("--runs", type=int, default=3, help="fresh processes a case for --soft")
    ap.add_argument("--budget", type=float, default=None, help="memory_limit_mb for --soft (default: automatic)")
    ap.add_argument("--child", nargs=6, help=argparse.SUPPRESS)
    ap.add_argument("--heap", choices=("bounded", "glibc"), default="bounded",
                    help="--soft: the C heap as rendered (bounded) or glibc's own (bound_heap not called)")
    ap.add_argument("--soft-child", nargs=4, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        child(*args.child)
        return 0
    if args.soft_child:
        soft_child(*args.soft_child)
        return 0
    if args.soft:
        return soft_main(args)
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
