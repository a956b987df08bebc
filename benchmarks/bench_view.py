"""Latency of ``bokehray view``'s live preview on a 12 MP photo, through its HTTP server (CPU).

Builds the demo scene at 4000 x 3000 (12 MP), opens a view session on it, starts
the real server on 127.0.0.1 and replays drags as the page sends them (one
request at a time, as the page does): a focus sweep of clicks, the blur slider,
the blade rotation of a 6-blade aperture, the highlight boost. Each update is
timed as the page sees it (request sent to JPEG received) and as the server
reports it (render + encode). Warm runs only: the first updates of each drag
are dropped. The same run times one full-resolution 12 MP render of the same
scene, the fixed workload the ratios are against, and repeats the focus sweep
at other proxy sizes, each alone (without the ladder of coarser proxies that
takes over when updates are slow).

Usage (from the repository root)::

    python benchmarks/bench_view.py            # about two minutes on 2 cores
    python benchmarks/bench_view.py --quick --out out/bench-view  # smoke test (3 MP, fewer updates)

Writes ``benchmarks/results/view--<machine>.json`` and ``docs/img/view_timing.png``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
import urllib.request
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import numpy as np  # noqa: E402

from benchmarks import common  # noqa: E402

TARGET_MS = 250.0


def _post(url: str, body: dict) -> tuple[float, float, int, int]:
    req = urllib.request.Request(url, data=json.dumps(body).encode(), headers={"Content-Type": "application/json"},
                                 method="POST")
    t = time.perf_counter()
    with urllib.request.urlopen(req, timeout=120) as r:
        data = r.read()
        server_s = float(r.headers["X-Bokehray-Render-Seconds"])
        factor = int(r.headers["X-Bokehray-Factor"])
    return time.perf_counter() - t, server_s, len(data), factor


def drags(w: int, h: int, k0: float, subject: tuple[int, int], n: int) -> dict[str, list[dict]]:
    """Parameter sequences of four drags, as the page would send them."""
    xs = np.linspace(0.1 * w, 0.9 * w, n).astype(int)
    ys = np.linspace(0.3 * h, 0.8 * h, n).astype(int)
    return {
        "focus clicks": [{"blur": k0, "focus_at": [int(x), int(y)]} for x, y in zip(xs, ys)],
        "blur slider": [{"blur": float(k), "focus_at": list(subject)} for k in np.linspace(0.3 * k0, 1.5 * k0, n)],
        "blade rotation": [{"blur": k0, "focus_at": list(subject), "aperture": "polygon", "blades": 6,
                            "rotation": float(r), "curvature": 0.2} for r in np.linspace(0, 60, n)],
        "highlight boost": [{"blur": k0, "focus_at": list(subject), "highlight_boost": float(b)}
                            for b in np.linspace(0, 8, n)],
        # the slider's far end (K up to w / 8) with a 9-blade aperture: the costliest updates
        "strong blur, 9 blades": [{"blur": float(k), "focus_at": list(subject), "aperture": "polygon", "blades": 9,
                                   "rotation": 10.0, "curvature": 0.1} for k in np.linspace(1.5 * k0, w / 8, n)],
    }


def run_drag(url: str, seq: list[dict], warmup: int) -> dict:
    rows = [_post(url + "api/render", {**p, "stage": "preview"}) for p in seq]
    rows = rows[warmup:]
    page = [r[0] * 1e3 for r in rows]
    server = [r[1] * 1e3 for r in rows]
    return {"updates": len(rows), "median_ms": statistics.median(page), "max_ms": max(page),
            "p90_ms": float(np.percentile(page, 90)), "server_median_ms": statistics.median(server),
            "jpeg_kb_median": statistics.median(r[2] for r in rows) / 1024, "page_ms": page,
            "proxy_factors": [r[3] for r in rows]}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--proxy-size", type=int, default=640, help="the session's finest proxy (default 640)")
    ap.add_argument("--quick", action="store_true", help="3 MP, fewer updates, no proxy sweep")
    ap.add_argument("--check", action="store_true", help="exit 1 when the median update misses the target")
    ap.add_argument("--out", default=str(common.REPO / "benchmarks" / "results"), help="folder of the JSON")
    ap.add_argument("--plot", default=str(common.REPO / "docs" / "img" / "view_timing.png"), help="PNG plot")
    args = ap.parse_args()

    import warp

    warp.config.log_level = warp.LOG_WARNING
    from bokehray.app.demo import build_demo_scene
    from bokehray.app.view.server import ViewServer
    from bokehray.app.view.session import ProxyLadder, ViewSession

    w, h = (2000, 1500) if args.quick else (4000, 3000)
    n, warmup = (6, 2) if args.quick else (14, 2)
    t0 = time.perf_counter()
    scene = build_demo_scene(width=w, height=h)
    k0 = float(scene.k_px)
    ys, xs = np.nonzero(np.abs(scene.disparity - 0.92) < 0.004)
    subject = (int(np.median(xs)), int(np.median(ys)))
    result: dict = {"benchmark": "view", "quick": args.quick, "machine": common.machine_info(),
                    "image": [w, h], "megapixels": round(w * h / 1e6, 2), "k_px": k0, "target_ms": TARGET_MS,
                    "scene_seconds": round(time.perf_counter() - t0, 2)}

    rss0 = common.status_kb("VmRSS")
    t = time.perf_counter()
    session = ViewSession(scene.image, scene.disparity, proxy_long_side=args.proxy_size)
    result["session_open_seconds"] = round(time.perf_counter() - t, 3)
    result["proxy"] = {"factor": session.proxy_factor, "shape": list(session.proxy_image.shape[:2])}
    with ViewServer(session) as server:
        t = time.perf_counter()
        for name in ("photo.jpg", "depth.png", "disparity16.png"):
            urllib.request.urlopen(server.url + "api/" + name, timeout=60).read()
        result["static_images_seconds"] = round(time.perf_counter() - t, 3)
        result["drags"] = {}
        for name, seq in drags(w, h, k0, subject, n).items():
            result["drags"][name] = run_drag(server.url, seq, warmup)
            print(f"{name:22s} factors {sorted(set(result['drags'][name]['proxy_factors']))} median {result['drags'][name]['median_ms']:6.1f} ms  p90 "
                  f"{result['drags'][name]['p90_ms']:6.1f} ms  (server {result['drags'][name]['server_median_ms']:.1f})",
                  flush=True)
        # the fixed workload: one full-resolution render of the same photo (what the page refines to)
        p = {"blur": k0, "focus_at": list(subject)}
        result["full_render_seconds"] = _post(server.url + "api/render", {**p, "stage": "full"})[1]
        result["rss_mb_after"] = round((common.status_kb("VmRSS") or 0) / 1024, 1)
        result["worker"] = dict(server.worker.counts)
    result["rss_mb_scene"] = round((rss0 or 0) / 1024, 1)
    all_ms = [v for d in result["drags"].values() for v in d["page_ms"]]
    result["all_updates"] = {"n": len(all_ms), "median_ms": statistics.median(all_ms),
                             "p90_ms": float(np.percentile(all_ms, 90)), "max_ms": max(all_ms)}
    result["ratio_update_to_full_render"] = result["all_updates"]["median_ms"] / 1e3 / result["full_render_seconds"]

    if not args.quick:  # the proxy size: what 640 buys
        sweep = {}
        for side in (480, 640, 800, 1024):
            s = ViewSession(scene.image, scene.disparity, proxy_long_side=side)
            s.ladder = ProxyLadder(1)  # this proxy only
            with ViewServer(s) as server:
                r = run_drag(server.url, drags(w, h, k0, subject, 8)["focus clicks"], 2)
            sweep[side] = {"factor": s.proxy_factor, "shape": list(s.proxy_image.shape[:2]),
                           "median_ms": r["median_ms"], "p90_ms": r["p90_ms"]}
            print(f"proxy {side:5d}: {s.proxy_image.shape[1]}x{s.proxy_image.shape[0]} median {r['median_ms']:.1f} ms",
                  flush=True)
        result["proxy_sweep"] = sweep
        # a second fixed workload of the same run: focus clicks on the 640 px proxy alone (no ladder)
        result["ratio_update_to_fixed_proxy640"] = result["all_updates"]["median_ms"] / sweep[640]["median_ms"]
    result["load_avg_at_end"] = list(os.getloadavg())
    result["pass"] = result["all_updates"]["median_ms"] <= TARGET_MS
    tag = common.machine_tag(result["machine"]) + ("-quick" if args.quick else "")
    path = common.write_json(Path(args.out) / f"view--{tag}.json", result)
    print(f"all updates: median {result['all_updates']['median_ms']:.1f} ms, p90 {result['all_updates']['p90_ms']:.1f} "
          f"ms (target {TARGET_MS:.0f}); full {w}x{h} render {result['full_render_seconds']:.2f} s; ratio "
          f"{result['ratio_update_to_full_render']:.3f}; wrote {path}")
    if not args.quick:
        _plot(result, Path(args.plot))
    print(("PASS" if result["pass"] else "MISS") + f": median update <= {TARGET_MS:.0f} ms")
    return 1 if args.check and not result["pass"] else 0


def _plot(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 3.6))
    names = list(result["drags"])
    a.boxplot([result["drags"][k]["page_ms"] for k in names], tick_labels=names, showfliers=True)
    a.axhline(result["target_ms"], color="tab:red", ls="--", lw=1, label=f"target {result['target_ms']:.0f} ms")
    a.set_ylabel("ms per update (request to JPEG)")
    used = sorted({f for d in result["drags"].values() for f in d["proxy_factors"]})
    a.set_title(f"live preview, {result['megapixels']} MP photo; proxy factors used {used} "
                f"(finest {result['proxy']['shape'][1]}x{result['proxy']['shape'][0]}); load "
                f"{result['load_avg_at_end'][0]:.1f}", fontsize=8)
    a.tick_params(axis="x", labelsize=6, rotation=15)
    a.legend(fontsize=8)
    sides = sorted(result.get("proxy_sweep", {}), key=int)
    if sides:
        sw = result["proxy_sweep"]
        b.plot([int(s) for s in sides], [sw[s]["median_ms"] for s in sides], "o-", label="median")
        b.plot([int(s) for s in sides], [sw[s]["p90_ms"] for s in sides], "s--", label="p90")
        b.axhline(result["target_ms"], color="tab:red", ls="--", lw=1)
        b.set_xlabel("proxy long side (px)")
        b.set_ylabel("ms per update (focus clicks)")
        b.set_title("proxy size against latency", fontsize=9)
        b.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)


if __name__ == "__main__":
    sys.exit(main())
