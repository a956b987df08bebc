"""Thin structures against exact renders: one depth a pixel versus soft edges (``bokehray.matting``).

Each scene is a two-layer stack in the style of ``bokehray.data.synth``: an RGBA foreground (hair-like strands 0.5-3 px,
fur around a cut-out, foliage, a fence mesh, a photo cut-out with an antialiased rim) on a plane in front of a
photo background with small bright lights. The stack is flattened to a photo plus one disparity a pixel, either by
the alpha >= 0.5 rule ("exact" map) or blurred like an estimator's ("estimated": Gaussian, sigma 1.5 px). The target
is the exact thin-lens render of the true stack (``bokehray.raytrace_layers``), with focus on the foreground and on
the background. Each input is scored:

* **matting alone** (renderer-free): the two-layer scene the photo gives, traced exactly by the same ray tracer:
  one depth a pixel ("one depth") versus the pixels split by ``split_mixed_pixels`` ("soft"); in both the
  background the near side hides is filled the same simple way (:func:`fill_hidden`); plus the alpha RMSE over
  the mixed pixels and their neighbours;
* **renderers**: ``bokehray.render`` at the preview (and, with ``--raytrace``, the ray-tracer) level with
  ``LayerOptions(soft_edges=False)`` and ``True``, when this build's LayerOptions has that option, and the preview
  with ``strand_gaps=False`` (dashed strands' gaps not bridged) where it has that one.

Scores are PSNR (sRGB, clipped, ``bokehray.data.metrics``) over the whole image, the 8 px band around depth edges and
the 1.5 px silhouette ring. It also times ``split_mixed_pixels`` on the 1536 x 1024 demo scene (median of warm
runs) against the preview render of the same scene with soft edges off, in the same run.

Usage (from the repository root)::

    python benchmarks/renderer/bench_thin.py                      # JSON in benchmarks/results/thin.json, figures in docs/img
    python benchmarks/renderer/bench_thin.py --quick              # fewer, smaller scenes (a smoke run)
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np
from scipy import ndimage

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/common.py

from common import REPO, machine_info, time_warm

import bokehray as br
from bokehray.app.demo import build_demo_scene
from bokehray.data import metrics, synth
from bokehray.levels.raytrace import Layer, raytrace_layers
from bokehray.matting import split_mixed_pixels
from bokehray.scene import SoftEdges, cap_coc

CLASSES = ("strands", "fur", "foliage", "mesh", "cutout")
D_FG, D_BG = 0.85, 0.15
K = 24.0
SPP = 256
ESTIMATED_SIGMA_PX = 1.5
RING_PX = 1.5


# --------------------------------------------------------------------------- scenes


def _strands(n: int, rng: np.random.Generator, widths=(0.5, 3.0), count=(30, 50)) -> np.ndarray:
    """Gently bent strands of uniform widths in ``widths`` (px), one tint."""
    yy, xx = (np.mgrid[0:n, 0:n] + 0.5).astype(np.float32)
    alpha = np.zeros((n, n), np.float32)
    for _ in range(int(rng.integers(*count))):
        a0, bend = rng.uniform(0, np.pi), rng.uniform(-0.004, 0.004)
        ox, oy = rng.uniform(0.1, 0.9, 2) * n
        u = (xx - ox) * np.cos(a0) + (yy - oy) * np.sin(a0)
        v = -(xx - ox) * np.sin(a0) + (yy - oy) * np.cos(a0) - bend * u * u
        cov = synth.stroke_coverage(np.abs(v), rng.uniform(*widths)) * (np.abs(u) < rng.uniform(0.15, 0.45) * n)
        np.maximum(alpha, cov, out=alpha)
    colour = np.array(rng.choice([[0.35, 0.22, 0.12], [0.8, 0.65, 0.4], [0.08, 0.06, 0.05], [0.9, 0.9, 0.85]]))
    return np.concatenate([np.broadcast_to(colour, (n, n, 3)), alpha[..., None]], 2).astype(np.float32)


def _fur(n: int, rng: np.random.Generator) -> np.ndarray:
    """A textured disc (the cat) with short fine hairs (0.5-1.2 px) standing out of its rim."""
    yy, xx = (np.mgrid[0:n, 0:n] + 0.5).astype(np.float32)
    tex = synth.fit_crop(synth.bundled_photo("chelsea"), n, rng)
    cx, cy, rad = 0.5 * n, 0.5 * n, 0.28 * n
    alpha = np.clip(rad + 0.5 - np.hypot(xx - cx, yy - cy), 0, 1).astype(np.float32)
    colour = np.zeros((n, n, 3), np.float32) + tex
    hair = np.array([0.55, 0.38, 0.22], np.float32)
    for _ in range(220):
        th = rng.uniform(0, 2 * np.pi)
        length = rng.uniform(0.03, 0.09) * n
        tilt = th + rng.uniform(-0.5, 0.5)
        bx, by = cx + (rad - 2) * np.cos(th), cy + (rad - 2) * np.sin(th)
        u = (xx - bx) * np.cos(tilt) + (yy - by) * np.sin(tilt)
        v = -(xx - bx) * np.sin(tilt) + (yy - by) * np.cos(tilt)
        cov = synth.stroke_coverage(np.abs(v), rng.uniform(0.5, 1.2)) * (u > 0) * (u < length)
        colour = np.where((cov > alpha)[..., None], hair * rng.uniform(0.7, 1.3), colour)
        np.maximum(alpha, cov, out=alpha)
    return np.concatenate([colour, alpha[..., None]], 2).astype(np.float32)


def foreground(kind: str, n: int, rng: np.random.Generator) -> np.ndarray:
    if kind == "strands":
        return _strands(n, rng)
    if kind == "fur":
        return _fur(n, rng)
    if kind == "cutout":
        return synth.cutout_layer(synth.bundled_photo("coffee"), n, rng)
    return synth.procedural_layer(kind, n, rng)


def background(n: int, rng: np.random.Generator) -> np.ndarray:
    """A photo with small very bright lights (radiance 5-20, radius 1-3 px): bokeh balls behind the foreground."""
    rgb = synth.fit_crop(synth.bundled_photo("rocket"), n, rng)
    yy, xx = (np.mgrid[0:n, 0:n] + 0.5).astype(np.float32)
    for _ in range(14):
        cx, cy = rng.uniform(0.05, 0.95, 2) * n
        cov = np.clip(rng.uniform(1.0, 3.0) + 0.5 - np.hypot(xx - cx, yy - cy), 0, 1)[..., None]
        hue = np.array(rng.choice([[1.0, 0.75, 0.45], [0.6, 0.8, 1.0], [1.0, 1.0, 1.0]]))
        rgb = rgb * (1 - cov) + cov * hue * rng.uniform(5, 20)
    return np.concatenate([rgb, np.ones((n, n, 1))], 2).astype(np.float32)


@dataclasses.dataclass
class Scene:
    kind: str
    fg: np.ndarray  # RGBA, straight alpha
    bg: np.ndarray  # RGBA, alpha 1
    photo: np.ndarray
    exact_map: np.ndarray  # disparity by the alpha >= 0.5 rule

    @property
    def layers(self) -> list[Layer]:
        return [Layer(self.fg, plane=(0.0, 0.0, D_FG)), Layer(self.bg, plane=(0.0, 0.0, D_BG))]

    def disparity(self, mapname: str) -> np.ndarray:
        if mapname == "exact":
            return self.exact_map
        return np.clip(ndimage.gaussian_filter(self.exact_map, ESTIMATED_SIGMA_PX), 0, 1).astype(np.float32)


def make_scene(kind: str, n: int, seed: int) -> Scene:
    rng = np.random.default_rng([seed, CLASSES.index(kind)])
    fg, bg = foreground(kind, n, rng), background(n, rng)
    a = fg[..., 3:4]
    photo = (a * fg[..., :3] + (1 - a) * bg[..., :3]).astype(np.float32)
    exact = np.where(fg[..., 3] >= 0.5, D_FG, D_BG).astype(np.float32)
    return Scene(kind, fg, bg, photo, exact)


# --------------------------------------------------------------------------- the scene a photo gives, traced exactly


def photo_stack(scene: Scene, disparity: np.ndarray, soft: SoftEdges | None, blur: br.BlurParams) -> list:
    """The two layers one depth a pixel (``soft`` None) or the soft split gives, as ray-traceable layers: the near
    layer holds the near-side pixels (alpha 1) and the split pixels' near parts (F, alpha); the far layer the
    far-side pixels, the split pixels' far parts (B) and, where the near side hides it, a fill of those
    (:func:`fill_hidden`)."""
    h, w = disparity.shape
    s = blur.signed_coc(disparity)
    mid = 0.5 * (float(s.max()) + float(s.min()))
    near = s > mid
    n_rgba = np.zeros((h * w, 4), np.float32)
    f_rgba = np.zeros((h * w, 4), np.float32)
    n_s = np.where(near, s, float(s.max())).ravel().astype(np.float32)
    f_s = np.where(near, blur.signed_coc(np.float32(D_BG)), s).ravel().astype(np.float32)
    photo = scene.photo.reshape(-1, 3)
    n_rgba[near.ravel(), :3] = photo[near.ravel()]
    n_rgba[near.ravel(), 3] = 1.0
    f_rgba[:, :3] = photo
    f_rgba[:, 3] = 1.0
    hidden = near.ravel().copy()
    if soft is not None and len(soft):
        i = soft.index
        n_rgba[i, :3], n_rgba[i, 3], n_s[i] = soft.foreground, soft.alpha, soft.near_coc
        f_rgba[i, :3], f_s[i] = soft.background, soft.far_coc
        hidden[i] = False
    f_rgba[:, :3] = fill_hidden(f_rgba[:, :3].reshape(h, w, 3), ~hidden.reshape(h, w)).reshape(-1, 3)

    def to_d(v: np.ndarray) -> np.ndarray:  # signed CoC back to disparity
        return np.clip(v / blur.k_px + blur.focus_disparity, 0.0, 1.0).reshape(h, w).astype(np.float32)

    return [Layer(n_rgba.reshape(h, w, 4), disparity=to_d(n_s)), Layer(f_rgba.reshape(h, w, 4), disparity=to_d(f_s))]


def fill_hidden(rgb: np.ndarray, known: np.ndarray) -> np.ndarray:
    """``rgb`` with the pixels not ``known`` filled by normalised Gaussian convolution of the known ones at growing
    scales (sigma 1, 2, 4, ... px; the first scale that reaches a pixel fills it), on tone-mapped colour
    ``c / (1 + c)`` so a bright light beside the hidden region does not flood it."""
    out = rgb.copy()
    todo = ~known
    tm = rgb / (1.0 + rgb)
    sigma = 1.0
    while todo.any() and sigma < 4 * max(rgb.shape):
        den = ndimage.gaussian_filter(known.astype(np.float64), sigma)
        num = np.stack([ndimage.gaussian_filter(tm[..., c] * known, sigma) for c in range(3)], -1)
        reach = todo & (den > 1e-3)
        v = num[reach] / den[reach][:, None]
        out[reach] = v / np.maximum(1.0 - v, 1e-6)
        todo &= ~reach
        sigma *= 2.0
    return out.astype(np.float32)


def trace(layers: list[Layer], blur: br.BlurParams, spp: int = SPP) -> np.ndarray:
    out, _ = raytrace_layers(layers, blur, options=br.RaytraceOptions(max_spp=spp))

    return out[..., :3]


# --------------------------------------------------------------------------- scoring


def masks(scene: Scene) -> tuple[np.ndarray, np.ndarray]:
    """The 8 px band around the depth edges and the 1.5 px silhouette ring (of the exact map)."""
    return (metrics.discontinuity_band(scene.exact_map),
            metrics.discontinuity_band(scene.exact_map, width=RING_PX))


def scores(pred: np.ndarray, target: np.ndarray, band: np.ndarray, ring: np.ndarray) -> dict:
    p, t = metrics.to_srgb(pred), metrics.to_srgb(target)
    return {"whole": metrics.psnr(t, p), "band": metrics.psnr(t, p, band), "ring": metrics.psnr(t, p, ring)}


def alpha_rmse(scene: Scene, disparity: np.ndarray, soft) -> tuple[float, float]:
    """Alpha RMSE over the mixed pixels and their 8-neighbours: one depth a pixel (alpha 1 on the near side, else 0)
    and with the split."""
    a = scene.fg[..., 3]
    region = ndimage.binary_dilation((a > 0) & (a < 1), np.ones((3, 3), bool))
    base = (disparity > 0.5 * (float(disparity.max()) + float(disparity.min()))).astype(np.float32)
    est = base.ravel().copy()
    if soft is not None and len(soft):
        est[soft.index] = soft.alpha
    est = est.reshape(a.shape)
    return (float(np.sqrt(((base - a)[region] ** 2).mean())), float(np.sqrt(((est - a)[region] ** 2).mean())))


def has_option(name: str) -> bool:
    return name in {f.name for f in dataclasses.fields(br.LayerOptions)}


def has_soft_option() -> bool:
    return has_option("soft_edges")


def run_case(scene: Scene, mapname: str, focus: str, raytrace: bool, keep: dict, spp: int = SPP) -> dict:
    d = scene.disparity(mapname)
    blur = br.BlurParams(K, D_FG if focus == "fg" else D_BG)
    target = trace(scene.layers, blur, spp)
    band, ring = masks(scene)
    s = blur.signed_coc(d)
    t = time.perf_counter()
    soft = split_mixed_pixels(scene.photo, s)
    t_split = time.perf_counter() - t
    a0, a1 = alpha_rmse(scene, d, soft)
    row = {"class": scene.kind, "map": mapname, "focus": focus, "split_pixels": len(soft),
           "split_seconds": t_split, "alpha_rmse": {"one_depth": a0, "soft": a1}}
    renders = {"one depth (exact trace)": trace(photo_stack(scene, d, None, blur), blur, spp),
               "soft (exact trace)": trace(photo_stack(scene, d, soft, blur), blur, spp)}
    if has_soft_option():
        for on in (False, True):
            renders[f"preview, soft_edges={on}"] = br.render(scene.photo, d, blur,
                                                             layers=br.LayerOptions(soft_edges=on))
            if raytrace:
                renders[f"raytrace, soft_edges={on}"] = br.render(scene.photo, d, blur, quality="raytrace",
                                                                  layers=br.LayerOptions(soft_edges=on))
        if has_option("strand_gaps"):  # the soft edges without the dashed strands' gaps bridged (bokehray.strands)
            renders["preview, strand_gaps=False"] = br.render(scene.photo, d, blur,
                                                              layers=br.LayerOptions(strand_gaps=False))
    row["scores"] = {name: scores(img, target, band, ring) for name, img in renders.items()}
    keep[(scene.kind, mapname, focus)] = (scene.photo, target, renders, ring)
    return row


def timing(runs: int) -> dict:
    """``split_mixed_pixels`` on the 1536 x 1024 demo scene (focus on the subject) against the preview render of
    the same scene with soft edges off: medians of warm runs, in this run."""
    demo = build_demo_scene(1536, 1024)
    blur = br.BlurParams(demo.k_px, demo.focus_near)
    s = cap_coc(blur.signed_coc(demo.disparity))
    split = time_warm(lambda: split_mixed_pixels(demo.image, s), runs=runs)
    off = br.LayerOptions(soft_edges=False) if has_soft_option() else br.LayerOptions()
    preview = time_warm(lambda: br.render(demo.image, demo.disparity, blur, layers=off), runs=runs)
    out = {"split_mixed_pixels": split, "preview_soft_off": preview,
           "ratio_split_to_preview": split["median"] / preview["median"],
           "split_pixels": len(split_mixed_pixels(demo.image, s))}
    if has_soft_option():
        on = time_warm(lambda: br.render(demo.image, demo.disparity, blur, layers=br.LayerOptions(soft_edges=True)),
                       runs=runs)
        out["preview_soft_on"] = on
        out["ratio_on_to_off"] = on["median"] / preview["median"]
    return out


# --------------------------------------------------------------------------- figures


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    variants = [v for v in rows[0]["scores"]]
    fig, axes = plt.subplots(1, 3, figsize=(16, 4.2), sharey=False)
    labels = [f"{r['class']}\n{r['map']}, f:{r['focus']}" for r in rows]
    x = np.arange(len(rows))
    wbar = 0.8 / len(variants)
    for ax, region in zip(axes, ("whole", "band", "ring")):
        for j, v in enumerate(variants):
            ax.bar(x + j * wbar - 0.4 + wbar / 2, [r["scores"][v][region] for r in rows], wbar, label=v)
        ax.set_title(f"PSNR (dB), {region}")
        ax.set_xticks(x, labels, rotation=90, fontsize=6)
        lo = min(r["scores"][v][region] for r in rows for v in variants)
        ax.set_ylim(max(0.0, lo - 3), None)
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def crops(keep: dict, out_dir: Path, size: int = 64) -> list[str]:
    """100 % crops (input / exact / before / after) at the ring of each class, exact map, focus on the background
    (the foreground blurred: where a mixed pixel's foreground share shows), one PNG per class."""
    from PIL import Image

    written = []
    for (kind, mapname, focus), (photo, target, renders, ring) in keep.items():
        if mapname != "exact" or focus != "bg":
            continue
        ys, xs = np.nonzero(ring)
        h, w = ring.shape
        # the crop holding the most ring pixels on a coarse grid
        grid = np.zeros((max(1, h // 16), max(1, w // 16)))
        np.add.at(grid, (np.minimum(ys // 16, grid.shape[0] - 1), np.minimum(xs // 16, grid.shape[1] - 1)), 1)
        dens = ndimage.uniform_filter(grid, size // 16, mode="constant")
        gy, gx = np.unravel_index(int(np.argmax(dens)), dens.shape)
        y0 = int(np.clip(gy * 16 + 8 - size // 2, 0, h - size))
        x0 = int(np.clip(gx * 16 + 8 - size // 2, 0, w - size))
        sl = (slice(y0, y0 + size), slice(x0, x0 + size))
        before = renders.get("preview, soft_edges=False", renders["one depth (exact trace)"])
        after = renders.get("preview, soft_edges=True", renders["soft (exact trace)"])
        tiles = [photo, target, before, after]
        row = np.concatenate([np.round(metrics.to_srgb(t[sl]) * 255).astype(np.uint8) for t in tiles], 1)
        name = f"thin_{kind}.png"
        Image.fromarray(row).resize((row.shape[1] * 3, row.shape[0] * 3), Image.NEAREST).save(out_dir / name)
        written.append(name)
    return written


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=320)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--quick", action="store_true", help="small scenes, two classes, no timing (a smoke run)")
    ap.add_argument("--classes", default=None, help="comma-separated classes (default: all; --quick: the first two)")
    ap.add_argument("--raytrace", action="store_true", help="also score the ray-tracer level")
    ap.add_argument("--spp", type=int, default=SPP, help="ray cap of the exact traces (targets and scenes)")
    ap.add_argument("--runs", type=int, default=5, help="warm runs of the timing (0: no timing)")
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "thin.json")
    ap.add_argument("--img", type=Path, default=REPO / "docs" / "img")
    args = ap.parse_args(argv)
    classes = tuple(args.classes.split(",")) if args.classes else CLASSES[:2] if args.quick else CLASSES
    size = 96 if args.quick else args.size
    rows, keep = [], {}
    for kind in classes:
        scene = make_scene(kind, size, args.seed)
        for mapname in ("exact", "estimated"):
            for focus in ("fg", "bg"):
                row = run_case(scene, mapname, focus, args.raytrace, keep, args.spp)
                rows.append(row)
                sc = row["scores"]
                print(f"{kind:8s} {mapname:9s} f:{focus}  alpha {row['alpha_rmse']['one_depth']:.3f} -> "
                      f"{row['alpha_rmse']['soft']:.3f}  " + "  ".join(
                          f"{v}: {sc[v]['whole']:.1f}/{sc[v]['band']:.1f}/{sc[v]['ring']:.1f}" for v in sc),
                      flush=True)
    result = {"machine": machine_info(), "seed": args.seed, "size": size, "K": K, "d_fg": D_FG, "d_bg": D_BG,
              "spp": args.spp,
              "estimated_sigma_px": ESTIMATED_SIGMA_PX, "ring_px": RING_PX, "rows": rows}
    summary = {}
    for v in rows[0]["scores"]:
        for mapname in ("exact", "estimated"):
            for kind in classes:
                sel = [r["scores"][v] for r in rows if r["map"] == mapname and r["class"] == kind]
                summary.setdefault(v, {}).setdefault(mapname, {})[kind] = {
                    reg: float(np.mean([x[reg] for x in sel])) for reg in ("whole", "band", "ring")}
    result["summary_mean_over_focus"] = summary
    if not args.quick and args.runs > 0:
        result["timing_demo_1536x1024"] = timing(args.runs)
        t = result["timing_demo_1536x1024"]
        print(f"split_mixed_pixels {t['split_mixed_pixels']['median']:.3f} s, "
              f"preview {t['preview_soft_off']['median']:.3f} s, ratio {t['ratio_split_to_preview']:.2f}")
    if not args.quick:
        args.img.mkdir(parents=True, exist_ok=True)
        plot(rows, args.img / "thin_psnr.png")
        result["crops"] = crops(keep, args.img)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1, default=float))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
