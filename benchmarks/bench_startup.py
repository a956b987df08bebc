"""Whole-process start-up cost of the command line: ``--help``, an argument error, a flag conflict, and a 1 MP
preview render end to end (read PNG + 16-bit disparity PNG, render, write PNG) with warm caches.

Every figure is the median of ``--runs`` warm runs of a fresh ``python`` process (after one untimed warm-up that
fills the OS file cache and Warp's kernel cache), next to ``python -c pass`` measured in the same run, interleaved
with the others, so that a busy machine shows as a larger baseline rather than as a slower bokehray.
Targets (issue 15): ``--help`` and argument errors <= 0.5 s, the 1 MP preview <= 1.5 s.

Usage (from the repository root)::

    python benchmarks/bench_startup.py              # 7 runs each, JSON to benchmarks/results/startup.json
    python benchmarks/bench_startup.py --runs 3 --out /tmp
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

REPO = Path(__file__).resolve().parent.parent
TARGETS_S = {"help": 0.5, "render_help": 0.5, "usage_error": 0.5, "flag_conflict": 0.5, "preview_1mp": 1.5}
CLI = "import sys; from bokehray.cli import main; sys.exit(main())"


def _env() -> dict[str, str]:
    env = dict(os.environ)
    paths = [str(REPO / "src"), str(REPO / "kernels"), str(REPO / "refiner")]
    env["PYTHONPATH"] = os.pathsep.join(paths + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else []))
    return env


def _once(argv: list[str], env: dict[str, str], expect: int) -> float:
    t = time.perf_counter()
    p = subprocess.run([sys.executable, *argv], env=env, capture_output=True, text=True, cwd=REPO)
    dt = time.perf_counter() - t
    if p.returncode != expect:
        raise SystemExit(f"{argv[-6:]}: exit {p.returncode}, expected {expect}: {p.stderr.strip()[-400:]}")
    return dt


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=7)
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results"))
    args = ap.parse_args()
    env = _env()
    with tempfile.TemporaryDirectory() as tmp:
        setup = (f"import bokehray as br; from bokehray.demo import build_demo_scene; s = build_demo_scene(width=1224, "
                 f"height=816); br.write_image({tmp!r} + '/in.png', s.image); "
                 f"br.write_disparity({tmp!r} + '/d.png', s.disparity)")
        subprocess.run([sys.executable, "-c", setup], env=env, check=True, cwd=REPO)
        render = ["render", f"{tmp}/in.png", "--disparity", f"{tmp}/d.png", "-o", f"{tmp}/out.png", "--quiet"]
        cases = {
            "python_pass": (["-c", "pass"], 0),
            "help": (["-c", CLI, "--help"], 0),
            "render_help": (["-c", CLI, "render", "--help"], 0),
            "usage_error": (["-c", CLI, "render", f"{tmp}/in.png", "-o", f"{tmp}/x.png"], 2),
            "flag_conflict": (["-c", CLI, *render[:-1], "--focus", "0.5", "--focus-at", "3,4"], 2),
            "preview_1mp": (["-c", CLI, *render], 0),
        }
        times: dict[str, list[float]] = {k: [] for k in cases}
        for argv, expect in cases.values():  # warm-up: file cache, Warp kernel cache
            _once(argv, env, expect)
        for _ in range(args.runs):
            for name, (argv, expect) in cases.items():
                times[name].append(_once(argv, env, expect))
    base = statistics.median(times["python_pass"])
    result = {
        "what": "whole-process seconds, median of warm runs; ratio = median / median of `python -c pass`",
        "runs": args.runs,
        "python": sys.version.split()[0],
        "cores": os.cpu_count(),
        "load_average": os.getloadavg(),
        "cases": {
            name: {"median_s": round(statistics.median(t), 4), "min_s": round(min(t), 4), "max_s": round(max(t), 4),
                   "ratio_to_python_pass": round(statistics.median(t) / base, 2),
                   **({"target_s": TARGETS_S[name], "meets_target": statistics.median(t) <= TARGETS_S[name]}
                      if name in TARGETS_S else {})}
            for name, t in times.items()
        },
    }
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "startup.json").write_text(json.dumps(result, indent=2) + "\n")
    for name, c in result["cases"].items():
        target = f"  target {c['target_s']} s: {'ok' if c['meets_target'] else 'MISSED'}" if "target_s" in c else ""
        print(f"{name:<14} {c['median_s']:7.3f} s  (min {c['min_s']:.3f}, x{c['ratio_to_python_pass']:.1f} python)"
              f"{target}")
    print(f"wrote {out / 'startup.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
