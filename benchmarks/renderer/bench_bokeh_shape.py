"""Shape exactness and cost of the preview's bokeh: point lights, an HDR plane, time vs radius.

Three measurements, all through ``bokehray.levels.preview.render_signed_coc`` (the default preview,
and its ``exact_highlights=False`` fast mode where named):

1. **Point light.** One light pixel behind (or in front of) the focus on a black frame of
   the same depth, radius R. Its rendered spread is compared with the analytic aperture
   integrated over every pixel (``tests/reference/scatter_ref.area_coverage``):
   relative L1 error, plateau flatness (peak / mean over the pixels fully inside the shape)
   and energy. Disc and 6-blade polygon, R = 16 ... 256.
2. **HDR plane.** A 1024 x 768 fronto-parallel plane (dark texture with HDR lights) at R = 96
   against the exact convolution (FFT) of the edge-replicated frame with the pixel-integrated
   disc, which is what the clamped border rule means. PSNR on linear radiance with the
   reference's peak; also after tone mapping c / (1 + c).
3. **Time vs R.** The demo scene at 1536 x 1024 focused near, largest CoC R; median of warm
   runs, with a fixed workload timed in the same run (a scipy FFT convolution of one channel
   with a 65 x 65 disc) to read ratios on a noisy machine.

Usage (repository root)::

    python benchmarks/renderer/bench_bokeh_shape.py            # full run (a few minutes)
    python benchmarks/renderer/bench_bokeh_shape.py --quick    # smoke test (< 1 min)
    python benchmarks/renderer/bench_bokeh_shape.py --device cuda
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tests"))

import numpy as np  # noqa: E402
import scipy.signal  # noqa: E402
from reference import scatter_ref  # noqa: E402

import bokehray  # noqa: E402
from benchmarks import common  # noqa: E402
from bokehray.app.demo import build_demo_scene  # noqa: E402
from bokehray.levels.preview import render_signed_coc  # noqa: E402
from bokehray.options import PreviewOptions  # noqa: E402

APERTURES = {"disc": bokehray.Aperture(), "6 blades": bokehray.Aperture(blades=6, rotation_deg=15.0)}
RADII = (16, 64, 128, 256)
TIME_RADII = (16, 32, 64, 128, 256)
L1_TARGET, PLATEAU_TARGET, ENERGY_TARGET, HDR_TARGET_DB, RATIO_TARGET = 0.04, 1.05, 1e-3, 45.0, 2.5


def _quiet_warp() -> None:
    import warp

    if hasattr(warp, "LOG_WARNING"):
        warp.config.log_level = warp.LOG_WARNING


def point_light(ap: bokehray.Aperture, radius: float, sign: float, options: PreviewOptions, device: str) -> dict:
    """One light of energy 1 at the centre of a black frame of one depth (signed CoC ``sign * radius``)."""
    size = int(2 * radius) + 41
    c = size // 2
    image = np.zeros((size, size, 3), np.float32)
    image[c, c] = 1.0
    s = np.full((size, size), sign * radius, np.float32)
    out, _ = render_signed_coc(image, s, ap, options=options, device=device)
    got = out[..., 0].astype(np.float64)
    want = scatter_ref.area_coverage(c + 0.5, c + 0.5, sign * radius, ap.blade_discs(), size, size)
    full = want >= want.max() * (1 - 1e-9)  # pixels wholly inside the shape
    plateau = got[full]
    return {"aperture": str(ap), "radius": radius, "side": "front" if sign > 0 else "back",
            "l1": float(np.abs(got - want).sum() / want.sum()), "plateau_peak_over_mean": float(plateau.max() / plateau.mean()),
            "energy_error": float(abs(got.sum() - 1.0))}


def hdr_plane(radius: float, options: PreviewOptions, device: str, size=(1024, 768), seed: int = 7) -> dict:
    """PSNR of a single fronto-parallel HDR plane against the exact convolution of the clamped frame."""
    w, h = size
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w]
    base = 0.03 + 0.02 * np.sin(xx / 23.0) * np.cos(yy / 17.0) + 0.015 * rng.random((h, w))
    image = np.repeat(base[..., None], 3, axis=2) * np.array([1.0, 0.9, 0.8])
    for _ in range(120):  # HDR lights: single pixels and small blobs whose balls reach 0.3 - 30 x the background
        y, x = int(rng.integers(0, h)), int(rng.integers(0, w))
        k = int(rng.integers(1, 4))
        energy = math.exp(rng.uniform(math.log(300.0), math.log(30000.0)))
        image[y:y + k, x:x + k] += energy / (k * k) * rng.uniform(0.5, 1.0, 3)
    image = image.astype(np.float32)
    s = np.full((h, w), -radius, np.float32)
    t = time.perf_counter()
    out, _ = render_signed_coc(image, s, bokehray.Aperture(), options=options, device=device)
    seconds = time.perf_counter() - t
    pad = int(math.ceil(radius)) + 2
    kernel = scatter_ref.area_coverage(pad + 0.5, pad + 0.5, -radius, np.zeros((0, 4)), 2 * pad + 1, 2 * pad + 1)
    big = np.pad(image.astype(np.float64), ((pad, pad), (pad, pad), (0, 0)), mode="edge")
    want = np.stack([scipy.signal.fftconvolve(big[..., i], kernel, mode="same") for i in range(3)], -1)
    want = want[pad:-pad, pad:-pad]
    mse = float(np.mean((out - want) ** 2))
    c = int(math.ceil(radius))
    mse_in = float(np.mean((out[c:-c, c:-c] - want[c:-c, c:-c]) ** 2))  # farther than R from the border
    tm = lambda a: a / (1 + a)  # noqa: E731
    mse_tm = float(np.mean((tm(np.maximum(out, 0)) - tm(want)) ** 2))
    peak = float(want.max())
    return {"size": [w, h], "radius": radius, "psnr_linear_db": 10 * math.log10(peak ** 2 / mse),
            "psnr_linear_interior_db": 10 * math.log10(peak ** 2 / mse_in),
            "psnr_tonemapped_db": 10 * math.log10(1.0 / mse_tm), "seconds": seconds, "peak": peak}


def _median_time(fn, runs: int) -> dict:
    fn()
    ts = []
    for _ in range(runs):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return {"median": statistics.median(ts), "min": min(ts), "max": max(ts), "runs": ts}


def time_vs_radius(radii, runs: int, device: str, size=(1536, 1024), modes=("exact", "fast")) -> list[dict]:
    scene = build_demo_scene(*size)
    yy, xx = np.mgrid[-32:33, -32:33]
    disc = ((xx ** 2 + yy ** 2) <= 32 ** 2).astype(np.float32)
    disc /= disc.sum()
    chan = np.ascontiguousarray(scene.image[..., 0])
    rows = []
    for r in radii:
        f = scene.focus_near
        blur = bokehray.BlurParams(k_px=r / float(np.abs(scene.disparity - f).max()), focus_disparity=f)
        row = {"radius": r, "size": list(size)}
        ref = _median_time(lambda: scipy.signal.fftconvolve(chan, disc, mode="same"), runs)
        row["fft_reference"] = ref
        for mode in modes:
            opts = PreviewOptions(exact_highlights=(mode == "exact"))
            st = {}

            def go(st=st, blur=blur, opts=opts):
                st["s"] = bokehray.render_with_stats(scene.image, scene.disparity, blur, aperture=None,
                                                     quality="preview", device=device, options=opts)[1]
            row[mode] = _median_time(go, runs)
            row[mode]["over_fft"] = row[mode]["median"] / ref["median"]
            row[mode]["layers"] = st["s"].layers
        rows.append(row)
        print(f"  R={r}: " + ", ".join(f"{m} {row[m]['median']:.3f} s ({row[m]['over_fft']:.1f}x fft)" for m in modes)
              + f", fft {ref['median'] * 1e3:.1f} ms", file=sys.stderr, flush=True)
    return rows


def devset_variants() -> dict:
    return {"preview (default)": PreviewOptions(),
            "preview, fast (no exact highlights)": PreviewOptions(exact_highlights=False),
            "preview, renormalised border (the rule before)": PreviewOptions(clamp_border=False)}


def devset(data: Path, crops=(0, 24)) -> dict:
    """Dev-set scores (its own score.py) of the preview variants, whole frame and with borders cropped."""
    import subprocess
    import tempfile

    from benchmarks.renderer import bench_devset

    out = {}
    for name, opts in devset_variants().items():
        with tempfile.TemporaryDirectory() as tmp:
            bench_devset.render_set(data, Path(tmp), opts)
            for crop in crops:
                text = subprocess.run([sys.executable, str(data / "score.py"), tmp, "--crop", str(crop)],
                                      capture_output=True, text=True, check=True).stdout
                line = next(ln for ln in text.splitlines() if ln.strip().startswith("mean over"))
                psnr, ssim, band_psnr, band_ssim = map(float, line.split()[-4:])
                out[f"{name}, crop {crop}"] = {"psnr": psnr, "ssim": ssim, "band_psnr": band_psnr,
                                               "band_ssim": band_ssim, "table": text}
                print(f"  {name}, {crop} px border ignored: {psnr:.2f} dB (band {band_psnr:.2f})", flush=True)
    return out


def plot(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    ax = axes[0]
    for key, rows in result["point_light"].items():
        for side in ("back", "front"):
            pts = [r for r in rows if r["side"] == side]
            ax.plot([r["radius"] for r in pts], [100 * r["l1"] for r in pts], marker="o",
                    ls="-" if side == "back" else "--", label=f"{key}, {side}")
    ax.axhline(100 * L1_TARGET, color="grey", ls=":", lw=0.8, label="target 4 %")
    ax.set(yscale="log", xlabel="radius R (px)", ylabel="relative L1 of the spread (%)",
           title="point light vs the exact pixel-integrated aperture")
    ax.set_xscale("log", base=2)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    ax = axes[1]
    rows = result["time_vs_radius"]
    for mode in ("exact", "fast"):
        if rows and mode in rows[0]:
            ax.plot([r["radius"] for r in rows], [r[mode]["over_fft"] for r in rows], marker="o",
                    label=f"preview ({'default' if mode == 'exact' else 'fast'})")
    ax.set(xlabel="largest CoC radius R (px)", ylabel="median time / one FFT convolution (same run)", ylim=(0, None),
           title=f"demo scene {rows[0]['size'][0]}x{rows[0]['size'][1]}, {result['device']}" if rows else "")
    ax.set_xscale("log", base=2)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    m = result["machine"]
    fig.suptitle(f"bokehray preview bokeh shape: {m['cpu']}, {m['cores']} cores, {m['git_commit']}", fontsize=9)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def ball_figure(path: Path, device: str = "cpu") -> None:
    """Two lights (one 70 px from the left border) on a dark plane, 7 curved blades, R = 60:
    the pyramid alone (fast mode, left) and the default (right), tone-mapped c / (1 + c)."""
    import imageio.v3 as iio

    n = 200
    img = np.full((n, n, 3), 0.02, np.float32)
    img[100, 100], img[100, 30] = 3000.0, 800.0
    s = np.full((n, n), -60.0, np.float32)
    ap = bokehray.Aperture(blades=7, rotation_deg=10.0, curvature=0.2)
    row = []
    for o in (PreviewOptions(exact_highlights=False), PreviewOptions()):
        out, _ = render_signed_coc(img, s, ap, options=o, device=device)
        row.append(np.clip(out / (1 + out), 0, 1) ** (1 / 2.2))
    path.parent.mkdir(parents=True, exist_ok=True)
    iio.imwrite(path, (np.concatenate(row, 1) * 255).astype(np.uint8))


def demo_lights(path: Path | None, device: str = "cpu", radius: float = 64.0) -> dict:
    """The demo at 1536 x 1024 focused near, R = 64, against the same render with every source exact (the pyramid
    off): sRGB code errors of the pyramid alone and of the default, and a crop of the fairy lights (pyramid
    alone, default, exact) written to ``path``."""
    import imageio.v3 as iio

    from bokehray.colour import linear_to_srgb

    scene = build_demo_scene(1536, 1024)
    f = scene.focus_near
    blur = bokehray.BlurParams(k_px=radius / float(np.abs(scene.disparity - f).max()), focus_disparity=f)
    renders = {name: bokehray.render(scene.image, scene.disparity, blur, quality="preview", device=device, options=o)
               for name, o in (("pyramid alone", PreviewOptions(exact_highlights=False)), ("default", PreviewOptions()),
                               ("exact", PreviewOptions(level_radius_px=1000.0)))}
    codes = {k: np.round(linear_to_srgb(np.clip(v, 0, 1)) * 255).astype(int) for k, v in renders.items()}
    out = {}
    for name in ("pyramid alone", "default"):
        err = np.abs(codes[name] - codes["exact"]).max(-1)
        out[name] = {"max": int(err.max()), "p99.9": float(np.percentile(err, 99.9)), "mean": float(err.mean())}
        print(f"demo R={radius:g} {name} vs exact: sRGB error max {err.max()}, p99.9 {out[name]['p99.9']:.0f}, "
              f"mean {err.mean():.2f}", flush=True)
    if path is not None:
        y0, x0 = 44, 1226
        crop = np.concatenate([codes[k][y0:y0 + 200, x0:x0 + 300] for k in ("pyramid alone", "default", "exact")], 1)
        iio.imwrite(path, crop.astype(np.uint8))
    return out


def replot(js: Path, png: Path) -> None:
    """Redraw the figure from a JSON this script wrote."""
    import json

    plot(json.loads(js.read_text()), png)


def main(argv: list[str] | None = None) -> int:  # noqa: C901
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="smoke test: R <= 64, small HDR plane, one timing")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--runs", type=int, default=5, help="warm runs per timing (median)")
    ap.add_argument("--out", type=Path, help="folder for the JSON and the plot (default: benchmarks/results, docs/img)")
    ap.add_argument("--devset", type=Path, nargs="?", const=REPO.parent / "shared" / "data" / "pathtraced-dev",
                    help="also score the path-traced dev set (default location ../shared/data/pathtraced-dev)")
    ap.add_argument("--only-devset", action="store_true", help="score the dev set only")
    args = ap.parse_args(argv)
    _quiet_warp()
    t0 = time.perf_counter()
    radii = (16, 64) if args.quick else RADII
    result = {"benchmark": "bokeh_shape", "quick": args.quick, "device": args.device,
              "machine": common.machine_info(), "point_light": {}, "hdr_plane": {}}
    if args.devset or args.only_devset:
        data = args.devset or REPO.parent / "shared" / "data" / "pathtraced-dev"
        print("dev set (PSNR, mean over 18 renders):")
        result["devset"] = devset(data)
        if args.only_devset:
            js = (args.out or REPO / "benchmarks" / "results") / "bokeh_shape--devset.json"
            common.write_json(js, result)
            print(f"wrote {js}")
            return 0
    print("point light (relative L1 / plateau peak over mean / energy error):")
    for mode, opts in (("default", PreviewOptions()), ("fast", PreviewOptions(exact_highlights=False))):
        for name, aper in APERTURES.items():
            rows = [point_light(aper, r, sg, opts, args.device) for r in radii for sg in (-1.0, 1.0)]
            result["point_light"][f"{name} ({mode})" if mode != "default" else name] = rows
            for row in rows:
                print(f"  {mode:10s} {name:8s} R={row['radius']:3g} {row['side']:5s}: L1 {100 * row['l1']:5.2f} % "
                      f"plateau {row['plateau_peak_over_mean']:.3f} energy {row['energy_error']:.1e}", flush=True)
    size = (512, 384) if args.quick else (1024, 768)
    for mode, opts in (("default", PreviewOptions()), ("fast", PreviewOptions(exact_highlights=False))):
        result["hdr_plane"][mode] = hdr_plane(96.0, opts, args.device, size=size)
        r = result["hdr_plane"][mode]
        print(f"HDR plane {size[0]}x{size[1]} R=96 {mode}: {r['psnr_linear_db']:.1f} dB linear "
              f"({r['psnr_linear_interior_db']:.1f} dB farther than R from the border), "
              f"{r['psnr_tonemapped_db']:.1f} dB tone-mapped ({r['seconds']:.2f} s)", flush=True)
    print("time vs R (demo scene, focus near):")
    result["time_vs_radius"] = time_vs_radius((16, 32) if args.quick else TIME_RADII, 2 if args.quick else args.runs,
                                              args.device, size=(768, 512) if args.quick else (1536, 1024))
    med = {r["radius"]: r["exact"]["median"] for r in result["time_vs_radius"]}
    pl = [row for k, rows in result["point_light"].items() if "(" not in k for row in rows]
    result["checks"] = {
        "point_light_l1": {"value": max(r["l1"] for r in pl), "limit": L1_TARGET},
        "plateau": {"value": max(r["plateau_peak_over_mean"] for r in pl), "limit": PLATEAU_TARGET},
        "energy": {"value": max(r["energy_error"] for r in pl), "limit": ENERGY_TARGET},
        "hdr_plane_db": {"value": result["hdr_plane"]["default"]["psnr_linear_db"], "limit": HDR_TARGET_DB},
    }
    if 128 in med and 16 in med:
        result["checks"]["t128_over_t16"] = {"value": med[128] / med[16], "limit": RATIO_TARGET}
    for k, c in result["checks"].items():
        ok = c["value"] >= c["limit"] if k == "hdr_plane_db" else c["value"] <= c["limit"]
        c["pass"] = bool(ok)
        print(f"{k}: {c['value']:.4g} (limit {c['limit']:g}) {'PASS' if ok else 'FAIL'}")
    result["wall_seconds"] = round(time.perf_counter() - t0, 1)
    result["load_avg_at_end"] = [round(x, 2) for x in os.getloadavg()]
    if args.out or not args.quick:
        suffix = "" if args.device == "cpu" else f"--{args.device}"
        js = (args.out or REPO / "benchmarks" / "results") / f"bokeh_shape{suffix}{'-quick' if args.quick else ''}.json"
        png = (args.out or REPO / "docs" / "img") / f"bokeh_shape{suffix}.png"
        common.write_json(js, result)
        plot(result, png)
        ball_figure(png.with_name(f"bokeh_ball{suffix}.png"), args.device)
        print(f"wrote {js}, {png} and {png.with_name(f'bokeh_ball{suffix}.png')}")
    if not args.quick:
        fig = (args.out or REPO / "docs" / "img") / f"fairy_lights{suffix}.png"
        result["demo_lights_r64"] = demo_lights(fig, args.device)
        common.write_json(js, result)
        print(f"wrote {fig}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
