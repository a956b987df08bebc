"""Does the refiner fix what wrong depth breaks? Preview, raytrace and refine on the dev set or a synthetic split.

The disparity handed to every method is the true one, or it eroded / dilated by 1-5 px (paper
fig. 7), blurred, shifted, or a depth estimator's kind of map (``bokehray_refiner.training.data.corrupt_disparity``);
the target is the exact render of the true scene. Scores are PSNR/SSIM in sRGB after clipping
(``bokehray.data.metrics``), over the whole image and within 8 px of a depth discontinuity of the
*true* disparity. Every case is scored with the refiner gated (the default) and ungated
(``GateOptions(enabled=False)``), so the gate's effect is measured on the same inputs.

    # the path-traced dev set (exact thin-lens renders; band from its depth.exr as its score.py does)
    python benchmarks/refiner/bench_refiner.py --devset ../shared/data/pathtraced-dev --threads 1

    # a held-out synthetic split
    bokehray synth -n 8 -o /tmp/refiner-split --seed 9000 --size 256 --blur-levels 8,16,24
    python benchmarks/refiner/bench_refiner.py --data /tmp/refiner-split --pairs 16 --all-corruptions --no-raytrace --threads 1

    # time at 1536 x 1024 (a dev-set scene scaled up), medians of warm runs, with the tiles refined
    python benchmarks/refiner/bench_refiner.py --timing --devset ../shared/data/pathtraced-dev --threads 1 --runs 3

Writes ``benchmarks/results/refiner_{devset,synth,time}.json`` and ``docs/img/refiner_{devset,synth}.png``.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/common.py

from dataclasses import replace

from common import REPO, machine_info, write_json

CONDITIONS = [("none", 0), ("erode", 1), ("erode", 3), ("erode", 5), ("dilate", 1), ("dilate", 3), ("dilate", 5)]
DEV_CONDITIONS = CONDITIONS + [("blur", 3), ("shift", 2), ("estimator", 4)]
NET_CONDITIONS = [("none", 0), ("local", 10), ("estimator", 6), ("missing", 2)]
"""The network's own target (docs/refiner.md): what the depth fix cannot undo, and the exact map."""
METHODS = ("preview", "raytrace", "depthfix", "edges", "refine", "refine_ungated", "refine_nofix")


def devset_samples(root: Path):
    """(name, image, disparity, blur, target, band) for every render of the path-traced dev set."""
    import importlib.util
    import json

    import bokehray as br

    spec = importlib.util.spec_from_file_location("devset_score", root / "score.py")
    sc = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(sc)
    for info_path in sorted(root.glob("*/info.json")):
        scene = info_path.parent
        info = json.loads(info_path.read_text())
        image = br.read_image(scene / "image.exr")
        disparity = br.read_disparity(scene / "disparity.exr")
        band = sc.discontinuity_band(sc.read_exr(str(scene / "depth.exr")), 8.0)
        for r in info["renders"]:
            blur = br.BlurParams(r["K"], min(1.0, max(0.0, r["focus_disparity"])))
            target = sc.read_exr(str(scene / f"{r['file']}.exr"))[..., :3]
            yield f"{scene.name}/{r['file']}", image, disparity, blur, target, band


def synth_samples(root: str, pairs: int):
    """(name, image, disparity, blur, target, band) for every k-th pair of a BLB-layout folder, ``pairs`` of them."""
    import bokehray as br
    from bokehray.data.datasets import BLBDataset
    from bokehray.data.metrics import discontinuity_band

    ds = BLBDataset(root)
    step = max(1, len(ds) // pairs)
    for i in list(range(0, len(ds), step))[:pairs]:
        s = ds[i]
        yield (s.name, s.image, s.disparity, br.BlurParams(s.k_px, s.focus_disparity), s.target,
               discontinuity_band(s.disparity))


def add_split_args(ap: argparse.ArgumentParser, stem: str) -> None:
    """The options of a script that scores one split: ``--data`` or ``--devset``, ``--pairs`` and ``--out`` (its
    default: :func:`split_out`)."""
    src = ap.add_mutually_exclusive_group(required=True)
    src.add_argument("--data", help="held-out BLB-layout folder (never used for training)")
    src.add_argument("--devset", help="the path-traced dev set folder (with score.py)")
    ap.add_argument("--pairs", type=int, default=24, help="--data: pairs to score (every k-th pair of the folder)")
    ap.add_argument("--out", default=None, help=f"JSON (default: {stem}_{{devset,synth}}.json)")


def split_out(args: argparse.Namespace, stem: str) -> str:
    """``--out``, or ``<stem>_devset.json`` (``_synth.json`` for ``--data``); ``stem`` is relative to the repository."""
    return args.out or str(REPO / f"{stem}_{'devset' if args.devset else 'synth'}.json")


def split_samples(args: argparse.Namespace):
    """The samples of the split :func:`add_split_args` parsed."""
    return devset_samples(Path(args.devset)) if args.devset else synth_samples(args.data, args.pairs)


def main() -> None:  # noqa: C901
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    src = ap.add_mutually_exclusive_group(required=True)
    src.add_argument("--data", help="held-out BLB-layout folder (never used for training)")
    src.add_argument("--devset", help="the path-traced dev set folder (with score.py)")
    ap.add_argument("--all-corruptions", action="store_true", help="synthetic split: also blur, shift, estimator")
    ap.add_argument("--network-conditions", action="store_true",
                    help="instead: the exact map, edges misplaced locally by 10 px, an estimator's map (1/6 "
                    "resolution) and strands up to 5 px missing (the network's own target)")
    ap.add_argument("--pairs", type=int, default=48, help="pairs to score (every k-th pair of the folder)")
    ap.add_argument("--weights", help="refiner weights (default: the shipped ones)")
    ap.add_argument("--edges", nargs="?", const="shipped", default=None,
                    help="the edge network refine uses (these weights, or the shipped ones, which refine uses "
                         "anyway); adds the method 'edges' (the depth fix and the edge network, no residual network)")
    ap.add_argument("--max-spp", type=int, default=64, help="raytrace rays per pixel cap")
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--band-margin", type=float, default=None,
                    help="RefineOptions.band_margin_px (inf: no band restriction); default: the option's default")
    ap.add_argument("--no-raytrace", action="store_true", help="skip the raytrace level (for quick sweeps)")
    ap.add_argument("--reuse-raytrace", default=None,
                    help="take the raytrace rows from this earlier JSON of the same data instead of rendering them "
                         "(the ray tracer does not depend on the refiner)")
    ap.add_argument("--edge-threshold", type=float, default=None,
                    help="RefineOptions.edge_threshold (the edge network's move threshold); default: the option's default")
    ap.add_argument("--edge-passes", type=int, default=None,
                    help="RefineOptions.edge_passes (the edge network's passes); default: the option's default")
    ap.add_argument("--no-agreement", action="store_true",
                    help="refine with the gate's colour/depth agreement off (highlight guard only)")
    ap.add_argument("--no-nofix", action="store_true", help="skip refine_nofix (the refiner without the depth fix)")
    ap.add_argument("--no-ungated", action="store_true", help="skip refine_ungated (and, with --timing, its timing)")
    ap.add_argument("--timing", action="store_true",
                    help="instead: time preview and refine at 1536 x 1024 (a dev-set scene scaled up; --devset DIR)")
    ap.add_argument("--runs", type=int, default=3, help="--timing: warm runs per case (medians reported)")
    ap.add_argument("--out", default=None, help="JSON (default: benchmarks/results/refiner_devset.json, _synth.json or _time.json)")
    ap.add_argument("--plot", default=None, help="plot (default: docs/img/refiner_devset.png or refiner_synth.png)")
    args = ap.parse_args()
    tag = "time" if args.timing else ("devset" if args.devset else "synth")
    args.out = args.out or str(REPO / f"benchmarks/results/refiner_{tag}.json")
    args.plot = args.plot or str(REPO / f"docs/img/refiner_{tag}.png")

    import torch

    if args.threads:
        torch.set_num_threads(args.threads)
    from bokehray_refiner.edges import load_edge_net
    from bokehray_refiner.refine import RefineOptions, load_refiner, refine
    from bokehray_refiner.training.data import corrupt_disparity

    import bokehray as br
    from bokehray.data.metrics import score

    ropts = RefineOptions() if args.band_margin is None else RefineOptions(band_margin_px=args.band_margin)
    if args.no_agreement:
        ropts = replace(ropts, gate=replace(ropts.gate, agreement=False))
    if args.edge_threshold is not None:
        ropts = replace(ropts, edge_threshold=args.edge_threshold)
    if args.edge_passes is not None:
        ropts = replace(ropts, edge_passes=args.edge_passes)

    model = load_refiner(args.weights)
    edge_model = None
    if args.edges:
        edge_model = load_edge_net(None if args.edges == "shipped" else args.edges)
    if args.timing:
        return timing(args, model, ropts, edge_model)
    if args.devset:
        samples = list(devset_samples(Path(args.devset)))
        conditions = NET_CONDITIONS if args.network_conditions else DEV_CONDITIONS
    else:
        samples = list(synth_samples(args.data, args.pairs))
        conditions = NET_CONDITIONS if args.network_conditions else (DEV_CONDITIONS if args.all_corruptions
                                                                      else CONDITIONS)
    ungated = replace(ropts, gate=replace(ropts.gate, enabled=False))
    fix_only = replace(ropts, neural=False, edges=False)  # the classical pipeline: what the networks add to
    edges_only = replace(ropts, neural=False)
    nofix = replace(ropts, depthfix=replace(ropts.depthfix, enabled=False))
    old_ray = {}
    if args.reuse_raytrace:
        for r in json.loads(Path(args.reuse_raytrace).read_text())["rows"]:
            if r["method"] == "raytrace":
                old_ray[(r["pair"], r["corruption"], r["px"])] = r
    rows = []
    for n, (name, image, disparity, blur, target, band) in enumerate(samples):
        for kind, amount in conditions:
            d = np.clip(corrupt_disparity(disparity, kind, amount), 0.0, 1.0)
            t0 = time.perf_counter()
            preview = br.render(image, d, blur)
            t_preview = time.perf_counter() - t0
            t0 = time.perf_counter()
            ray = None if (args.no_raytrace or args.reuse_raytrace) else br.render(
                image, d, blur, quality="raytrace", options=br.RaytraceOptions(max_spp=args.max_spp))
            t_ray = time.perf_counter() - t0
            if (name, kind, amount) in old_ray:
                rows.append(old_ray[(name, kind, amount)] | {"reused": True})
            rer = lambda dd, im=image, bl=blur: br.render(im, dd, bl)  # noqa: E731  (the preview on the fixed map)
            fixed, st_fix = refine(image, d, blur, preview, options=fix_only, rerender=rer)
            moved, st_edges = (None, None) if edge_model is None else refine(
                image, d, blur, preview, options=edges_only, rerender=rer, edge_model=edge_model)
            refined, st = refine(image, d, blur, preview, model=model, options=ropts, rerender=rer,
                                 edge_model=edge_model)
            raw, st_raw = (None, None) if args.no_ungated else refine(image, d, blur, preview, model=model,
                                                                       options=ungated, rerender=rer,
                                                                       edge_model=edge_model)
            plain, st_plain = (None, None) if args.no_nofix else refine(image, d, blur, preview, model=model,
                                                                         options=nofix)
            for method, img, t, stx in (("preview", preview, t_preview, None), ("raytrace", ray, t_ray, None),
                                        ("depthfix", fixed, t_preview + st_fix.seconds, st_fix),
                                        ("edges", moved, t_preview + (st_edges.seconds if st_edges else 0),
                                         st_edges),
                                        ("refine", refined, t_preview + st.seconds, st),
                                        ("refine_ungated", raw, t_preview + (st_raw.seconds if st_raw else 0),
                                         st_raw),
                                        ("refine_nofix", plain, t_preview + (st_plain.seconds if st_plain else 0),
                                         st_plain)):
                if img is None:
                    continue
                rows.append({"pair": name, "k_px": blur.k_px, "corruption": kind, "px": amount, "method": method,
                             "seconds": t, "share_refined": stx.share_refined if stx else None,
                             "gate_open": stx.gate_open if stx else None,
                             "depth_fixed_px": stx.depth_fixed_px if stx else None,
                             "fixed_share": stx.fixed_share if stx else None} | score(img, target, band))
        print(f"{n + 1}/{len(samples)} {name}", flush=True)
    data_label = str(args.devset or args.data)
    summary = summarise(rows, conditions)
    gains = network_gains(summary)
    write_json(args.out, {"machine": machine_info(), "data": data_label, "pairs": len(samples),
                          "weights": str(args.weights or "shipped"), "edges": args.edges,
                          "refine_options": repr(ropts),
                          "network_gain": gains, "summary": summary, "rows": rows})
    print_table(summary)
    (plot_network if args.network_conditions else plot)(summary, args.plot)
    for g in gains:
        print(f"network alone (refine - depth fix), {g['corruption']} {g['px']}: whole {g['psnr']:+.2f} dB, "
              f"band {g['band_psnr']:+.2f} dB")


def timing(args, model, ropts, edge_model=None) -> None:
    """Preview vs preview + refine at 1536 x 1024, medians of warm runs, with the tiles refined."""
    from bokehray_refiner.refine import refine
    from bokehray_refiner.training.data import corrupt_disparity
    from scipy import ndimage

    import bokehray as br

    root = Path(args.devset or "../shared/data/pathtraced-dev")
    scene = root / "d2_leafy_twig"  # a twig and a card over a receding ground: a typical edge share
    image = br.read_image(scene / "image.exr")[..., :3]
    disp = br.read_disparity(scene / "disparity.exr")
    h, w = 1024, 1536
    y0 = (image.shape[0] - 320 * h // w) // 2
    crop = (slice(y0, y0 + 320 * h // w), slice(None))
    zoom = (h / (320 * h // w), w / 320)
    image = np.clip(ndimage.zoom(image[crop], zoom + (1,), order=1), 0, None)[:h, :w].astype(np.float32)
    disp = ndimage.zoom(disp[crop], zoom, order=0)[:h, :w].astype(np.float32)
    blur = br.BlurParams(32.0, 0.8)  # focus on the twig, background CoC up to ~25 px
    ungated = replace(ropts, gate=replace(ropts.gate, enabled=False))
    rows = []
    for kind, amount in (("none", 0), ("erode", 3), ("estimator", 8)):
        d = np.clip(corrupt_disparity(disp, kind, amount), 0, 1)
        rer = lambda dd: br.render(image, dd, blur)  # noqa: E731
        br.render(image, d, blur)  # warm-up
        refine(image, d, blur, None, model=model, options=ropts, rerender=rer, edge_model=edge_model)
        tp, tg, tu, tt, stages = [], [], [], [], {k: [] for k in ("depthfix", "rerender", "gate", "neural")}
        for _ in range(args.runs):  # alternating: the preview alone, then render --refine (fix, one render, gate, net)
            t0 = time.perf_counter()
            br.render(image, d, blur)
            tp.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            _, st = refine(image, d, blur, None, model=model, options=ropts, rerender=rer, edge_model=edge_model)
            tt.append(time.perf_counter() - t0)
            tg.append(st.seconds)
            for k in stages:
                stages[k].append(getattr(st, f"{k}_seconds"))
            if not args.no_ungated:
                _, su = refine(image, d, blur, None, model=model, options=ungated, rerender=rer,
                               edge_model=edge_model)
                tu.append(su.seconds)
        row = {"disparity": f"{kind} {amount}", "preview_s": float(np.median(tp)), "refine_s": float(np.median(tg)),
               "render_refine_s": float(np.median(tt)), "preview_runs_s": tp, "refine_runs_s": tg,
               "refine_ungated_s": float(np.median(tu)) if tu else None, "tiles_total": st.tiles_total,
               "tiles_near_edges": st.tiles_near_edges, "tiles_refined": st.tiles_refined,
               "tiles_refined_ungated": su.tiles_refined if tu else None, "band_share": st.band_pixels / d.size,
               "gate_open": st.gate_open, "depth_fixed_px": st.depth_fixed_px}
        row |= {f"{k}_s": float(np.median(v)) for k, v in stages.items()}
        # the refine pass: what render --refine adds to the preview (the level itself renders once, on the
        # corrected map, and that render is the preview's cost, not the pass's)
        row["refine_over_preview"] = float(np.median(np.array(tg) / np.array(tp)))
        row["ratio"] = float(np.median(np.array(tt) / np.array(tp)))  # render --refine / preview, same run
        row["ratio_ungated"] = (row["preview_s"] + row["refine_ungated_s"]) / row["preview_s"] if tu else None
        rows.append(row)
        print(json.dumps({k: (round(v, 3) if isinstance(v, float) else v) for k, v in row.items()
                          if not k.endswith("runs_s")}), flush=True)
    ratios = [r["refine_over_preview"] for r in rows]
    print(f"refine pass / preview, median over the three maps: {float(np.median(ratios)):.2f}x", flush=True)
    write_json(args.out, {"machine": machine_info(), "size": [h, w], "k_px": blur.k_px, "runs": args.runs,
                          "torch_threads": args.threads, "median_refine_over_preview": float(np.median(ratios)),
                          "rows": rows})


def summarise(rows: list[dict], conditions=CONDITIONS) -> list[dict]:
    out = []
    for kind, amount in conditions:
        for method in METHODS:
            sel = [r for r in rows if r["corruption"] == kind and r["px"] == amount and r["method"] == method]
            if not sel:
                continue
            band = [r["band_psnr"] for r in sel if not math.isnan(r["band_psnr"])]
            out.append({"corruption": kind, "px": amount, "method": method,
                        "psnr": float(np.mean([r["psnr"] for r in sel])),
                        "ssim": float(np.mean([r["ssim"] for r in sel])),
                        "band_psnr": float(np.mean(band)) if band else math.nan,
                        "band_ssim": float(np.nanmean([r["band_ssim"] for r in sel])),
                        "seconds": float(np.median([r["seconds"] for r in sel])),
                        "share_refined": float(np.mean([r["share_refined"] for r in sel]))
                        if method.startswith("refine") or method in ("depthfix", "edges") else None,
                        "gate_open": float(np.mean([r["gate_open"] for r in sel]))
                        if method.startswith("refine") else None,
                        "depth_fixed_px": float(np.mean([r.get("depth_fixed_px") or 0 for r in sel]))})
    return out


def network_gains(summary: list[dict]) -> list[dict]:
    """Per condition, what the network adds on top of the classical pipeline: refine - depth fix (mean dB)."""
    out = []
    for kind, amount in dict.fromkeys((r["corruption"], r["px"]) for r in summary):
        get = {r["method"]: r for r in summary if (r["corruption"], r["px"]) == (kind, amount)}
        if "refine" in get and "depthfix" in get:
            out.append({"corruption": kind, "px": amount,
                        **{m: get["refine"][m] - get["depthfix"][m] for m in ("psnr", "band_psnr")}})
    return out


def print_table(summary: list[dict]) -> None:
    print(f"{'depth':>10} {'method':>9} {'PSNR':>7} {'band':>7} {'SSIM':>6} {'bSSIM':>6} {'time s':>7}")
    for r in summary:
        print(f"{r['corruption'] + ' ' + str(r['px']):>10} {r['method']:>9} {r['psnr']:7.2f} {r['band_psnr']:7.2f} "
              f"{r['ssim']:6.3f} {r['band_ssim']:6.3f} {r['seconds']:7.3f}")


def plot(summary: list[dict], path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    xs = [-5, -3, -1, 0, 1, 3, 5]  # erosion negative, dilation positive

    def key(x):
        return ("none", 0) if x == 0 else (("erode", -x) if x < 0 else ("dilate", x))

    fig, axes = plt.subplots(1, 3, figsize=(14, 3.8), dpi=120)
    for method, style, color in (("preview", "o-", "tab:blue"), ("raytrace", "s-", "tab:orange"),
                                 ("depthfix", "d-", "tab:purple"), ("refine", "^-", "tab:green"),
                                 ("refine_ungated", "v:", "tab:red")):
        for ax, metric in zip(axes, ("psnr", "band_psnr")):
            ys = [next((r[metric] for r in summary if (r["corruption"], r["px"]) == key(x) and r["method"] == method),
                       None) for x in xs]
            if None not in ys:
                ax.plot(xs, ys, style, color=color, label=method)
    for ax, title in zip(axes, ("whole image", "within 8 px of depth edges")):
        ax.set_xlabel("disparity error: erosion (-) / dilation (+), px")
        ax.set_ylabel("PSNR (dB)")
        ax.set_title(title)
        ax.grid(alpha=0.3)
        ax.legend()
    conds = list(dict.fromkeys((r["corruption"], r["px"]) for r in summary))
    ax = axes[2]
    bars = (("depthfix", "tab:purple"), ("refine", "tab:green"), ("refine_ungated", "tab:red"))
    for j, (method, color) in enumerate(bars):
        gains = []
        for c in conds:
            get = {r["method"]: r["band_psnr"] for r in summary if (r["corruption"], r["px"]) == c}
            best = max(get["preview"], get.get("raytrace", -math.inf))
            gains.append(get.get(method, math.nan) - best)
        ax.bar(np.arange(len(conds)) + 0.27 * (j - 1), gains, 0.27, color=color, label=method)
    ax.axhline(0, color="k", lw=0.8)
    ax.axhline(-0.1, color="k", lw=0.6, ls=":")
    ax.set_xticks(np.arange(len(conds)), [f"{k} {p}" if p else k for k, p in conds], rotation=45, ha="right",
                  fontsize=8)
    ax.set_ylabel("band PSNR - best classical level (dB)")
    ax.set_title("per corruption")
    ax.grid(alpha=0.3, axis="y")
    ax.legend()
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)


def plot_network(summary: list[dict], path: str) -> None:
    """Per condition: band PSNR of each method, and what the network adds over the depth fix."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    conds = list(dict.fromkeys((r["corruption"], r["px"]) for r in summary))
    names = [f"{k} {p}" if p else "exact" for k, p in conds]
    fig, axes = plt.subplots(1, 2, figsize=(11, 3.8), dpi=120)
    methods = [m for m in ("preview", "depthfix", "edges", "refine", "refine_ungated") if any(r["method"] == m for r in summary)]
    for j, method in enumerate(methods):
        ys = [next((r["band_psnr"] for r in summary if (r["corruption"], r["px"]) == c and r["method"] == method),
                   math.nan) for c in conds]
        axes[0].bar(np.arange(len(conds)) + 0.8 / len(methods) * (j - (len(methods) - 1) / 2), ys,
                    0.8 / len(methods), label=method)
    axes[0].set_ylabel("band PSNR (dB)")
    axes[0].set_ylim(bottom=min(r["band_psnr"] for r in summary) - 2)
    gains = network_gains(summary)
    axes[1].bar(np.arange(len(gains)), [g["band_psnr"] for g in gains], color="tab:green", label="band")
    axes[1].bar(np.arange(len(gains)) + 0.3, [g["psnr"] for g in gains], 0.3, color="tab:olive", label="whole")
    axes[1].axhline(0, color="k", lw=0.8)
    axes[1].set_ylabel("refine - depth fix (dB)")
    axes[1].set_title("the network's own contribution")
    for ax in axes:
        ax.set_xticks(np.arange(len(conds)), names)
        ax.grid(alpha=0.3, axis="y")
        ax.legend(fontsize=8)
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)


if __name__ == "__main__":
    main()
