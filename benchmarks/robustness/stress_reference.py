"""Worst error of the Warp kernels against their float64 NumPy references over many random extreme cases.

Cases (tests/reference/stress_cases.py): level-0 scatter of sources of any radius (0, sub-pixel,
exactly 0.5, far beyond the image) and sign with every aperture; the layered preview (random,
one-pixel steps, edges, constant, all-0 and all-1 disparity; K 0 to 25; d_f 0, 1 or random);
the ray tracer on plane layers (alpha exactly 0 and 1, hard alpha edges, layers at identical
depth, 1 to 7 rays). Radiance scales 0, 1e-40 (float32 denormal), 1e-8, 1, 1e4. Reports the
worst relative error per kernel, separately for normal and denormal radiance, with a reproducer.

Usage (from the repository root)::

    python benchmarks/robustness/stress_reference.py --cases 1000 --out benchmarks/results
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

import warp as wp  # noqa: E402
from reference import stress_cases  # noqa: E402

from benchmarks import common  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=1000, help="cases per kernel")
    ap.add_argument("--seed", type=int, default=0, help="first seed (case i uses seed + i)")
    ap.add_argument("--out", type=Path, help="folder for stress-reference.json")
    args = ap.parse_args()
    wp.config.log_level = wp.LOG_WARNING
    report = {"machine": common.machine_info(), "cases_per_kernel": args.cases, "kernels": {}}
    for name, case in stress_cases.CASES.items():
        t0 = time.perf_counter()
        worst = {"normal": (0.0, None, ""), "denormal": (0.0, None, "")}
        for i in range(args.cases):
            seed = args.seed + i
            err, scale, desc = case(seed)
            key = "denormal" if 0.0 < scale < 1e-37 else "normal"
            if err > worst[key][0] or worst[key][1] is None:
                worst[key] = (err, seed, desc)
        report["kernels"][name] = {k: {"worst_rel_error": e, "seed": s, "case": d} for k, (e, s, d) in worst.items()}
        report["kernels"][name]["seconds"] = round(time.perf_counter() - t0, 1)
        for k, (e, s, d) in worst.items():
            print(f"{name:9s} {k:8s} worst relative error {e:.3g}  (seed {s}: {d})")
    if args.out:
        print("wrote", common.write_json(args.out / "stress-reference.json", report))
    return 0


if __name__ == "__main__":
    sys.exit(main())
