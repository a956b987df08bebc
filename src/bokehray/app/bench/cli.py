"""The ``bokehray bench`` subcommand (registered by :mod:`bokehray.app.cli`)."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from ...errors import InputError


def add_parser(sub) -> argparse.ArgumentParser:
    b = sub.add_parser(
        "bench",
        help="measure run time against error for every quality level and for peers, on the same inputs",
        description="Default data: our synthetic test split (fixed seed, generated once into the cache). "
        "Writes bench_<data>.json/.csv/.md and Pareto and robustness plots. See docs/benchmarks.md.",
    )
    data = b.add_mutually_exclusive_group()
    data.add_argument("--blb", metavar="PATH", help="a BLB folder (<scene>/image.exr, depth.exr, bokeh_<k>_<f>.exr)")
    data.add_argument("--ebb", metavar="PATH", help="an EBB Val294-style folder: input/, target/, disparity/ "
                      "[, mask/ salient-region masks]")
    b.add_argument("--blb-level", type=int, default=5, help="BLB blur level k (default 5, as the papers)")
    b.add_argument("--quick", action="store_true", help="about one minute: 4 small images, a method subset")
    b.add_argument("--methods", help="comma-separated methods (default: all; --list-methods shows them)")
    b.add_argument("--list-methods", action="store_true", help="list the methods and whether they can run here")
    b.add_argument("--limit", type=int, help="use only the first N images")
    b.add_argument("--runs", type=int, help="timed warm runs per image and method (default 3, quick 2)")
    b.add_argument("--robustness", type=int, metavar="N",
                   help="images of the erode/dilate robustness sweep (default 4, quick 1; 0 = off)")
    b.add_argument("--k-max", type=float, default=64.0, help="EBB: upper end of the K search (default 64)")
    b.add_argument("--lpips", metavar="FILE", help="local TorchScript LPIPS model (see docs/benchmarks.md)")
    b.add_argument("--dists", metavar="FILE", help="local TorchScript DISTS model")
    b.add_argument("--out", default="out/bench", help="folder for JSON/CSV/markdown results (default out/bench)")
    b.add_argument("--plots", help="folder for the PNG plots (default: --out)")
    b.add_argument("--cache", help="cache of the synthetic test split (default $BOKEHRAY_CACHE or ~/.cache/bokehray)")
    from ...executor import add_executor_args

    add_executor_args(b, workers_help="processes generating the synthetic split (the timing itself runs in this "
                      "process, one method at a time)")
    b.add_argument("--debug", action="store_true", help="show tracebacks")
    b.add_argument("--quiet", action="store_true", help="print only the summary")
    return b


def cmd_bench(args: argparse.Namespace) -> int:  # noqa: C901
    from ...data.metrics import PerceptualMetric
    from .machine import machine_info
    from .methods import registry, select
    from .run import (
        QUICK_SPLIT,
        SynthSplit,
        blb_cases,
        default_cache,
        ebb_cases,
        markdown_table,
        robustness_table,
        run_bench,
        synth_cases,
        write_reports,
    )

    if args.list_methods:
        for m in registry():
            try:
                reason = m.unavailable()
            except Exception as exc:  # noqa: BLE001 - listing must not crash on a broken peer
                reason = f"{type(exc).__name__}: {exc}"
            print(f"{m.name:16s} {m.family:9s} {'ok' if reason is None else 'skipped: ' + reason}  ({m.description})")
        return 0
    for flag in ("limit", "runs", "robustness"):
        v = getattr(args, flag)
        if v is not None and v < (0 if flag == "robustness" else 1):
            raise InputError(f"--{flag}: expected a positive number, got {v}")
    log = (lambda s: None) if args.quiet else (lambda s: print(s, flush=True))
    t0 = time.perf_counter()
    methods = select(args.methods, args.quick)
    perceptual = [PerceptualMetric(n, p) for n, p in (("lpips", args.lpips), ("dists", args.dists)) if p]
    if args.blb:
        cases, tag, source = blb_cases(args.blb, args.blb_level, args.limit), f"blb-l{args.blb_level}", args.blb
    elif args.ebb:
        cases, tag, source = ebb_cases(args.ebb, args.limit), "ebb", args.ebb
    else:
        split = QUICK_SPLIT if args.quick else SynthSplit()
        cache = Path(args.cache) if args.cache else default_cache()
        cases, root = synth_cases(split, cache, workers=args.workers, progress=not args.quiet, log=log,
                                   executor=args.executor, scheduler=args.scheduler)
        cases = cases[: args.limit] if args.limit else cases
        tag, source = "synth-quick" if args.quick else "synth", str(root)
    runs = args.runs or (2 if args.quick else 3)
    rob = args.robustness if args.robustness is not None else (1 if args.quick else 4)
    results = run_bench(cases, methods, runs=runs, robustness_cases=rob,
                        robustness_radii=(-2, 2) if args.quick else (-5, -4, -3, -2, -1, 1, 2, 3, 4, 5),
                        perceptual=perceptual, k_range=(0.0, args.k_max), log=log)
    results["dataset"] = {"kind": tag, "source": source, "images": len(cases),
                          "size": list(cases[0].image.shape[:2])}
    results["machine"] = machine_info()
    results["wall_seconds"] = round(time.perf_counter() - t0, 1)
    written = write_reports(results, Path(args.out), Path(args.plots or args.out), tag)
    print(markdown_table(results))
    rt = robustness_table(results)
    if rt:
        print("\nPSNR change (dB) with eroded/dilated disparity:\n" + rt)
    chk = results["preview_check"]
    if chk is not None:
        beaten = ", ".join(chk["peers_faster_and_more_accurate"]) or "none"
        print(f"\npeers both faster and more accurate than preview: {beaten} (target: none); "
              f"preview on the Pareto front of all methods: {'yes' if chk['on_front'] else 'no'}")
    for name, reason in results["skipped"].items():
        print(f"skipped {name}: {reason}")
    print(f"wrote {', '.join(str(p) for p in written)} ({results['wall_seconds']:.0f} s)")
    if args.debug:
        print(json.dumps(results["machine"]))
    return 0
