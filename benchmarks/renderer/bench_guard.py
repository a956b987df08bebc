"""The guard against a silent slowdown: the preview's speed as ratios to fixed workloads measured in the same run,
beside the committed baseline (``benchmarks/results/baseline.json``); a figure more than 15 % worse prints
REGRESSION. A print, not a failing test: CI may run on a busy machine.

Figures:

* ``t32/tFFT``: the demo scene at 1536 x 1024 focused near, largest CoC 32 px, over one scipy FFT convolution of
  the same 3-channel image with a 65 x 65 disc (medians of interleaved warm runs, as ``shared/tools/speed_ratio.py``);
* ``t128/t16``: the same render at 128 px over 16 px (the radius pyramid's flat cost);
* ``12 MP``: the demo upscaled to 4000 x 3000 with its map blurred by a Gaussian of 6 px (a soft map, as a depth
  model gives), default blur (``--amount 50``) and focus (the subject): each stage of ``render_with_stats`` and the
  whole over one FFT convolution of that image with a disc of its largest CoC (one warm run: a smoke figure).

Usage (from the repository root)::

    python benchmarks/renderer/bench_guard.py                   # measure, compare with the baseline
    python benchmarks/renderer/bench_guard.py --no-12mp         # the two 1.5 MP ratios only (half a minute)
    python benchmarks/renderer/bench_guard.py --write-baseline  # measure and make it the baseline
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import numpy as np
from scipy import ndimage
from scipy.signal import fftconvolve

import bokehray as br
from benchmarks import common
from bokehray.app.demo import build_demo_scene

BASELINE = Path(__file__).resolve().parents[1] / "results" / "baseline.json"
WORSE = 1.15
"""A figure this many times its baseline (or more) is a REGRESSION."""
STAGE_FLOOR = 0.2
"""... and for a 12 MP stage, also at least this many FFTs more (a stage of 0.3 FFTs moved by 0.1 on a busy machine
in a fresh-clone CI run: noise, not a slowdown)."""


def _disc(r: float) -> np.ndarray:
    n = int(np.ceil(r))
    y, x = np.mgrid[-n : n + 1, -n : n + 1]
    d = (x * x + y * y <= r * r).astype(np.float32)
    return d / d.sum()


def _fft(img: np.ndarray, kernel: np.ndarray) -> float:
    t = time.perf_counter()
    for c in range(3):
        fftconvolve(img[..., c], kernel, mode="same")
    return time.perf_counter() - t


def preview_ratios(runs: int) -> dict:
    """t32/tFFT and t128/t16 on the 1536 x 1024 demo, medians of ``runs`` interleaved warm runs."""
    sc = build_demo_scene(1536, 1024)
    img, d, f = sc.image, sc.disparity, float(sc.focus_near)
    span = max(float(np.abs(d - f).max()), 1e-6)
    disc = _disc(32)
    jobs = {r: (lambda r=r: br.render(img, d, br.BlurParams(r / span, f))) for r in (16, 32, 128)}
    jobs["fft"] = lambda: _fft(img, disc)
    for job in jobs.values():
        job()
    times = {k: [] for k in jobs}
    for _ in range(runs):
        for k, job in jobs.items():
            t = time.perf_counter()
            job()
            times[k].append(time.perf_counter() - t)
    m = {k: float(np.median(v)) for k, v in times.items()}
    return {"t16_s": m[16], "t32_s": m[32], "t128_s": m[128], "fft_s": m["fft"],
            "t32/tFFT": m[32] / m["fft"], "t128/t16": m[128] / m[16]}


def photo_12mp() -> dict:
    """The 12 MP soft-map render's stages over one FFT of the image with a disc of its largest CoC."""
    from bokehray.photo.subject import k_from_amount, subject_focus

    sc = build_demo_scene(1500, 1000)
    z = (3000 / 1000, 4000 / 1500)
    img = np.clip(ndimage.zoom(sc.image, (*z, 1), order=1), 0, None).astype(np.float32)
    d = np.clip(ndimage.gaussian_filter(ndimage.zoom(sc.disparity, z, order=0), 6.0), 0, 1).astype(np.float32)
    blur = br.BlurParams(k_from_amount(50.0, *d.shape), subject_focus(d).d_f)
    br.render(img[:256, :256], d[:256, :256], blur)  # the kernels compiled and loaded
    _, stats = br.render_with_stats(img, d, blur)
    fft = _fft(img, _disc(min(stats.max_coc_px, 256.0)))
    out = {f"12MP {k}/tFFT": v / fft for k, v in stats.stage_seconds.items()}
    out.update({"12MP fft_s": fft, "12MP stage_s": stats.stage_seconds, "12MP max_coc_px": stats.max_coc_px})
    return out


def compare(now: dict, base: dict | None) -> list[str]:
    """The table's lines: each ratio beside its baseline, REGRESSION where it is ``WORSE`` times it or more."""
    lines = [f"{'figure':28s} {'now':>9s} {'baseline':>9s}"]
    for k, v in now.items():
        if "/" not in k or not isinstance(v, float):
            continue
        b = None if base is None else base.get("figures", {}).get(k)
        floor = STAGE_FLOOR if k.startswith("12MP") else 0.0  # a stage of a fraction of an FFT is noise-bound
        mark = "" if b is None else ("  REGRESSION" if v >= WORSE * b and v - b > floor else "")
        lines.append(f"{k:28s} {v:9.2f} {'-' if b is None else f'{b:9.2f}':>9s}{mark}")
    return lines


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--no-12mp", action="store_true", help="the two 1.5 MP ratios only")
    ap.add_argument("--write-baseline", action="store_true", help="make this run the baseline")
    args = ap.parse_args()
    figures = preview_ratios(args.runs)
    if not args.no_12mp:
        figures.update(photo_12mp())
    base = json.loads(BASELINE.read_text()) if BASELINE.exists() else None
    info = common.machine_info()
    load = os.getloadavg()[0]
    print(f"preview guard on {common.machine_tag(info)}, load {load:.1f} on {os.cpu_count()} cores "
          f"(compare only runs below a load of {os.cpu_count()})")
    print("\n".join(compare(figures, base)))
    if args.write_baseline:
        BASELINE.write_text(json.dumps({"machine": info, "figures": figures}, indent=1) + "\n")
        print(f"wrote {BASELINE}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
