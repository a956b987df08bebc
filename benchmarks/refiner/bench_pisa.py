"""PISA attention: memory and time of the windowed form against the dense one, and one-step pipeline times.

Each configuration runs in a fresh process: one warm-up call, then the peak RSS
(VmHWM, reset through /proc/self/clear_refs) of a second call minus the RSS just
before it (inputs and masks already built). Times are medians of warm runs.

    python benchmarks/refiner/bench_pisa.py                 # full table -> benchmarks/results/pisa.json, docs/img/pisa_memory.png
    python benchmarks/refiner/bench_pisa.py --quick         # two sizes, no plot
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/common.py

from common import REPO, machine_info, peak_rss_mb_of, report_rss, reset_peak_rss, time_warm, write_json

HEADS, HEAD_DIM, MAX_COC = 4, 16, 8.0


def _inputs(n: int):
    import numpy as np
    import torch
    from bokehray_refiner.pisa import pisa_masks

    rng = np.random.default_rng(0)
    d = rng.uniform(0.0, 1.0, (n, n)).astype(np.float32)
    d[0, 0], d[-1, -1] = 0.0, 1.0  # CoC spans 0..MAX_COC latent px
    m = pisa_masks(d, 0.0, MAX_COC)
    coc, vis = (torch.from_numpy(a)[None] for a in m.numpy())
    g = torch.Generator().manual_seed(0)
    q, k, v = (torch.randn(1, HEADS, n, n, HEAD_DIM, generator=g) for _ in range(3))
    return q, k, v, coc, vis, m.window


def _call(form: str, n: int):
    import torch
    from bokehray_refiner.attention import pisa_attention, pisa_attention_dense

    q, k, v, coc, vis, w = _inputs(n)
    if form == "dense":
        import numpy as np

        sys.path.insert(0, str(REPO / "tests"))
        from reference.pisa_ref import window_to_dense

        cd = torch.from_numpy(window_to_dense(coc[0].numpy(), w))[None]
        vd = torch.from_numpy(window_to_dense(vis[0].numpy(), w))[None]
        del np
        return lambda: pisa_attention_dense(q.flatten(2, 3), k.flatten(2, 3), v.flatten(2, 3), cd, vd)
    return lambda: pisa_attention(q, k, v, coc, vis, w)


def child(form: str, n: int) -> None:
    import torch

    with torch.no_grad():
        fn = _call(form, n)
        fn()  # warm: first-call allocations (thread pools, kernel scratch) are not the attention's
        del fn
        fn = _call(form, n)
        reset_peak_rss()  # so the peak is this call's
        report_rss(peak=False)
        fn()
        report_rss(peak=True)


def child_time(form: str, n: int) -> float:
    import torch

    with torch.no_grad():
        return time_warm(_call(form, n), runs=3, warmup=1)


def pipeline_times() -> dict:
    """CPU time of the one-step pipeline (tiny SDXL-layout model) and of the shipped refiner, at 512 x 512."""
    import tempfile

    import numpy as np
    import torch
    from bokehray_refiner.masks import PisaMaskProvider
    from bokehray_refiner.model import BokehRefiner
    from bokehray_refiner.onestep import OneStepOptions, load_one_step
    from bokehray_refiner.onestep.testing import write_tiny_sdxl

    from bokehray.lens import BlurParams

    rng = np.random.default_rng(0)
    img = rng.uniform(0, 1, (512, 512, 3)).astype(np.float32)
    d = np.full((512, 512), 0.2, np.float32)
    d[128:384, 160:352] = 0.9
    out = {"threads": torch.get_num_threads()}
    with tempfile.TemporaryDirectory() as tmp:
        model = load_one_step(write_tiny_sdxl(tmp), options=OneStepOptions(tile=512))
        out["tiny_sdxl_onestep_512"] = time_warm(lambda: model.render(img, d, BlurParams(16.0, 0.9)), runs=3)
    refiner = BokehRefiner().eval()
    x = torch.from_numpy(img).permute(2, 0, 1)[None]
    coc = torch.from_numpy(16.0 * (d - 0.9))[None]

    def full() -> None:
        with torch.no_grad():
            refiner(x, x, coc, PisaMaskProvider(d, 0.9, 16.0))

    out["refiner_full_frame_512"] = time_warm(full, runs=3)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--out", default=str(REPO / "benchmarks/results/pisa.json"))
    ap.add_argument("--plot", default=str(REPO / "docs/img/pisa_memory.png"))
    ap.add_argument("--child", nargs=2, metavar=("FORM", "N"))
    ap.add_argument("--child-time", nargs=2, metavar=("FORM", "N"))
    args = ap.parse_args()
    if args.child:
        child(args.child[0], int(args.child[1]))
        return
    if args.child_time:
        import json

        print("TIME=" + json.dumps(child_time(args.child_time[0], int(args.child_time[1]))))
        return
    import json
    import subprocess

    sizes = [16, 32] if args.quick else [16, 32, 48, 64, 96]
    rows = []
    for n in sizes:
        for form in ("windowed", "dense"):
            if form == "dense" and n > 64:
                rows.append({"latent": n, "form": form, "skipped": "N^2 matrices of 9216^2 x 4 heads exceed RAM"})
                continue
            mem = peak_rss_mb_of([__file__, "--child", form, str(n)])
            p = subprocess.run([sys.executable, __file__, "--child-time", form, str(n)], capture_output=True,
                               text=True, cwd=REPO)
            t = next((json.loads(ln[5:]) for ln in p.stdout.splitlines() if ln.startswith("TIME=")), None)
            row = {"latent": n, "form": form, "tokens": n * n, "peak_mb": mem.get("peak_mb"),
                   "before_mb": mem.get("before_mb"), "time": t, "error": mem.get("error")}
            if row["peak_mb"] is not None and row["before_mb"] is not None:
                row["extra_mb"] = row["peak_mb"] - row["before_mb"]
            rows.append(row)
            print(f"latent {n:3d}  {form:6s}  extra {row.get('extra_mb', float('nan')):8.1f} MB  "
                  f"median {t['median'] if t else float('nan'):.3f} s", flush=True)
    result = {"machine": machine_info(), "heads": HEADS, "head_dim": HEAD_DIM, "max_coc_latent_px": MAX_COC,
              "rows": rows}
    if not args.quick:
        result["pipelines"] = pipeline_times()
        print(json.dumps(result["pipelines"], indent=1))
        _plot(rows, args.plot)
    if not args.quick:  # the quick run is a smoke test: it prints, and keeps no file
        write_json(args.out, result)


def _plot(rows: list[dict], path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(9, 3.5), dpi=120)
    for form, style in (("dense", "o-"), ("windowed", "s-")):
        pts = [r for r in rows if r["form"] == form and r.get("extra_mb") is not None]
        axes[0].plot([r["latent"] for r in pts], [max(r["extra_mb"], 0.1) for r in pts], style, label=form)
        axes[1].plot([r["latent"] for r in pts], [r["time"]["median"] for r in pts], style, label=form)
    axes[0].set_ylabel("extra peak memory (MB)")
    axes[1].set_ylabel("forward time, median (s)")
    for ax in axes:
        ax.set_xlabel("latent side (tokens = side^2)")
        ax.set_yscale("log")
        ax.grid(alpha=0.3)
        ax.legend()
    fig.suptitle(f"PISA attention, {HEADS} heads x {HEAD_DIM}, max CoC {MAX_COC:g} latent px")
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)


if __name__ == "__main__":
    main()
