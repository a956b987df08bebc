"""Speed and memory benchmark of the preview renderer on the built-in demo scene (CPU).

Sweeps the maximum CoC radius at 1536 x 1024 and the image size at radius 32,
plus one focus-far configuration, timing ``bokehray.render_with_stats`` end to
end (validation included) after one warm-up call, and measuring peak RSS in a
fresh process per configuration.

Usage (from the repository root)::

    python benchmarks/renderer/bench_preview.py            # full run, a few minutes
    python benchmarks/renderer/bench_preview.py --quick    # smoke test for CI (< 30 s)
    python benchmarks/renderer/bench_preview.py --out DIR  # write JSON and plot into DIR
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import numpy as np

import bokehray
from benchmarks import common
from bokehray.app.demo import build_demo_scene

BASE = (1536, 1024)
RADII = (2, 4, 8, 16, 32, 64)
SIZES = ((776, 516), (1500, 1000), (3000, 2000), (4242, 2828))  # 0.4, 1.5, 6, 12 MP at 3:2
SIZE_RADIUS = 32
TARGET_S, TARGET_RATIO = 1.0, 2.5


def _quiet_warp() -> None:
    import warp

    if hasattr(warp, "LOG_WARNING"):  # Warp 1.19 has ``config.log_level`` (no ``config.quiet``)
        warp.config.log_level = warp.LOG_WARNING


def _blur(disparity: np.ndarray, focus: float, radius: float) -> bokehray.BlurParams:
    """Blur parameters focused at ``focus`` whose largest CoC radius is ``radius`` pixels."""
    return bokehray.BlurParams(k_px=radius / max(float(np.abs(disparity - focus).max()), 1e-6), focus_disparity=focus)


def _render(image: np.ndarray, disparity: np.ndarray, blur: bokehray.BlurParams) -> bokehray.RenderStats:
    return bokehray.render_with_stats(image, disparity, blur, aperture=None, quality="preview", device="cpu")[1]


def child(npz: str, k_px: float, focus: float) -> None:
    """Fresh-process memory probe: load the scene, report RSS, render once (cold), report peak RSS."""
    _quiet_warp()
    with np.load(npz) as f:
        image, disparity = f["image"], f["disparity"]
    common.report_rss(peak=False)
    _render(image, disparity, bokehray.BlurParams(k_px=k_px, focus_disparity=focus))
    common.report_rss(peak=True)


def measure(scene, sweep: str, focus_name: str, radius: float, runs: int, npz: str | None) -> dict:
    """Time one configuration (``runs`` warm runs after one warm-up), then probe its memory."""
    h, w = scene.disparity.shape
    focus = scene.focus_near if focus_name == "near" else scene.focus_far
    blur = _blur(scene.disparity, focus, radius)
    row = {"sweep": sweep, "width": w, "height": h, "megapixels": round(w * h / 1e6, 3), "radius": radius,
           "focus": focus_name, "focus_disparity": focus, "k_px": round(blur.k_px, 4)}
    stats = []
    try:
        row["time"] = common.time_warm(lambda: stats.append(_render(scene.image, scene.disparity, blur)), runs=runs)
        st = stats[-1].as_dict()
        row.update({k: st[k] for k in ("layers", "tiles_copied", "tiles_total", "pyramid_levels", "threads")})
        row["stage_seconds"] = st["stage_seconds"]
    except Exception as e:  # noqa: BLE001 - report, do not hide: e.g. MemoryError at large sizes
        row["error"] = f"{type(e).__name__}: {e}"
    if npz is not None:
        row["memory"] = common.peak_rss_mb_of([__file__, "--child", npz, repr(blur.k_px), repr(focus)])
    t = row.get("time")
    print(f"  {sweep:6s} {w}x{h} R={radius:g} focus={focus_name}: "
          + (f"median {t['median']:.3f} s" if t else row["error"])
          + (f", peak {row['memory'].get('peak_mb', 0):.0f} MB" if npz else ""), file=sys.stderr, flush=True)
    return row


def run_all(quick: bool) -> list[dict]:
    """Run the sweeps; returns one row per configuration."""
    plan = ([("radius", (512, 341), "near", r, 2) for r in (4, 16)] if quick else
            [("radius", BASE, "near", r, 5) for r in RADII] + [("focus", BASE, "far", SIZE_RADIUS, 5)]
            + [("size", wh, "near", SIZE_RADIUS, 5 if wh[0] * wh[1] < 4e6 else 3) for wh in SIZES])
    rows, scene = [], None
    with tempfile.TemporaryDirectory(prefix="bokehray-bench-") as tmp:
        for sweep, (w, h), focus, radius, runs in plan:
            npz = None if quick else f"{tmp}/demo-{w}x{h}.npz"
            if scene is None or scene.disparity.shape != (h, w):
                scene = None  # free the previous size first
                scene = build_demo_scene(w, h)
                if npz is not None:
                    np.savez(npz, image=scene.image, disparity=scene.disparity)
            rows.append(measure(scene, sweep, focus, radius, runs, npz))
    return rows


def checks(rows: list[dict]) -> dict:
    """The two targets: median at 1536 x 1024 R=32 <= 1 s, and time(R=64) / time(R=16) <= 2.5."""
    med = {r["radius"]: r["time"]["median"] for r in rows
           if r["sweep"] == "radius" and (r["width"], r["height"]) == BASE and "time" in r}
    out = {}
    if 32 in med:
        out["r32_under_1s"] = {"value": med[32], "limit": TARGET_S, "pass": med[32] <= TARGET_S}
    if 16 in med and 64 in med:
        ratio = med[64] / med[16]
        out["r64_over_r16"] = {"value": ratio, "limit": TARGET_RATIO, "pass": ratio <= TARGET_RATIO}
    return out


def table(rows: list[dict]) -> str:
    """Markdown table of all configurations (``+render MB``: peak RSS minus RSS with the inputs loaded)."""
    lines = ["| sweep | size | MP | R | focus | median s | min s | max s | runs | peak RSS MB | +render MB | layers "
             "| tiles copied |", "|---" * 13 + "|"]
    for r in rows:
        mem = r.get("memory", {})
        if "peak_mb" in mem:
            before = mem.get("before_mb")
            rss = f"{mem['peak_mb']:.0f} | " + (f"{mem['peak_mb'] - before:.0f}" if before is not None else "-")
        else:
            rss = f"FAILED ({mem['error']}) | -" if mem else "- | -"
        head = f"| {r['sweep']} | {r['width']}x{r['height']} | {r['megapixels']:.2f} | {r['radius']:g} | {r['focus']} |"
        if "time" not in r:
            lines.append(f"{head} FAILED: {r['error']} | | | | {rss} | | |")
            continue
        t = r["time"]
        lines.append(f"{head} {t['median']:.3f} | {t['min']:.3f} | {t['max']:.3f} | {len(t['runs'])} | {rss} | "
                     f"{r['layers']} | {r['tiles_copied']}/{r['tiles_total']} |")
    return "\n".join(lines)


def plot(rows: list[dict], machine: dict, path: Path) -> None:
    """Time vs radius (left) and time vs megapixels (right), median with min-max bars."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    panels = ((axes[0], "radius", "radius", "max CoC radius R (px)"), (axes[1], "size", "megapixels", "megapixels"))
    for ax, sweep, key, xlabel in panels:
        ok = [r for r in rows if r["sweep"] == sweep and "time" in r]
        if ok:
            x = [r[key] for r in ok]
            med = np.array([r["time"]["median"] for r in ok])
            err = [med - [r["time"]["min"] for r in ok], [r["time"]["max"] for r in ok] - med]
            size = f"{ok[0]['width']}x{ok[0]['height']}" if sweep == "radius" else f"R={SIZE_RADIUS}"
            ax.errorbar(x, med, yerr=err, marker="o", capsize=3, label=f"focus near, {size}")
            if sweep == "radius":
                ax.set_xscale("log", base=2)
                ax.set_xticks(x, [f"{v:g}" for v in x])
        far = [r for r in rows if r["sweep"] == "focus" and "time" in r]
        for r in far:
            t = r["time"]
            ax.errorbar([r[key]], [t["median"]], yerr=[[t["median"] - t["min"]], [t["max"] - t["median"]]],
                        marker="s", ls="none", capsize=3, color="C3", label=f"focus far, {r['width']}x{r['height']}")
        if sweep == "radius":
            ax.axhline(TARGET_S, color="grey", ls="--", lw=0.8, label=f"target {TARGET_S:g} s at R=32")
        ax.set(xlabel=xlabel, ylabel="seconds (median, min-max)", ylim=(0, None),
               title=f"preview time vs {'radius' if sweep == 'radius' else 'image size'}")
        ax.grid(alpha=0.3)
        if ok or far:
            ax.legend(fontsize=8)
        else:
            ax.text(0.5, 0.5, "not run", ha="center", transform=ax.transAxes)
    fig.suptitle(f"bokehray preview, CPU: {machine['cpu']}, {machine['cores']} cores, {machine['ram_gb']} GB "
                 f"({machine['hostname']}), warp {machine['warp']}, {machine['git_commit']}", fontsize=9)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="smoke test: 512x341, R in {4, 16}, 2 runs, no memory probe")
    ap.add_argument("--out", type=Path, help="folder for the JSON and the plot (default: benchmarks/results, docs/img)")
    ap.add_argument("--child", nargs=3, metavar=("NPZ", "K", "FOCUS"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        child(args.child[0], float(args.child[1]), float(args.child[2]))
        return 0
    _quiet_warp()
    machine = common.machine_info()
    tag = common.machine_tag(machine)
    t0 = time.perf_counter()
    rows = run_all(args.quick)
    result = {"benchmark": "preview", "quick": args.quick, "machine": machine, "rows": rows,
              "checks": checks(rows), "wall_seconds": round(time.perf_counter() - t0, 1),
              "load_avg_at_end": [round(x, 2) for x in os.getloadavg()]}
    print(f"\n## bokehray preview on {machine['cpu']} ({machine['cores']} cores, {tag})\n")
    print(table(rows))
    print()
    names = {"r32_under_1s": f"(a) median at {BASE[0]}x{BASE[1]} R=32 <= {TARGET_S:g} s",
             "r64_over_r16": f"(b) time(R=64) / time(R=16) <= {TARGET_RATIO:g}"}
    for key, name in names.items():
        c = result["checks"].get(key)
        print(f"{name}: " + (f"{'PASS' if c['pass'] else 'FAIL'} ({c['value']:.3f})" if c else "n/a (not measured)"))
    if args.out or not args.quick:
        name = f"preview--{tag}{'-quick' if args.quick else ''}.json"
        js = (args.out or common.REPO / "benchmarks" / "results") / name
        png = (args.out or common.REPO / "docs" / "img") / "preview_timing.png"
        common.write_json(js, result)
        plot(rows, machine, png)
        print(f"\nwrote {js} and {png}")
    print(f"benchmark wall time {result['wall_seconds']:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
