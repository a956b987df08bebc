"""End to end: ``bokehray render photo.jpg --disparity d.png -o out.jpg --stats`` with defaults at 1, 12 and 24 MP,
beside one FFT disc convolution of the same image (a fixed workload, measured in the same run).

Each size: the demo scene at that size written as a JPEG and a 16-bit PNG disparity; then three rounds of (one
scipy ``fftconvolve`` of the 3-channel float32 image with a disc of the render's largest CoC radius, in a fresh
process; the render, in a fresh process). Reported per size: medians of the three rounds of the render's wall
time, CPU time (user + system), system time, minor page faults, peak RSS (the child's VmHWM) and stage times
(``--stats``), the FFT's wall and CPU time, and the ratios render / FFT (wall and CPU). The machine is shared:
wall times follow its load (recorded); CPU times, faults and peak RSS hardly do.

Results go to ``benchmarks/results/photo--<machine>[--<label>].json``; ``--plot`` draws docs/img/photo_scaling.png
from the JSON files given.

Usage (from the repository root)::

    python benchmarks/photo/bench_photo.py                      # 1, 12 and 24 MP (about 10 minutes on 2 cores)
    python benchmarks/photo/bench_photo.py --sizes 1 --rounds 1 # a smoke test
    python benchmarks/photo/bench_photo.py --src OTHER/src:OTHER/kernels --label before  # another checkout's code (src_commit)
    python benchmarks/photo/bench_photo.py --plot benchmarks/results/photo--*.json
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from benchmarks import common

SIZES = {1: (1224, 816), 12: (4000, 3000), 24: (6000, 4000)}

RENDER = r"""
import json, resource, sys, time
t = time.perf_counter()
from bokehray.app.cli import main
rc = main(sys.argv[1:])
wall = time.perf_counter() - t
ru = resource.getrusage(resource.RUSAGE_SELF)
hwm = [int(l.split()[1]) for l in open("/proc/self/status") if l.startswith("VmHWM:")][0]
print("BENCH=" + json.dumps({"rc": rc, "wall_s": wall, "user_s": ru.ru_utime, "sys_s": ru.ru_stime,
                             "minor_faults": ru.ru_minflt, "peak_rss_mb": hwm / 1024}), flush=True)
"""

FFT = r"""
import json, resource, sys, time
import numpy as np
from scipy.signal import fftconvolve
from bokehray.photo.read import read_image
img = read_image(sys.argv[1])
r = float(sys.argv[2])
n = int(np.ceil(r))
y, x = np.mgrid[-n:n + 1, -n:n + 1]
disc = (x * x + y * y <= r * r).astype(np.float32)
disc /= disc.sum()
ru0 = resource.getrusage(resource.RUSAGE_SELF)
t = time.perf_counter()
out = np.stack([fftconvolve(img[..., c], disc, mode="same") for c in range(3)], axis=-1)
wall = time.perf_counter() - t
ru = resource.getrusage(resource.RUSAGE_SELF)
print("BENCH=" + json.dumps({"wall_s": wall, "cpu_s": ru.ru_utime + ru.ru_stime - ru0.ru_utime - ru0.ru_stime}))
"""


def _child(code: str, args: list[str], env: dict) -> tuple[dict, str]:
    p = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, env=env, timeout=1800)
    line = [ln for ln in p.stdout.splitlines() if ln.startswith("BENCH=")]
    if p.returncode != 0 or not line:
        raise RuntimeError(f"child failed ({p.returncode}): {p.stderr.strip()[-2000:]}")
    return json.loads(line[-1][6:]), p.stdout


def _stats_json(stdout: str) -> dict:
    text = "\n".join(ln for ln in stdout.splitlines() if not ln.startswith("BENCH="))
    return json.loads(text[text.index("{"):])


def bench_size(mp: int, rounds: int, env: dict, tmp: Path) -> dict:
    import bokehray as br
    from bokehray.app.demo import build_demo_scene

    w, h = SIZES[mp]
    scene = build_demo_scene(width=w, height=h)
    photo, disp = tmp / f"photo{mp}.jpg", tmp / f"d{mp}.png"
    br.write_image(photo, scene.image)
    br.write_disparity(disp, scene.disparity)
    del scene
    runs, ffts = [], []
    for _ in range(rounds):
        res, out = _child(RENDER, ["render", str(photo), "--disparity", str(disp), "-o", str(tmp / f"out{mp}.jpg"),
                                   "--stats", "--quiet"], env)
        res["stats"] = _stats_json(out)
        runs.append(res)
        fft, _ = _child(FFT, [str(photo), str(res["stats"]["max_coc_px"])], env)
        ffts.append(fft)

    def med(key, rows=runs):
        return statistics.median(r[key] for r in rows)

    stages = sorted({k for r in runs for k in r["stats"]["stage_seconds"]})
    row = {
        "megapixels": round(w * h / 1e6, 2), "shape": [h, w], "max_coc_px": runs[0]["stats"]["max_coc_px"],
        "layers": runs[0]["stats"]["layers"], "rounds": rounds,
        "wall_s": med("wall_s"), "cpu_s": statistics.median(r["user_s"] + r["sys_s"] for r in runs),
        "sys_s": med("sys_s"), "minor_faults": med("minor_faults"), "peak_rss_mb": med("peak_rss_mb"),
        "stage_s": {k: statistics.median(r["stats"]["stage_seconds"].get(k, 0.0) for r in runs) for k in stages},
        "fft_wall_s": med("wall_s", ffts), "fft_cpu_s": med("cpu_s", ffts),
        "runs": runs, "ffts": ffts,
    }
    row["ratio_wall"] = row["wall_s"] / row["fft_wall_s"]
    row["ratio_cpu"] = row["cpu_s"] / row["fft_cpu_s"]
    return row


def plot(paths: list[str], out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(13, 3.8))
    for p in paths:
        data = json.loads(Path(p).read_text())
        label = data.get("label") or Path(p).stem
        rows = data["rows"]
        mp = [r["megapixels"] for r in rows]
        axes[0].plot(mp, [r["cpu_s"] for r in rows], "o-", label=f"{label}: render CPU")
        axes[0].plot(mp, [r["fft_cpu_s"] for r in rows], "x--", label=f"{label}: one FFT disc convolution")
        axes[1].plot(mp, [r["ratio_cpu"] for r in rows], "o-", label=f"{label} (CPU)")
        axes[1].plot(mp, [r["ratio_wall"] for r in rows], "s:", label=f"{label} (wall)")
        axes[2].plot(mp, [r["peak_rss_mb"] / 1024 for r in rows], "o-", label=label)
    axes[0].set(xlabel="megapixels", ylabel="seconds (user + system)", title="CPU time, end to end")
    axes[1].set(xlabel="megapixels", ylabel="render / FFT", title="ratio to one FFT disc convolution")
    axes[1].axhline(6, color="grey", lw=0.8, ls="--")
    axes[2].set(xlabel="megapixels", ylabel="GB", title="peak RSS")
    axes[2].plot([12, 24], [1.5, 3.0], "k_", ms=20, label="target")
    for a in axes:
        a.grid(alpha=0.3)
        a.legend(fontsize=7)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    print(f"wrote {out}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[1, 12, 24], choices=sorted(SIZES))
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--src", default=None, help="PYTHONPATH of the code to render with (default: this checkout)")
    ap.add_argument("--label", default="")
    ap.add_argument("--plot", nargs="+", default=None, help="JSON results to plot (no benchmark run)")
    a = ap.parse_args()
    if a.plot:
        plot(a.plot, common.REPO / "docs" / "img" / "photo_scaling.png")
        return
    env = dict(os.environ)
    if a.src:
        env["PYTHONPATH"] = a.src
    info = common.machine_info()
    if a.src:  # the code measured is --src's, not this checkout's (machine_info's git_commit)
        info["src_commit"] = common.git_commit(Path(a.src.split(os.pathsep)[0]).resolve())
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for mp in a.sizes:
            t = time.perf_counter()
            rows.append(bench_size(mp, a.rounds, env, Path(tmp)))
            r = rows[-1]
            print(f"{r['megapixels']:5.1f} MP: wall {r['wall_s']:6.2f} s, CPU {r['cpu_s']:6.2f} s (sys {r['sys_s']:5.2f}), "
                  f"faults {r['minor_faults'] / 1e6:5.2f} M, peak {r['peak_rss_mb']:6.0f} MB | FFT wall "
                  f"{r['fft_wall_s']:5.2f} s, CPU {r['fft_cpu_s']:5.2f} s | ratio wall {r['ratio_wall']:5.1f}, "
                  f"CPU {r['ratio_cpu']:5.1f} | stages {', '.join(f'{k} {v:.2f}' for k, v in r['stage_s'].items())}"
                  f"  [{time.perf_counter() - t:.0f} s]", flush=True)
    info["load_after"] = os.getloadavg()
    tag = common.machine_tag(info) + (f"--{a.label}" if a.label else "")
    path = common.write_json(common.REPO / "benchmarks" / "results" / f"photo--{tag}.json",
                             {"machine": info, "label": a.label or "this checkout", "src": a.src, "rows": rows})
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
