"""Batch work through the executor seam: the in-process path, the local pool and Dask with the same workers.

Measures, on this machine (docs/scale.md):

* the cost of the engine per task: ``R`` no-op tasks (``abs``) through each executor, wall time / ``R``;
* ``bokehray synth`` throughput in scenes per minute (the ``generate_one`` tasks that ``generate`` runs);
* batch-render throughput in megapixels per second (the ``render_file`` tasks of ``bokehray render DIR``);
* the start-up cost of each executor (pool or cluster up, every worker warm) and the bytes one scene takes.

The executors are started once, warmed up (every worker has imported bokehray and initialised Warp), and then
timed round-robin, so a burst of load from other processes on a shared machine hits all of them alike. The
in-process path (``local``, one worker) is the fixed reference workload: the pool and Dask are reported as speed-ups
over it measured in the same rounds.

Usage (from the repository root)::

    python benchmarks/scale/bench_scale.py [--quick] [--workers 2] [--out benchmarks/results] [--plots docs/img]
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import numpy as np

import bokehray as br
from benchmarks import common
from bokehray.app.batch import RenderSettings, RenderTask, render_file
from bokehray.data.synth import SynthConfig, generate_one
from bokehray.executor import make_executor


def _cpu_seconds() -> float:
    """CPU time of this process and every live descendant (pool workers, Dask nannies and workers)."""
    import psutil

    total = 0.0
    me = psutil.Process()
    for p in [me, *me.children(recursive=True)]:
        try:
            t = p.cpu_times()
            total += t.user + t.system
        except psutil.Error:  # ended meanwhile
            pass
    return total


def _drain(ex, fn, tasks, cpu: list | None = None) -> float:
    """Wall seconds of running ``tasks``; appends the CPU seconds they got (all processes) to ``cpu``."""
    c, t = _cpu_seconds(), time.perf_counter()
    bad = [o.error for o in ex.map(fn, tasks) if not o.ok]
    if bad:
        raise RuntimeError(f"{ex.describe()}: {bad[0]}")
    wall = time.perf_counter() - t
    if cpu is not None:
        cpu.append(_cpu_seconds() - c)
    return wall


def _bytes(folder: Path) -> dict:
    files = [f for f in folder.rglob("*") if f.is_file()]
    by_ext: dict[str, int] = {}
    for f in files:
        by_ext[f.suffix] = by_ext.get(f.suffix, 0) + f.stat().st_size
    return {"total": sum(by_ext.values()), "by_extension": by_ext, "files": len(files)}


def photos(folder: Path, n: int, width: int, height: int) -> tuple[list[tuple[Path, Path]], float, float]:
    from bokehray.app.demo import build_demo_scene

    scene = build_demo_scene(width=width, height=height)
    pairs = []
    for i in range(n):  # shifted copies: different pixels, the same work
        img, d = np.roll(scene.image, 37 * i, axis=1), np.roll(scene.disparity, 37 * i, axis=1)
        pairs.append((br.write_image(folder / f"photo_{i:03d}.exr", img),
                      br.write_disparity(folder / f"photo_{i:03d}_disp.png", d)))
    return pairs, scene.k_px, scene.focus_near


def main() -> int:  # noqa: C901
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="small sizes, one round")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--rounds", type=int, default=None, help="timed rounds per executor (default 2, quick 1)")
    ap.add_argument("--default-scenes", type=int, default=None,
                    help="512 px default scenes timed in this process (default 3, quick 1)")
    ap.add_argument("--plot-only", metavar="JSON", help="redraw the plot of an earlier result and stop")
    ap.add_argument("--out", default=str(common.REPO / "benchmarks" / "results"))
    ap.add_argument("--plots", default=str(common.REPO / "docs" / "img"))
    args = ap.parse_args()
    if args.plot_only:
        import json

        _plot(json.loads(Path(args.plot_only).read_text()), Path(args.plots) / "scale_throughput.png")
        return 0
    rounds = args.rounds or (1 if args.quick else 2)
    args.default_scenes = args.default_scenes or (1 if args.quick else 3)
    w = args.workers
    synth_n, synth_size = (4, 128) if args.quick else (8, 256)
    photo_n, (pw, ph) = (4, (512, 341)) if args.quick else (8, (1024, 683))
    noop_n = 200 if args.quick else 1000
    from bokehray._quiet import init_warp_quietly

    init_warp_quietly()
    tmp = Path(tempfile.mkdtemp(prefix="bokehray-scale-"))
    result: dict = {"machine": common.machine_info(), "workers": w, "rounds": rounds,
                    "load_average_before": os.getloadavg()}
    try:
        pairs, k, d_f = photos(tmp / "photos", photo_n, pw, ph)
        from bokehray.app.cli import build_parser

        settings = RenderSettings.from_args(build_parser().parse_args(
            ["render", "IMAGE", "--disparity", "MAP", "-o", "OUT.png", "--blur", str(k), "--focus", str(d_f),
             "--no-highlight-reconstruction"]))
        cfg = SynthConfig(size=synth_size)
        kinds = {"inline": ("local", 1), f"local-{w}": ("local", w), f"dask-{w}": ("dask", w)}
        exs, startup = {}, {}
        for name, (kind, n) in kinds.items():
            t = time.perf_counter()
            ex = make_executor(kind, workers=n)
            ex.__enter__()
            # warm: every worker imports bokehray and initialises Warp before the clock starts
            _drain(ex, render_file, [RenderTask(str(pairs[0][0]), str(pairs[0][1]),
                                                str(tmp / "warm" / f"{name}-{i}.png"), settings) for i in range(n)])
            startup[name] = time.perf_counter() - t
            exs[name] = ex
            print(f"{ex.describe()}: up and warm in {startup[name]:.1f} s", flush=True)
        result["startup_seconds"] = startup
        times: dict[str, dict[str, list[float]]] = {name: {"noop": [], "synth": [], "render": []} for name in exs}
        cpu: dict[str, dict[str, list[float]]] = {name: {"noop": [], "synth": [], "render": []} for name in exs}
        for r in range(rounds):
            for name, ex in exs.items():
                times[name]["noop"].append(_drain(ex, abs, list(range(noop_n)), cpu[name]["noop"]))
                out = tmp / f"synth-{name}-{r}"
                jobs = [(cfg, 0, i, str(out), True) for i in range(synth_n)]
                times[name]["synth"].append(_drain(ex, generate_one, jobs, cpu[name]["synth"]))
                if r == 0 and name == "inline":
                    result["synth_bytes_per_scene"] = {synth_size: _bytes(out)["total"] / synth_n}
                shutil.rmtree(out)
                # as bokehray render does: the workers of a pool share the cores (preview threads)
                share = replace(settings, threads=max(1, (os.cpu_count() or 1) // ex.workers)) if ex.workers > 1 \
                    else settings
                tasks = [RenderTask(str(img), str(dp), str(tmp / f"render-{name}-{r}" / f"{img.stem}.exr"), share)
                         for img, dp in pairs]
                times[name]["render"].append(_drain(ex, render_file, tasks, cpu[name]["render"]))
                shutil.rmtree(tmp / f"render-{name}-{r}")
                print(f"round {r + 1}/{rounds} {name}: noop {times[name]['noop'][-1]:.2f} s, "
                      f"synth {times[name]['synth'][-1]:.1f} s, render {times[name]['render'][-1]:.1f} s", flush=True)
        for ex in exs.values():
            ex.close()
        mp = photo_n * pw * ph / 1e6
        rows = {}
        for name, t in times.items():
            med = {k: statistics.median(v) for k, v in t.items()}
            med_cpu = {k: statistics.median(v) for k, v in cpu[name].items()}
            rows[name] = {
                "noop_us_per_task": med["noop"] / noop_n * 1e6,
                "noop_cpu_us_per_task": med_cpu["noop"] / noop_n * 1e6,
                # cores this executor got: CPU seconds of all its processes / wall seconds (the rest went to others)
                "synth_cores_used": med_cpu["synth"] / med["synth"],
                "render_cores_used": med_cpu["render"] / med["render"],
                "synth_cpu_seconds_per_scene": med_cpu["synth"] / synth_n,
                "render_cpu_seconds_per_mp": med_cpu["render"] / (photo_n * pw * ph / 1e6),
                "cpu_seconds": cpu[name],
                "synth_scenes_per_minute": synth_n / med["synth"] * 60,
                "render_mp_per_second": mp / med["render"],
                "seconds": t,
            }
        ref = rows["inline"]
        for row in rows.values():
            row["synth_speedup_vs_inline"] = row["synth_scenes_per_minute"] / ref["synth_scenes_per_minute"]
            row["render_speedup_vs_inline"] = row["render_mp_per_second"] / ref["render_mp_per_second"]
        result["executors"] = rows
        result["workload"] = {"synth": {"scenes": synth_n, "size": synth_size, "blur_levels": list(cfg.blur_levels),
                                        "max_spp": cfg.max_spp, "targets_per_scene": 2 * len(cfg.blur_levels)},
                              "render": {"photos": photo_n, "size": [pw, ph], "quality": "preview", "k_px": k,
                                         "output": "exr"},
                              "noop_tasks": noop_n}
        # scenes at the default size (512 px, K 10/20/30, 64 spp), in this process: time and bytes (EXR + PNG)
        out = tmp / "default-scene"
        secs, cpus = [], []
        for i in range(args.default_scenes):
            c, t = time.process_time(), time.perf_counter()
            generate_one((SynthConfig(), 0, i, str(out), True))
            secs.append(time.perf_counter() - t)
            cpus.append(time.process_time() - c)
        result["default_scene_seconds_inline"] = secs
        result["default_scene_cpu_seconds_inline"] = cpus
        result["synth_bytes_per_scene"][512] = {k: v / args.default_scenes if k != "by_extension" else
                                                {e: b / args.default_scenes for e, b in v.items()}
                                                for k, v in _bytes(out).items()}
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    result["load_average_after"] = os.getloadavg()  # other processes on a shared machine take their share
    tag = "quick" if args.quick else common.machine_tag(result["machine"])
    path = common.write_json(Path(args.out) / f"scale--{tag}.json", result)
    print(f"wrote {path}")
    _plot(result, Path(args.plots) / ("scale_throughput_quick.png" if args.quick else "scale_throughput.png"))
    for name, row in result["executors"].items():
        print(f"{name:8s} {row['noop_us_per_task']:8.0f} us/task  {row['synth_scenes_per_minute']:6.2f} scenes/min "
              f"(x{row['synth_speedup_vs_inline']:.2f}, {row['synth_cores_used']:.2f} cores, "
              f"{row['synth_cpu_seconds_per_scene']:.1f} CPU s/scene)  {row['render_mp_per_second']:6.3f} MP/s "
              f"(x{row['render_speedup_vs_inline']:.2f}, {row['render_cores_used']:.2f} cores, "
              f"{row['render_cpu_seconds_per_mp']:.2f} CPU s/MP)")
    return 0


def _plot(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = result["executors"]
    names = list(rows)
    fig, axes = plt.subplots(1, 4, figsize=(14, 3.3))
    for ax, key, title in zip(axes, ("synth_scenes_per_minute", "render_mp_per_second", "synth_cpu_seconds_per_scene",
                                     "noop_us_per_task"),
                              ("synth: scenes / min (wall)", "batch render: MP / s (wall)",
                               "synth: CPU s / scene (all processes)", "engine cost: us / no-op task")):
        vals = [rows[n][key] for n in names]
        ax.bar(names, vals, color=["#888", "#4a7", "#47a"])
        ax.set_title(title, fontsize=10)
        for i, v in enumerate(vals):
            ax.text(i, v, f"{v:.3g}", ha="center", va="bottom", fontsize=9)
        ax.set_yscale("log" if key == "noop_us_per_task" else "linear")
    wl = result["workload"]
    cores = ", ".join(f"{n} {rows[n]['synth_cores_used']:.2f}" for n in names)
    fig.suptitle(f"{result['machine']['cores']} cores shared (cores this run got in synth: {cores}); synth {wl['synth']['scenes']} x {wl['synth']['size']} px, "
                 f"render {wl['render']['photos']} x {wl['render']['size'][0]}x{wl['render']['size'][1]} preview",
                 fontsize=10)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    print(f"wrote {path}")


if __name__ == "__main__":
    sys.exit(main())
