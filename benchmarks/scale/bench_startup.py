"""Whole-process start-up cost of the command line: ``--help``, an argument error, a flag conflict, and a 1 MP
preview render end to end (read PNG + 16-bit disparity PNG, render, write PNG) with warm caches.

Every figure is the median of ``--runs`` warm runs of a fresh ``python`` process (after one untimed warm-up that
fills the OS file cache and Warp's kernel cache), next to ``python -c pass`` measured in the same run, interleaved
with the others, so that a busy machine shows as a larger baseline rather than as a slower bokehray.
Targets: ``--help`` and argument errors <= 0.5 s, the 1 MP preview <= 1.5 s.

Usage (from the repository root)::

    python benchmarks/scale/bench_startup.py              # 7 runs each, JSON to benchmarks/results/startup.json
    python benchmarks/scale/bench_startup.py --runs 3 --out /tmp
    git archive 4306d6f | tar -x -C /tmp/before && python benchmarks/scale/bench_startup.py --baseline /tmp/before
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

REPO = Path(__file__).resolve().parents[2]
TARGETS_S = {"help": 0.5, "render_help": 0.5, "usage_error": 0.5, "flag_conflict": 0.5, "preview_1mp": 1.5,
             "preview_1mp_explicit": 1.5}
CLI = "import sys; from bokehray.app.cli import main; sys.exit(main())"


def _env(repo: Path) -> dict[str, str]:
    env = dict(os.environ)
    paths = [str(repo / "src"), str(repo / "kernels"), str(repo / "refiner")]
    env["PYTHONPATH"] = os.pathsep.join(paths + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else []))
    return env


def _once(argv: list[str], env: dict[str, str], expect: int) -> float:
    t = time.perf_counter()
    p = subprocess.run([sys.executable, *argv], env=env, capture_output=True, text=True, cwd=REPO)
    dt = time.perf_counter() - t
    if p.returncode != expect:
        raise SystemExit(f"{argv[-6:]}: exit {p.returncode}, expected {expect}: {p.stderr.strip()[-400:]}")
    return dt


def _cases(tmp: str, defaults: bool) -> dict[str, tuple[list[str], int]]:
    render = ["render", f"{tmp}/in.png", "--disparity", f"{tmp}/d.png", "-o", f"{tmp}/out.png", "--quiet"]
    cases = {
        "help": (["-c", CLI, "--help"], 0),
        "render_help": (["-c", CLI, "render", "--help"], 0),
        "usage_error": (["-c", CLI, "render", f"{tmp}/in.png", "-o", f"{tmp}/x.png"], 2),
        "flag_conflict": (["-c", CLI, *render, "--focus", "0.5", "--focus-at", "3,4"], 2),
        "preview_1mp_explicit": (["-c", CLI, *render, "--blur", "44.13", "--focus", "0.892"], 0),
    }
    if defaults:  # the defaults: subject focus, highlight reconstruction (an older checkout may have none)
        cases["preview_1mp"] = (["-c", CLI, *render], 0)
    return cases


def _summary(times: dict[str, list[float]], base: float) -> dict:
    return {
        name: {"median_s": round(statistics.median(t), 4), "min_s": round(min(t), 4), "max_s": round(max(t), 4),
               "ratio_to_python_pass": round(statistics.median(t) / base, 2),
               **({"target_s": TARGETS_S[name], "meets_target": statistics.median(t) <= TARGETS_S[name]}
                  if name in TARGETS_S else {})}
        for name, t in times.items()
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=7)
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results"))
    ap.add_argument("--baseline", type=Path,
                    help="also measure another checkout, interleaved in the same run (e.g. the commit before issue "
                    "15, exported with `git archive REV | tar -x -C DIR`)")
    args = ap.parse_args()
    checkouts = {"this": REPO} | ({"baseline": args.baseline.resolve()} if args.baseline else {})
    envs = {k: _env(v) for k, v in checkouts.items()}
    with tempfile.TemporaryDirectory() as tmp:
        setup = (f"import bokehray as br; from bokehray.app.demo import build_demo_scene; s = build_demo_scene(width=1224, "
                 f"height=816); br.write_image({tmp!r} + '/in.png', s.image); "
                 f"br.write_disparity({tmp!r} + '/d.png', s.disparity)")
        subprocess.run([sys.executable, "-c", setup], env=envs["this"], check=True, cwd=REPO)
        plan = [("python_pass", "this", ["-c", "pass"], 0)]
        for who in checkouts:
            plan += [(name, who, argv, expect) for name, (argv, expect) in _cases(tmp, who == "this").items()]
        times: dict[tuple[str, str], list[float]] = {(n, w): [] for n, w, _, _ in plan}
        for _, who, argv, expect in plan:  # warm-up: file cache, Warp kernel cache
            _once(argv, envs[who], expect)
        for _ in range(args.runs):
            for name, who, argv, expect in plan:
                times[(name, who)].append(_once(argv, envs[who], expect))
    base = statistics.median(times[("python_pass", "this")])
    result = {
        "what": "whole-process seconds, median of warm runs; ratio = median / median of `python -c pass`, all "
                "measured interleaved in the same run",
        "runs": args.runs,
        "python": sys.version.split()[0],
        "cores": os.cpu_count(),
        "load_average": os.getloadavg(),
        "checkouts": {k: str(v) for k, v in checkouts.items()},
    }
    for who in checkouts:
        result[who] = _summary({n: t for (n, w), t in times.items() if w == who or n == "python_pass"}, base)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "startup.json").write_text(json.dumps(result, indent=2) + "\n")
    for who in checkouts:
        print(f"[{who}] {checkouts[who]}")
        for name, c in result[who].items():
            target = f"  target {c['target_s']} s: {'ok' if c['meets_target'] else 'MISSED'}" if "target_s" in c else ""
            print(f"  {name:<21} {c['median_s']:7.3f} s  (min {c['min_s']:.3f}, x{c['ratio_to_python_pass']:.1f} "
                  f"python){target}")
    print(f"wrote {out / 'startup.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
