"""Latency of ``bokehray view`` on a 12 MP photo as the page sees it (CPU), quiet and beside two busy processes.

**Page protocol** (the default): a 12 MP JPEG (the demo scene at 4000 x 3000, display-referred, so highlight
reconstruction is on as ``render`` would do) and its 16-bit disparity PNG are written once. For each of
``--reps`` repetitions, and each load (``quiet``: nothing added; ``busy``: two processes spinning on the CPU
beside the server, started before it), a fresh ``bokehray view`` process is started; once it prints its URL the
page is loaded as the browser does (``/``, ``app.js``, ``/api/info``, then the first preview at the page's
defaults, then the photo, depth and disparity images) and the **time to first picture** is the
time from the first request of the page to the first preview received. Then ``--changes`` changes are made one
after the other as the page makes them (focus clicks across the frame and blur-amount changes, alternating):
the **change to proxy** is the time from the change to the preview received, the **change to sharp** the time
from the change to the sharp version received (asked for, as the page does, only once the preview is in;
rendered at ``--screen`` px on the long side, a 1280-px canvas by default). Medians and p90 over every
repetition. Fixed workload of the same run: one full-resolution (12 MP) preview-level render in this process,
the time the page's "full" stage took before it followed the screen's size; ratios are against it.

``--drags`` also replays the older drag protocol (five drags of the live preview through one server).

Usage (from the repository root)::

    python benchmarks/page/bench_view.py                     # about five minutes on 2 cores
    python benchmarks/page/bench_view.py --quick --out out/bench-view  # smoke test (3 MP, 2 repetitions)

Writes ``benchmarks/results/view--<machine>.json`` (``view-page--<machine>.json`` for the page protocol).
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

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import numpy as np

from benchmarks import common

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


CLI = "import sys; from bokehray.app.cli import main; sys.exit(main())"
BUSY = "while True: pass"


def _get(url: str) -> bytes:
    with urllib.request.urlopen(url, timeout=600) as r:
        return r.read()


def _post_page(url: str, body: dict) -> tuple[float, int]:
    req = urllib.request.Request(url + "api/render", data=json.dumps(body).encode(),
                                 headers={"Content-Type": "application/json"}, method="POST")
    t = time.perf_counter()
    with urllib.request.urlopen(req, timeout=600) as r:
        r.read()
        factor = int(r.headers["X-Bokehray-Factor"])
    return time.perf_counter() - t, factor


def page_session(image: Path, disp: Path, changes: int, screen: int) -> dict:
    """One ``bokehray view`` process: the page's first picture, then ``changes`` changes (proxy, then sharp)."""
    import subprocess
    from concurrent.futures import ThreadPoolExecutor

    t_start = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-c", CLI, "view", str(image), "--disparity", str(disp), "--quiet",
                             "--export-dir", str(image.parent)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        line = proc.stdout.readline()
        if not line.startswith("bokehray view: http"):
            raise RuntimeError(line + proc.stderr.read())
        url = line.split()[2]
        startup_s = time.perf_counter() - t_start
        t0 = time.perf_counter()
        _get(url)
        _get(url + "static/app.js")
        info = json.loads(_get(url + "api/info"))
        _, factor = _post_page(url, {"stage": "preview"})  # the page's defaults: render's
        first_s = time.perf_counter() - t0
        with ThreadPoolExecutor(3) as pool:  # then the page loads its three images, as it does once it shows one
            for f in [pool.submit(_get, url + "api/" + n) for n in ("photo.jpg", "depth.png", "disparity16.png")]:
                f.result()
        w, h = info["width"], info["height"]
        rows = []
        for i in range(changes):
            if i % 2 == 0:
                x, y = int(w * (0.15 + 0.7 * i / max(1, changes))), int(h * (0.35 + 0.4 * ((i * 7) % 5) / 5))
                p = {"focus_at": [x, y], "amount": 50}
            else:
                p = {"amount": float(20 + (i * 37) % 80)}
            t = time.perf_counter()
            _, pf = _post_page(url, {**p, "stage": "preview"})
            proxy_s = time.perf_counter() - t
            _, sf = _post_page(url, {**p, "stage": "full", "long_side": screen})
            rows.append({"proxy_s": proxy_s, "sharp_s": time.perf_counter() - t, "proxy_factor": pf,
                         "sharp_factor": sf})
        return {"startup_s": startup_s, "first_picture_s": first_s, "first_factor": factor, "changes": rows}
    finally:
        proc.terminate()
        proc.wait(60)


def _stats(values: list[float]) -> dict:
    return {"n": len(values), "median_s": round(statistics.median(values), 3),
            "p90_s": round(float(np.percentile(values, 90)), 3), "max_s": round(max(values), 3)}


def write_photo(folder: Path, w: int, h: int) -> tuple[Path, Path]:
    """The demo scene at ``w`` x ``h`` as a display-referred JPEG and its 16-bit disparity PNG in ``folder``."""
    from PIL import Image

    import bokehray as br
    from bokehray.app.demo import build_demo_scene
    from bokehray.colour import linear_to_srgb

    scene = build_demo_scene(width=w, height=h)
    srgb = (np.clip(linear_to_srgb(np.clip(scene.image, 0, 1)), 0, 1) * 255 + 0.5).astype(np.uint8)
    Image.fromarray(srgb).save(folder / "photo.jpg", quality=92)
    br.write_disparity(folder / "disparity.png", scene.disparity)
    return folder / "photo.jpg", folder / "disparity.png"


def page_protocol(args) -> int:
    import subprocess
    import tempfile


    w, h = (2000, 1500) if args.quick else (4000, 3000)
    reps = 2 if args.quick else args.reps
    changes = 4 if args.quick else args.changes
    tmp = Path(tempfile.mkdtemp(prefix="bench-view-"))
    write_photo(tmp, w, h)
    result: dict = {"benchmark": "view-page", "quick": args.quick, "machine": common.machine_info(),
                    "image": [w, h], "megapixels": round(w * h / 1e6, 2), "screen_long_side": args.screen,
                    "reps": reps, "changes_per_rep": changes, "load_avg_at_start": list(os.getloadavg())}
    # the fixed workload: the full-resolution render the page's sharp stage used to be, in this process
    from bokehray.app.view.session import ViewSession

    s = ViewSession.from_files(str(tmp / "photo.jpg"), disparity=str(tmp / "disparity.png"), export_dir=tmp)
    s.warm_up()
    t = time.perf_counter()
    s.render_full(dataclasses_replace_quality(s.parse({})))
    result["fixed_full_resolution_render_s"] = round(time.perf_counter() - t, 2)
    print(f"fixed workload: {w}x{h} preview-level render {result['fixed_full_resolution_render_s']:.2f} s", flush=True)
    del s
    for load in ("quiet", "busy"):
        busy = [subprocess.Popen([sys.executable, "-c", BUSY]) for _ in range(2 if load == "busy" else 0)]
        try:
            runs = []
            for r in range(reps):
                runs.append(page_session(tmp / "photo.jpg", tmp / "disparity.png", changes, args.screen))
                print(f"{load} rep {r}: first picture {runs[-1]['first_picture_s']:.2f} s (startup "
                      f"{runs[-1]['startup_s']:.1f} s), proxy {[round(c['proxy_s'], 2) for c in runs[-1]['changes']]}"
                      f", sharp {[round(c['sharp_s'], 2) for c in runs[-1]['changes']]}", flush=True)
        finally:
            for b in busy:
                b.kill()
                b.wait()
        first = [x["first_picture_s"] for x in runs]
        proxy = [c["proxy_s"] for x in runs for c in x["changes"]]
        sharp = [c["sharp_s"] for x in runs for c in x["changes"]]
        result[load] = {"first_picture": _stats(first), "change_to_proxy": _stats(proxy),
                        "change_to_sharp": _stats(sharp), "startup": _stats([x["startup_s"] for x in runs]),
                        "proxy_factors": sorted({c["proxy_factor"] for x in runs for c in x["changes"]}),
                        "sharp_factors": sorted({c["sharp_factor"] for x in runs for c in x["changes"]}),
                        "load_avg_after": list(os.getloadavg()), "runs": runs}
        full = result["fixed_full_resolution_render_s"]
        result[load]["ratio_sharp_median_to_fixed_full"] = round(result[load]["change_to_sharp"]["median_s"] / full, 4)
        print(f"{load}: first picture median {result[load]['first_picture']['median_s']} s p90 "
              f"{result[load]['first_picture']['p90_s']} s; change->proxy median "
              f"{result[load]['change_to_proxy']['median_s']} s p90 {result[load]['change_to_proxy']['p90_s']} s; "
              f"change->sharp median {result[load]['change_to_sharp']['median_s']} s p90 "
              f"{result[load]['change_to_sharp']['p90_s']} s (fixed full render {full} s)", flush=True)
    tag = common.machine_tag(result["machine"]) + ("-quick" if args.quick else "")
    path = common.write_json(Path(args.out) / f"view-page--{tag}.json", result)
    print(f"wrote {path}")
    import shutil

    shutil.rmtree(tmp, ignore_errors=True)
    return 0


def dataclasses_replace_quality(p):
    import dataclasses

    return dataclasses.replace(p, quality="preview")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--proxy-size", type=int, default=640, help="the session's finest proxy (default 640)")
    ap.add_argument("--quick", action="store_true", help="3 MP, fewer updates, no proxy sweep")
    ap.add_argument("--check", action="store_true", help="exit 1 when the median update misses the target")
    ap.add_argument("--out", default=str(common.REPO / "benchmarks" / "results"), help="folder of the JSON")
    ap.add_argument("--plot", default=str(common.REPO / "docs" / "img" / "view_timing.png"), help="PNG plot")
    ap.add_argument("--reps", type=int, default=4, help="view processes per load (page protocol; default 4)")
    ap.add_argument("--changes", type=int, default=8, help="changes per process (page protocol; default 8)")
    ap.add_argument("--screen", type=int, default=1280, help="the canvas's long side in pixels (default 1280)")
    ap.add_argument("--drags", action="store_true", help="the older drag protocol instead of the page protocol")
    args = ap.parse_args()
    if not args.drags:
        return page_protocol(args)

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
