"""Ray tracer: accuracy and time of the aperture quadrature against exact references.

Four studies (``--only`` picks some):

- ``stack``: a 512 x 512 scene of three plane layers (thin semi-transparent
  strands at r = 24 px and a card with a hole at r = 12 px, both blurred, over a
  sharp photo background with a light of radiance 12). Error (PSNR in sRGB after
  clipping) against a render with 16x the cells, against time, for ray caps 1..256;
  on the same plot the preview and photo-mode raytrace of the scene's pinhole
  image and front-most disparity (what a photo would give them).
- ``plane``: one fronto-parallel layer of a random texture at r = 10 px against the
  exact disc convolution (float64, texels as boxes).
- ``light``: a one-pixel light at R = 16..256 px, disc and polygons: L1 of the
  normalised spread against the exact aperture (area-integrated), energy, time.
- ``synth``: the targets of the default ``bokehray synth`` (K = 30, both focus
  choices) against 16x the cells.

Usage (from the repository root)::

    python benchmarks/renderer/bench_raytrace.py [--out benchmarks/results] [--plot docs/img/raytrace_convergence.png]
    python benchmarks/renderer/bench_raytrace.py --device cuda --quick
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tests"))

import numpy as np
from skimage import data
from skimage.transform import resize

import bokehray as br
from benchmarks import common

CAPS = (1, 8, 16, 32, 64, 128, 256)
APERTURES = {"disc": br.Aperture(), "hexagon": br.Aperture(blades=6, rotation_deg=10.0),
             "pentagon, curved 0.3": br.Aperture(blades=5, curvature=0.3)}


def scene(size: int = 512) -> list[br.Layer]:
    """Nearest first: strands (d 0.9), a card with a round hole (d 0.45-0.55), a photo background (d 0-0.1)."""
    yy, xx = np.mgrid[0:size, 0:size] + 0.5
    bg = br.colour.srgb_to_linear(resize(data.astronaut(), (size, size), anti_aliasing=True)).astype(np.float32)
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
    f = lambda x: br.colour.linear_to_srgb(np.clip(x, 0, 1))  # noqa: E731
    mse = float(np.mean((f(a) - f(b)) ** 2))
    return float("inf") if mse == 0 else float(10 * np.log10(1.0 / mse))


def sixteen_x(opts: br.RaytraceOptions) -> br.RaytraceOptions:
    """16x the cells: 4x the strips (16x samples per px^2 and cap)."""
    return br.RaytraceOptions(samples_per_px2=16 * opts.samples_per_px2, max_spp=16 * opts.max_spp)


def pinhole_layers(layers: list[br.Layer]) -> tuple[np.ndarray, np.ndarray]:
    from bokehray.data.synth import pinhole_layers as pin

    return pin(layers)


def study_stack(device: str, runs: int, size: int) -> dict:
    layers = scene(size)
    blur = br.BlurParams(k_px=24.0 / 0.9, focus_disparity=0.0)  # background sharp; strands r = 24 px
    ref_opts = br.RaytraceOptions(samples_per_px2=8.0, max_spp=2048)
    br.raytrace_layers(layers, blur, options=br.RaytraceOptions(max_spp=1), device=device)  # warm-up (kernel load)
    t = time.perf_counter()
    truth, st = br.raytrace_layers(layers, blur, options=ref_opts, device=device)
    ref = {"rays_mean": st.spp_mean, "seconds": time.perf_counter() - t}
    rows = []
    for cap in CAPS:
        opts = br.RaytraceOptions(max_spp=cap)
        timing = common.time_warm(lambda o=opts: br.raytrace_layers(layers, blur, options=o, device=device),
                                  runs=runs, warmup=0)
        out, st = br.raytrace_layers(layers, blur, options=opts, device=device)
        rows.append({"max_spp": cap, "rays_mean": round(st.spp_mean, 1),
                     "psnr_db": round(psnr(out[..., :3], truth[..., :3]), 2), **timing})
    image, disparity = pinhole_layers(layers)
    photo = {}
    for name, kw in (("preview", {}), ("raytrace (photo mode)", {"quality": "raytrace"})):
        timing = common.time_warm(lambda kw=kw: br.render(image, disparity, blur, device=device, **kw), runs=runs,
                                  warmup=1)
        out = br.render(image, disparity, blur, device=device, **kw)
        photo[name] = {"psnr_db": round(psnr(out, truth[..., :3]), 2), **timing}
    return {"size": size, "reference": ref, "rows": rows, "from_pinhole_photo": photo}


def _exact_plane(tex: np.ndarray, r: float, aperture: br.Aperture) -> np.ndarray:
    from reference import raytrace_ref

    return raytrace_ref.disc_convolution(tex, r, raytrace_ref.inside(aperture))


def study_plane(device: str, runs: int) -> dict:
    rng = np.random.default_rng(1)
    n = 192
    tex = np.concatenate([rng.random((n, n, 3)), np.ones((n, n, 1))], 2).astype(np.float32)
    blur = br.BlurParams(20.0, 0.5)  # r = 10 px
    layer = [br.Layer(tex, plane=(0, 0, 0.0))]
    out, st = br.raytrace_layers(layer, blur, device=device)
    want = _exact_plane(tex[..., :3], 10.0, br.Aperture())
    lin = float(10 * np.log10(1.0 / np.mean((out[..., :3].astype(np.float64) - want) ** 2)))
    timing = common.time_warm(lambda: br.raytrace_layers(layer, blur, device=device), runs=runs, warmup=0)
    return {"size": n, "radius_px": 10.0, "psnr_linear_db": round(lin, 2), "psnr_srgb_db": round(psnr(out[..., :3], want), 2),
            "rays_mean": st.spp_mean, **timing}


def study_light(device: str, radii: tuple[int, ...]) -> list[dict]:
    rows = []
    for name, ap in APERTURES.items():
        for radius in radii:
            n = 2 * radius + 9
            c = n // 2
            tex = np.zeros((n, n, 4), np.float32)
            tex[..., 3] = 1.0
            tex[c, c, :3] = 1000.0
            t = time.perf_counter()
            got, st = br.raytrace_layers([br.Layer(tex, plane=(0, 0, 0.0))], br.BlurParams(float(radius), 1.0), ap,
                                         device=device)
            dt = time.perf_counter() - t
            spread = got[..., 0].astype(np.float64) / 1000.0
            light = np.zeros((n, n, 1))
            light[c, c] = 1.0
            want = _exact_plane(light, float(radius), ap)[..., 0]
            rows.append({"aperture": name, "radius_px": radius, "l1": round(float(np.abs(spread - want).sum()), 4),
                         "energy": round(float(spread.sum()), 6), "rays": st.spp_max, "seconds": round(dt, 3),
                         "size": n})
    return rows


def study_synth(device: str, scenes: int) -> list[dict]:
    from bokehray.data.synth import SynthConfig, make_scene, mean_disparity

    cfg = SynthConfig()
    opts = br.RaytraceOptions(max_spp=cfg.max_spp)
    rows = []
    for idx in range(scenes):
        layers, desc = make_scene(cfg, 0, idx)
        for f_index, d_f in enumerate((mean_disparity(layers[0]), mean_disparity(layers[-1]))):
            blur = br.BlurParams(max(cfg.blur_levels), d_f)
            t = time.perf_counter()
            out, st = br.raytrace_layers(layers, blur, cfg.aperture, options=opts, device=device)
            dt = time.perf_counter() - t
            ref, _ = br.raytrace_layers(layers, blur, cfg.aperture, options=sixteen_x(opts), device=device)
            rows.append({"scene": idx, "layers": [lyr["kind"] for lyr in desc["layers"]], "f_index": f_index,
                         "K": max(cfg.blur_levels), "psnr_vs_16x_db": round(psnr(out[..., :3], ref[..., :3]), 2),
                         "rays_mean": round(st.spp_mean, 1), "seconds": round(dt, 3)})
    return rows


def main() -> int:  # noqa: C901
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, help="folder for raytrace--quadrature[-DEVICE].json")
    ap.add_argument("--plot", type=Path, help="PNG of error against time (stack study)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--quick", action="store_true", help="fewer runs and radii, 2 synth scenes")
    ap.add_argument("--only", default="stack,plane,light,synth")
    args = ap.parse_args()
    only = set(args.only.split(","))
    runs = 1 if args.quick else 3
    result: dict = {"machine": common.machine_info(), "device": args.device}
    if "plane" in only:
        result["plane"] = study_plane(args.device, runs)
        p = result["plane"]
        print(f"plane r = 10 px: {p['psnr_linear_db']:.2f} dB linear, {p['psnr_srgb_db']:.2f} dB sRGB vs the exact "
              f"disc convolution, {p['rays_mean']:.0f} rays, {p['median']:.3f} s")
    if "light" in only:
        result["light"] = study_light(args.device, (16, 64, 256) if args.quick else (16, 32, 64, 128, 256))
        print("| aperture | R (px) | L1 vs exact | energy | rays | s |\n|---|---|---|---|---|---|")
        for r in result["light"]:
            print(f"| {r['aperture']} | {r['radius_px']} | {r['l1']:.4f} | {r['energy']:.5f} | {r['rays']} | "
                  f"{r['seconds']:.2f} |")
    if "synth" in only:
        result["synth"] = study_synth(args.device, 2 if args.quick else 4)
        print("| scene | layers | focus | PSNR vs 16x cells (dB) | rays (mean) | s |\n|---|---|---|---|---|---|")
        for r in result["synth"]:
            print(f"| {r['scene']} | {', '.join(r['layers'])} | {r['f_index']} | {r['psnr_vs_16x_db']:.2f} | "
                  f"{r['rays_mean']:.0f} | {r['seconds']:.2f} |")
    if "stack" in only:
        result["stack"] = study_stack(args.device, runs, 512)
        s = result["stack"]
        print(f"stack: reference {s['reference']['rays_mean']:.0f} rays/px in {s['reference']['seconds']:.1f} s")
        print("| max_spp | rays (mean) | PSNR vs 16x cells (dB) | median s |\n|---|---|---|---|")
        for r in s["rows"]:
            print(f"| {r['max_spp']} | {r['rays_mean']:.0f} | {r['psnr_db']:.2f} | {r['median']:.3f} |")
        for name, r in s["from_pinhole_photo"].items():
            print(f"| {name} from the pinhole image | - | {r['psnr_db']:.2f} | {r['median']:.3f} |")
    if args.out:
        tag = "" if args.device == "cpu" else f"-{args.device}"
        common.write_json(args.out / f"raytrace--quadrature{tag}.json", result)
    if args.plot and "stack" in result:
        plot(result["stack"], args.plot)
    return 0


def plot(stack: dict, path: Path) -> None:
    """PSNR against time: the quadrature at each ray cap, the former spiral sampler, the photo levels."""
    import json

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.2))
    rows = stack["rows"]
    ax.semilogx([r["median"] for r in rows], [r["psnr_db"] for r in rows], "o-", color="C0",
                label="layer stack: cell quadrature (max_spp 1..256)")
    for r in rows:
        ax.annotate(str(r["max_spp"]), (r["median"], r["psnr_db"]), textcoords="offset points", xytext=(4, -10),
                    fontsize=7)
    before = common.REPO / "benchmarks" / "results" / "raytrace--spp-spiral-before.json"
    if before.exists():
        old = [r for r in json.loads(before.read_text())["rows"] if isinstance(r["spp"], int)]
        ax.semilogx([r["median"] for r in old], [r["psnr_db"] for r in old], "s--", color="C7",
                    label="layer stack: former spiral point samples (8..256 rays; earlier, quiet run; vs 1024 rays)")
    marks = {"preview": ("D", "C1"), "raytrace (photo mode)": ("^", "C2")}
    for name, r in stack["from_pinhole_photo"].items():
        m, c = marks[name]
        ax.semilogx([r["median"]], [r["psnr_db"]], m, color=c, markersize=8, label=f"{name} of the pinhole image")
    ax.set_xlabel("median time per render, 512 x 512 (s)")
    ax.set_ylabel("PSNR vs converged render (dB)")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7, loc="upper left")
    ax.set_title("3-layer scene (strands r = 24, card r = 12, sharp background)", fontsize=9)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)


if __name__ == "__main__":
    sys.exit(main())
