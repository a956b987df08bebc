"""Ray tracer: time and error against rays per pixel on a 512 x 512, 3-layer scene (max CoC 24 px).

The error is measured against a render with 4x the largest sample count
(PSNR in sRGB after clipping, as everywhere in bokehray). Layers are planes
(a tilted photo background, a tilted card with a hole, a foreground of thin
semi-transparent strands), so this measures the sampling alone.

Usage (from the repository root)::

    python benchmarks/bench_raytrace.py [--out benchmarks/results]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import numpy as np  # noqa: E402
from skimage import data  # noqa: E402
from skimage.transform import resize  # noqa: E402

import bokehray as br  # noqa: E402
from benchmarks import common  # noqa: E402

SPP = (8, 16, 32, 64, 128, 256)


def scene(size: int = 512) -> list[br.Layer]:
    """Nearest first: strands (d 0.9), a card with a round hole (d 0.45-0.55), a photo background (d 0-0.1)."""
    yy, xx = np.mgrid[0:size, 0:size] + 0.5
    bg = br.io.srgb_to_linear(resize(data.astronaut(), (size, size), anti_aliasing=True)).astype(np.float32)
    bg = np.concatenate([bg, np.ones((size, size, 1), np.float32)], axis=2)
    bg[200:206, 300:306, :3] = 12.0  # a small bright light
    card = np.zeros((size, size, 4), np.float32)
    inside = (np.abs(xx - 256) < 150) & (np.abs(yy - 300) < 110) & ((xx - 300) ** 2 + (yy - 290) ** 2 > 40**2)
    card[inside] = [0.6, 0.35, 0.2, 1.0]
    strands = np.zeros((size, size, 4), np.float32)
    for k, x0 in enumerate(range(40, size, 37)):
        dist = np.abs(xx - (x0 + 0.15 * (yy - 256) + 6 * np.sin(yy / 40 + k)))
        strands[..., 3] = np.maximum(strands[..., 3], np.clip(1.2 - dist, 0, 1))
    strands[..., :3] = [0.9, 0.85, 0.6]
    return [br.Layer(strands, plane=(0.0, 0.0, 0.9)),
            br.Layer(card, plane=(0.1 / size, 0.0, 0.45)),
            br.Layer(bg, plane=(0.0, 0.1 / size, 0.0))]


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    f = lambda x: br.io.linear_to_srgb(np.clip(x, 0, 1))  # noqa: E731
    return float(10 * np.log10(1.0 / np.mean((f(a) - f(b)) ** 2)))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, help="folder for raytrace--spp.json")
    ap.add_argument("--plot", type=Path, help="PNG of error and time against rays per pixel")
    args = ap.parse_args()
    layers = scene()
    blur = br.BlurParams(k_px=24.0 / 0.9, focus_disparity=0.0)  # background sharp; strands r = 24 px
    fixed = lambda n: br.RaytraceOptions(samples_per_px2=1e6, max_spp=n, min_spp=n)  # noqa: E731
    br.raytrace_layers(layers, blur, options=fixed(4))  # warm-up (kernel load)
    truth, _ = br.raytrace_layers(layers, blur, options=fixed(4 * SPP[-1]), )
    rows = []
    for n in SPP:
        timing = common.time_warm(lambda n=n: br.raytrace_layers(layers, blur, options=fixed(n)), runs=3, warmup=0)
        out, _ = br.raytrace_layers(layers, blur, options=fixed(n))
        rows.append({"spp": n, "psnr_db": round(psnr(out[..., :3], truth[..., :3]), 2), **timing})
    adaptive = br.RaytraceOptions()
    out, st = br.raytrace_layers(layers, blur, options=adaptive)
    t = common.time_warm(lambda: br.raytrace_layers(layers, blur, options=adaptive), runs=3, warmup=0)
    rows.append({"spp": f"adaptive (mean {st.spp_mean:.0f}, max {st.spp_max})",
                 "psnr_db": round(psnr(out[..., :3], truth[..., :3]), 2), **t})
    print("| rays per pixel | PSNR vs 1024 rays (dB) | median s | min s | max s |")
    print("|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['spp']} | {r['psnr_db']:.2f} | {r['median']:.3f} | {r['min']:.3f} | {r['max']:.3f} |")
    if args.out:
        common.write_json(args.out / "raytrace--spp.json", {"machine": common.machine_info(), "rows": rows})
    if args.plot:
        plot(rows[:-1], args.plot)
    return 0


def plot(rows: list[dict], path: Path) -> None:
    """Error and time against rays per pixel (log2 axis)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    spp = [r["spp"] for r in rows]
    fig, ax = plt.subplots(figsize=(6, 3.6))
    ax.semilogx(spp, [r["psnr_db"] for r in rows], "o-", base=2, color="C0")
    ax.set_xlabel("rays per pixel")
    ax.set_ylabel("PSNR vs 1024 rays (dB)", color="C0")
    ax.grid(alpha=0.3)
    ax2 = ax.twinx()
    ax2.semilogx(spp, [r["median"] for r in rows], "s--", base=2, color="C1")
    ax2.set_ylabel("time, 512 x 512 (s)", color="C1")
    ax.set_title("layered ray tracer: 3 layers, max CoC 24 px, 2-core CPU")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)


if __name__ == "__main__":
    sys.exit(main())
