"""The demo focused far, at 100 %: soft edges before and after, against the exact thin-lens render.

    python research/demo_soft_crops/demo_soft_crops.py [--width 1536] [--height 1024] [--tile 256]

1. Builds the demo scene (``bokehray.app.demo.build_demo_scene``) and records its true layers: the module paints
   the photo back to front with straight-alpha "over" (``demo._over``); that function is wrapped for the call
   (not edited) so every painted layer's alpha, colour and disparity is kept. Layers at the background's depth
   (the photo, the fairy lights' cord and discs) are flattened into one opaque tilted plane; the brick panel is
   a tilted plane (fitted to its recorded disparity), the cat a dome (a disparity-map layer), each wire and
   blade a fronto-parallel plane ``(0, 0, d)``. The flattened stack is checked against the demo photo.
2. The exact reference: ``bokehray.raytrace_layers`` of that stack (128 rays a pixel at most), traced in
   square tiles with a halo of the largest CoC (a ray from a pixel meets a layer within the layer's CoC of it,
   so each tile's core is the whole trace's; layers with no content in a tile's window are left out).
3. The preview of the demo photo and its map, before (``LayerOptions(soft_edges=False)``) and after (default).
4. Scores (PSNR in sRGB of the clipped image): whole image, the 8 px band around depth edges, the 1.5 px
   ring around the cat's silhouette, the wires' and the grass's own (visible) pixels.
5. ``docs/img/demo_soft_crops.png``: crops at 100 % and x4 (nearest neighbour) of the cat's rim, a wire,
   grass blades and a fairy light; ``research/demo_soft_crops/results/demo_soft_crops.json``: the numbers.
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import time
from pathlib import Path

import numpy as np
from scipy import ndimage

import bokehray
import bokehray.app.demo as demo
from bokehray.colour import linear_to_srgb
from bokehray.edge_estimate import depth_edges

ROOT = Path(__file__).resolve().parents[2]
IMG = ROOT / "docs" / "img" / "demo_soft_crops.png"
OUT = ROOT / "research" / "demo_soft_crops" / "results" / "demo_soft_crops.json"
EDGE_JUMP = 0.05  # a depth edge: neighbouring disparities differ by more than this


# --------------------------------------------------------------------------- the true layers


def record_layers(width: int, height: int):
    """Build the demo with ``demo._over`` wrapped; returns the scene, the background before any layer, and the
    painted layers in painting order (slice, alpha, rgb, d)."""
    calls, first = [], {}
    orig = demo._over

    def recording_over(img, disp, sl, alpha, rgb, d):
        if not first:
            first["img"], first["disp"] = img.copy(), disp.copy()
        calls.append((sl, np.array(alpha, np.float32), np.array(rgb, np.float32), np.array(d, np.float32)))
        orig(img, disp, sl, alpha, rgb, d)

    demo._over = recording_over
    try:
        scene = demo.build_demo_scene(width, height)
    finally:
        demo._over = orig
    return scene, first["img"], first["disp"], calls


def fit_plane(d: np.ndarray, mask: np.ndarray, y0: int = 0, x0: int = 0):
    """Least-squares ``d = a x + b y + c`` over ``mask`` at pixel centres (x = i + 0.5) in frame coordinates."""
    yy, xx = np.nonzero(mask)
    A = np.stack([xx + x0 + 0.5, yy + y0 + 0.5, np.ones(xx.size)], 1).astype(np.float64)
    coef, *_ = np.linalg.lstsq(A, d[mask].astype(np.float64), rcond=None)
    resid = float(np.abs(A @ coef - d[mask]).max())
    return tuple(float(v) for v in coef), resid


class TrueStack:
    """The demo's layers, nearest first, each stored on its own box: kind, box slice, alpha, rgb, plane or
    disparity map (on the box), name."""

    def __init__(self, scene, base_img, base_disp, calls):
        H, W = scene.disparity.shape
        self.shape = (H, W)
        bg = base_img.copy()
        bg_calls, rest = [], []
        for c in calls:
            sl, alpha, rgb, d = c
            if d.ndim and d.shape == alpha.shape and np.array_equal(d, base_disp[sl]):
                bg_calls.append(c)  # cord and fairy lights: painted on the background plane
            else:
                rest.append(c)
        for sl, alpha, rgb, _ in bg_calls:
            a = alpha[..., None]
            bg[sl] = bg[sl] * (1.0 - a) + a * rgb
        self.n_lights = len(bg_calls) - 1
        self.lights = [(sl, alpha) for sl, alpha, _, _ in bg_calls[1:]]
        plane_bg, res_bg = fit_plane(base_disp, np.ones_like(base_disp, bool))
        self.fit_residual = {"background": res_bg}
        layers = [dict(kind="plane", sl=(slice(0, H), slice(0, W)), alpha=np.ones((H, W), np.float32), rgb=bg,
                       plane=plane_bg, name="background")]  # farthest first while building
        maps = [c for c in rest if c[3].ndim]
        assert len(maps) == 2, f"expected the panel and the cat as the layers with a disparity map, got {len(maps)}"
        for sl, alpha, rgb, d in rest:
            if d.ndim == 0:
                wide = (sl[1].stop - sl[1].start) > 0.9 * W
                layers.append(dict(kind="plane", sl=sl, alpha=alpha, rgb=rgb, plane=(0.0, 0.0, float(d)),
                                   name="wire" if wide else "grass"))
            elif sl is maps[0][0] or (d.min() >= 0.4 and d.max() <= 0.6):
                inner = (alpha > 0) & (d > d.min() + 1e-3) & (d < d.max() - 1e-3)
                plane, res = fit_plane(d, inner, sl[0].start, sl[1].start)
                self.fit_residual["panel"] = res
                layers.append(dict(kind="plane", sl=sl, alpha=alpha, rgb=rgb, plane=plane, name="panel"))
            else:
                layers.append(dict(kind="map", sl=sl, alpha=alpha, rgb=rgb, disp=d, name="cat"))
        self.layers = layers[::-1]  # nearest first

    def composite(self) -> np.ndarray:
        """Flatten back to front: the photo the stack stands for."""
        H, W = self.shape
        img = np.zeros((H, W, 3), np.float32)
        for L in self.layers[::-1]:
            a = L["alpha"][..., None]
            img[L["sl"]] = img[L["sl"]] * (1.0 - a) + a * L["rgb"]
        return img

    def name_alpha(self, name: str) -> np.ndarray:
        """Visible weight of the layers called ``name``: their alpha times the transmittance of nearer layers."""
        H, W = self.shape
        trans = np.ones((H, W), np.float32)
        out = np.zeros((H, W), np.float32)
        for L in self.layers:
            a = np.zeros((H, W), np.float32)
            a[L["sl"]] = L["alpha"]
            if L["name"] == name:
                out += a * trans
            trans *= 1.0 - a
        return out

    def own_alpha(self, name: str) -> np.ndarray:
        """Coverage of the layers called ``name`` on their own (nearer layers ignored)."""
        out = np.zeros(self.shape, np.float32)
        for L in self.layers:
            if L["name"] == name:
                np.maximum(out[L["sl"]], L["alpha"], out=out[L["sl"]])
        return out

    def window(self, y0: int, y1: int, x0: int, x1: int) -> list:
        """``bokehray.Layer`` list of the window (layers with no content in it left out), nearest first."""
        out = []
        h, w = y1 - y0, x1 - x0
        for L in self.layers:
            sl = L["sl"]
            ya, yb = max(sl[0].start, y0), min(sl[0].stop, y1)
            xa, xb = max(sl[1].start, x0), min(sl[1].stop, x1)
            if ya >= yb or xa >= xb:
                continue
            sub = (slice(ya - sl[0].start, yb - sl[0].start), slice(xa - sl[1].start, xb - sl[1].start))
            alpha = L["alpha"][sub]
            if not (alpha > 0).any():
                continue
            rgba = np.zeros((h, w, 4), np.float32)
            dst = (slice(ya - y0, yb - y0), slice(xa - x0, xb - x0))
            rgba[dst + (3,)] = alpha
            rgb = L["rgb"]
            rgba[dst + (slice(0, 3),)] = rgb[sub] if rgb.ndim == 3 else rgb
            if L["kind"] == "plane":
                a, b, c = L["plane"]
                out.append(bokehray.Layer(rgba, plane=(a, b, c + a * x0 + b * y0)))
            else:
                disp = np.full((h, w), float(L["disp"].min()), np.float32)  # the cat's rim, outside its box
                disp[dst] = L["disp"][sub]
                out.append(bokehray.Layer(rgba, disparity=disp))
        return out


def exact_render(stack: TrueStack, blur, tile: int, halo: int, log) -> np.ndarray:
    H, W = stack.shape
    out = np.zeros((H, W, 3), np.float32)
    tiles = [(ty, tx) for ty in range(0, H, tile) for tx in range(0, W, tile)]
    for i, (ty, tx) in enumerate(tiles):
        y0, y1 = max(ty - halo, 0), min(ty + tile + halo, H)
        x0, x1 = max(tx - halo, 0), min(tx + tile + halo, W)
        layers = stack.window(y0, y1, x0, x1)
        t = time.perf_counter()
        res, _ = bokehray.raytrace_layers(layers, blur)
        cy, cx = min(ty + tile, H), min(tx + tile, W)
        out[ty:cy, tx:cx] = res[ty - y0:cy - y0, tx - x0:cx - x0, :3]
        log(f"  exact tile {i + 1}/{len(tiles)} ({len(layers)} layers) {time.perf_counter() - t:.1f} s")
    return out


# --------------------------------------------------------------------------- scores


def srgb(x: np.ndarray) -> np.ndarray:
    return linear_to_srgb(np.clip(x, 0.0, 1.0)).astype(np.float64)


def psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> float:
    d = (srgb(a) - srgb(b)) ** 2
    mse = float(d[mask].mean()) if mask is not None else float(d.mean())
    return float("inf") if mse == 0 else 10.0 * math.log10(1.0 / mse)


# --------------------------------------------------------------------------- crops


def pick_crops(stack: TrueStack, img: np.ndarray, disp: np.ndarray, blur, size: int) -> dict:
    """Centres of the crops, chosen on the map: where the disparity jumps at the cat's rim and along a wire with
    the photo's largest contrast across the jump (where a sharp outline or dashes would show most) and the
    fewest other near layers in the crop, among the most grass blades, and at a visible fairy light closest to
    a depth edge."""
    H, W = disp.shape
    edge = depth_edges(disp, EDGE_JUMP)
    cat = stack.own_alpha("cat") >= 0.5
    wire = stack.own_alpha("wire") >= 0.5
    grass = stack.name_alpha("grass") > 0
    panel = stack.own_alpha("panel") > 0
    frac = lambda m: ndimage.uniform_filter(m.astype(np.float32), size)  # noqa: E731  (share of the crop)
    lum = srgb(img).mean(axis=-1)
    contrast = ndimage.maximum_filter(lum, 5) - ndimage.minimum_filter(lum, 5)
    along = lambda m: (ndimage.uniform_filter(contrast * m, 31)  # noqa: E731
                       / np.maximum(ndimage.uniform_filter(m.astype(np.float64), 31), 1e-9))
    yy, xx = np.mgrid[0:H, 0:W]
    inside = (yy >= size) & (yy < H - size) & (xx >= size) & (xx < W - size)
    out = {}
    # the cat's rim: a silhouette pixel on a depth edge, high contrast along the rim, few strands or panel
    rim = cat & ~ndimage.binary_erosion(cat) & edge
    score = np.where(rim & inside, along(rim) - frac(grass | wire) - frac(panel), -np.inf)
    out["cat rim"] = np.unravel_index(np.argmax(score), score.shape)
    # a wire: a wire pixel on a depth edge, high contrast along the wire, no cat, panel or grass in the crop
    score = np.where(wire & edge & inside, along(wire) - 4 * frac(grass | cat | panel), -np.inf)
    out["wire"] = np.unravel_index(np.argmax(score), score.shape)
    # grass: the crop with the most blade pixels on depth edges (away from the cat)
    score = np.where(inside, frac(grass & edge) - 5 * frac(cat), -np.inf)
    out["grass"] = np.unravel_index(np.argmax(score), score.shape)
    # a fairy light: a visible one (nothing in front of its centre) with the most depth edges close to it
    visible_bg = stack.name_alpha("background")
    dist_edge = ndimage.distance_transform_edt(~edge)
    best, best_score = None, -np.inf
    for sl, _alpha in stack.lights:
        cy, cx = (sl[0].start + sl[0].stop) // 2, (sl[1].start + sl[1].stop) // 2
        if not (size <= cy < H - size and size <= cx < W - size) or visible_bg[cy, cx] < 0.99:
            continue
        coc = float(blur.k_px) * abs(float(disp[cy, cx]) - float(blur.focus_disparity))
        s = -float(dist_edge[cy, cx]) + 0.1 * coc
        if s > best_score:
            best, best_score = (cy, cx), s
    if best is not None:
        out["fairy light"] = best
    return {k: (int(v[0]), int(v[1])) for k, v in out.items()}


def crop(img: np.ndarray, c, size: int) -> np.ndarray:
    y0, x0 = c[0] - size // 2, c[1] - size // 2
    return img[y0:y0 + size, x0:x0 + size]


def figure(panels: dict, centres: dict, notes: dict, size100: int, size4: int, path: Path) -> None:
    """Rows: regions; columns: input / exact / before / after at 100 % (``size100`` px), then the same at x4
    (nearest neighbour) of the central ``size4`` px. Pixels placed 1:1 (``figimage``), labels by matplotlib."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = ["input", "exact", "before (soft_edges=False)", "after (soft edges)"]
    gap, head, lab = 8, 30, 20
    big = size4 * 4
    row_h = max(size100, big) + lab + gap
    width = gap + 4 * (size100 + gap) + 4 * (big + gap)
    height = head + len(centres) * row_h + gap
    canvas = np.full((height, width, 3), 255, np.uint8)
    labels = []
    for r, (region, c) in enumerate(centres.items()):
        y = head + r * row_h
        labels.append((gap, y + max(size100, big) + 3, f"{region}: centre (x={c[1]}, y={c[0]}); {notes[region]}"))
        for k, name in enumerate(names):
            tile = np.round(srgb(crop(panels[name], c, size100)) * 255).astype(np.uint8)
            x = gap + k * (size100 + gap)
            canvas[y:y + size100, x:x + size100] = tile
            o = (size100 - size4) // 2  # outline of the enlarged part
            for (yy, xx) in ((slice(y + o - 1, y + o), slice(x + o - 1, x + o + size4 + 1)),
                             (slice(y + o + size4, y + o + size4 + 1), slice(x + o - 1, x + o + size4 + 1)),
                             (slice(y + o - 1, y + o + size4 + 1), slice(x + o - 1, x + o)),
                             (slice(y + o - 1, y + o + size4 + 1), slice(x + o + size4, x + o + size4 + 1))):
                canvas[yy, xx] = (255, 40, 40)
            zoom = np.repeat(np.repeat(tile[o:o + size4, o:o + size4], 4, 0), 4, 1)
            xz = gap + 4 * (size100 + gap) + k * (big + gap)
            canvas[y:y + big, xz:xz + big] = zoom
    fig = plt.figure(figsize=(width / 100, height / 100), dpi=100)
    fig.figimage(canvas, 0, 0, origin="upper")
    for k, name in enumerate(names):
        fig.text((gap + k * (size100 + gap) + size100 / 2) / width, 1 - 10 / height, name + " 100 %",
                 ha="center", va="center", fontsize=10)
        fig.text((gap + 4 * (size100 + gap) + k * (big + gap) + big / 2) / width, 1 - 10 / height,
                 name + " x4", ha="center", va="center", fontsize=10)
    for x, y, text in labels:
        fig.text(x / width, 1 - (y + lab / 2) / height, text, ha="left", va="center", fontsize=9)
    fig.savefig(path, dpi=100)
    plt.close(fig)


# --------------------------------------------------------------------------- main


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--width", type=int, default=1536)
    ap.add_argument("--height", type=int, default=1024)
    ap.add_argument("--tile", type=int, default=256, help="core side of the exact trace's tiles")
    ap.add_argument("--crop", type=int, default=224, help="side of the 100 %% crops")
    ap.add_argument("--zoom", type=int, default=56, help="side of the part enlarged x4")
    ap.add_argument("--no-figure", action="store_true")
    ap.add_argument("--cache", help="npz of the exact reference and the render without soft edges: read "
                    "if it exists (the soft-edge render is always made), else written")
    args = ap.parse_args()
    log = lambda s: print(s, flush=True)  # noqa: E731

    t0 = time.perf_counter()
    scene, base_img, base_disp, calls = record_layers(args.width, args.height)
    clean = demo.build_demo_scene(args.width, args.height)
    assert np.array_equal(clean.image, scene.image) and np.array_equal(clean.disparity, scene.disparity)
    stack = TrueStack(scene, base_img, base_disp, calls)
    comp = np.maximum(stack.composite(), 0.0)
    comp_diff = float(np.abs(comp - scene.image).max())
    log(f"{len(stack.layers)} true layers ({stack.n_lights} fairy lights flattened into the background); "
        f"composite vs demo photo: max |diff| = {comp_diff:.3g} (linear); plane fits: {stack.fit_residual}")
    blur = bokehray.BlurParams(k_px=scene.k_px, focus_disparity=scene.focus_far)
    img, disp = scene.image, scene.disparity

    cached = bool(args.cache and Path(args.cache).exists())
    if cached:  # the exact reference and the render without soft edges do not depend on the matting
        z = np.load(args.cache)
        before, exact = z["before"], z["exact"]
        t_before, _, t_exact, halo = (float(v) for v in z["times"])
        halo = int(halo)
        log(f"exact reference and 'before' read from {args.cache}")
    else:
        t = time.perf_counter()
        before = bokehray.render(img, disp, blur, layers=bokehray.LayerOptions(soft_edges=False))
        t_before = time.perf_counter() - t
    t = time.perf_counter()
    after = bokehray.render(img, disp, blur, layers=bokehray.LayerOptions())
    t_after = time.perf_counter() - t
    log(f"preview before {t_before:.1f} s, after {t_after:.1f} s")
    if not cached:
        d_lo = min(float(disp.min()), 0.0)
        halo = int(math.ceil(float(blur.k_px) * max(1.0 - blur.focus_disparity, blur.focus_disparity - d_lo))) + 4
        t = time.perf_counter()
        exact = exact_render(stack, blur, args.tile, halo, log)
        t_exact = time.perf_counter() - t
        log(f"exact {t_exact:.0f} s (halo {halo} px)")
        if args.cache:
            np.savez(args.cache, before=before, after=after, exact=exact,
                     times=np.array([t_before, t_after, t_exact, halo]))

    edge = depth_edges(disp, EDGE_JUMP)
    band = ndimage.distance_transform_edt(~edge) <= 8.0
    cat = stack.own_alpha("cat") >= 0.5
    wire_v, grass_v = stack.name_alpha("wire"), stack.name_alpha("grass")
    wire, grass = wire_v > 0.01, grass_v > 0.01
    # pixel centres within about 1.5 px of the silhouette (2 px from a pixel on the other side), not hidden by
    # a blade in front
    ring = np.where(cat, ndimage.distance_transform_edt(cat), ndimage.distance_transform_edt(~cat)) <= 2.0
    ring &= ~grass & ~wire
    regions = {"whole": None, "band 8 px": band, "cat ring 1.5 px": ring, "wire": wire, "grass": grass,
               "wire, mixed pixels": wire & (wire_v < 0.99), "wire, opaque core": wire_v >= 0.99,
               "grass, mixed pixels": grass & (grass_v < 0.99), "grass, opaque core": grass_v >= 0.99}
    scores = {}
    for name, m in regions.items():
        scores[name] = {"pixels": int(m.sum()) if m is not None else int(disp.size),
                        "before": round(psnr(before, exact, m), 2), "after": round(psnr(after, exact, m), 2),
                        "input": round(psnr(img, exact, m), 2)}
        log(f"{name:20s} before {scores[name]['before']:6.2f}  after {scores[name]['after']:6.2f} dB")

    centres = pick_crops(stack, img, disp, blur, args.crop)
    log(f"crops: {centres}")
    crop_scores = {}
    for name, c in centres.items():
        ref = crop(exact, c, args.crop)
        crop_scores[name] = {"before": round(psnr(crop(before, c, args.crop), ref), 2),
                             "after": round(psnr(crop(after, c, args.crop), ref), 2)}
    notes = {k: f"PSNR of the 100 % crop against the exact render: before {v['before']:.1f} dB, after "
                f"{v['after']:.1f} dB" for k, v in crop_scores.items()}
    if not args.no_figure:
        figure({"input": img, "exact": exact, "before (soft_edges=False)": before, "after (soft edges)": after},
               centres, notes, args.crop, args.zoom, IMG)
        log(f"wrote {IMG}")
    result = {
        "scene": f"demo {args.width} x {args.height}, focused far",
        "k_px": float(blur.k_px), "focus_disparity": float(blur.focus_disparity),
        "exact": {"method": "bokehray.raytrace_layers of the demo's true layers (default RaytraceOptions: <= 128 "
                            f"rays a pixel), {args.tile} px tiles with a {halo} px halo",
                  "layers": len(stack.layers), "composite_max_abs_diff_linear": comp_diff,
                  "plane_fit_max_residual": stack.fit_residual, "seconds": round(t_exact, 1)},
        "metric": "PSNR in sRGB of the image clipped to [0, 1], against the exact render",
        "regions": {"band 8 px": f"within 8 px of a disparity jump > {EDGE_JUMP} between neighbours",
                    "cat ring 1.5 px": "pixel centres within about 1.5 px of the cat's silhouette (its own coverage >= 0.5; <= 2 px from a pixel on the other side), less wire and grass pixels",
                    "wire": "pixels where the wires' visible coverage > 0.01",
                    "grass": "pixels where the blades' visible coverage > 0.01",
                    "mixed pixels / opaque core": "the same pixels split at a visible coverage of 0.99"},
        "scores": scores,
        "crops": {"side_px": args.crop, "centres_yx": centres, "psnr": crop_scores},
        "preview_seconds": {"before": round(t_before, 2), "after": round(t_after, 2)},
        "machine": platform.platform(),
        "total_seconds": round(time.perf_counter() - t0, 1),
        "renders_read_from_cache": bool(args.cache and cached),
    }
    OUT.write_text(json.dumps(result, indent=2) + "\n")
    log(f"wrote {OUT}")


if __name__ == "__main__":
    main()
