"""The preview's time on the demo scene, this checkout against another one, in alternating fresh processes.

Each round runs one fresh ``python`` per checkout and radius (this, then the other, then the next radius): it
builds the demo scene at 1536 x 1024 focused near, renders once to warm up, then times ``--renders`` renders and
one scipy FFT convolution of one channel with a 65 x 65 disc (a fixed workload: a busy machine shows as a slower
FFT too). The figures are medians over the rounds of each process's median, and their ratio, so slow drifts of
a shared machine hit both checkouts alike.

Usage (from the repository root)::

    git worktree add --detach /tmp/before REV      # or: git archive REV | tar -x -C /tmp/before
    python benchmarks/renderer/bench_against.py /tmp/before --radii 16,32,128 --rounds 5
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]

CHILD = r"""
import json, statistics, sys, time
import numpy as np, scipy.signal
import bokehray
from bokehray.app.demo import build_demo_scene
radius, renders = float(sys.argv[1]), int(sys.argv[2])
scene = build_demo_scene(1536, 1024)
f = scene.focus_near
blur = bokehray.BlurParams(k_px=radius / float(np.abs(scene.disparity - f).max()), focus_disparity=f)
yy, xx = np.mgrid[-32:33, -32:33]
disc = ((xx ** 2 + yy ** 2) <= 32 ** 2).astype(np.float32)
disc /= disc.sum()
chan = np.ascontiguousarray(scene.image[..., 0])
def median_time(fn):
    fn()
    ts = []
    for _ in range(renders):
        t = time.perf_counter(); fn(); ts.append(time.perf_counter() - t)
    return statistics.median(ts)
fft = median_time(lambda: scipy.signal.fftconvolve(chan, disc, mode="same"))
render = median_time(lambda: bokehray.render(scene.image, scene.disparity, blur, quality="preview"))
print(json.dumps({"render_s": render, "fft_s": fft}))
"""


def _run(checkout: Path, radius: float, renders: int) -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(str(checkout / p) for p in ("src", "kernels", "refiner"))
    out = subprocess.run([sys.executable, "-c", CHILD, str(radius), str(renders)], env=env, capture_output=True,
                         text=True, check=True, cwd=checkout).stdout
    return json.loads(out.strip().splitlines()[-1])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("baseline", type=Path, help="the other checkout (its src/ and kernels/ are imported)")
    ap.add_argument("--radii", default="16,32,128", help="largest CoC radii [px], comma-separated")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--renders", type=int, default=5, help="timed renders per process (median)")
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "preview_against.json")
    args = ap.parse_args()
    radii = [float(r) for r in args.radii.split(",")]
    who = {"this": REPO, "baseline": args.baseline.resolve()}
    runs = {(w, r): [] for w in who for r in radii}
    for i in range(args.rounds):
        for r in radii:
            for w, path in who.items():
                runs[(w, r)].append(_run(path, r, args.renders))
        print(f"round {i + 1}/{args.rounds} done", file=sys.stderr, flush=True)
    rows = []
    for r in radii:
        row = {"radius": r}
        for w in who:
            row[w] = {"median_s": statistics.median(x["render_s"] for x in runs[(w, r)]),
                      "over_fft": statistics.median(x["render_s"] / x["fft_s"] for x in runs[(w, r)]),
                      "runs_s": [x["render_s"] for x in runs[(w, r)]]}
        row["this_over_baseline"] = row["this"]["median_s"] / row["baseline"]["median_s"]
        rows.append(row)
        print(f"R={r:g}: this {row['this']['median_s']:.3f} s ({row['this']['over_fft']:.1f}x fft), baseline "
              f"{row['baseline']['median_s']:.3f} s ({row['baseline']['over_fft']:.1f}x fft), ratio "
              f"{row['this_over_baseline']:.2f}")
    result = {"what": "demo 1536 x 1024 focused near, preview defaults; medians over rounds of alternating fresh "
                      "processes", "rounds": args.rounds, "renders": args.renders, "cores": os.cpu_count(),
              "load_average": os.getloadavg(), "checkouts": {k: str(v) for k, v in who.items()}, "rows": rows}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
