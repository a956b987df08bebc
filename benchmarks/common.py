"""Shared helpers of the bokehray benchmarks: machine description, warm timing, peak memory, JSON."""

from __future__ import annotations

import json
import re
import resource
import statistics
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path

from bokehray.app.bench.machine import git_commit, machine_info, reset_peak_rss, status_kb

__all__ = ["REPO", "git_commit", "machine_info", "machine_tag", "peak_rss_mb_of", "report_rss", "reset_peak_rss", "time_warm",
           "write_json"]

REPO = Path(__file__).resolve().parent.parent


def machine_tag(info: dict) -> str:
    """Short file-name-safe tag, e.g. ``vm-amd-epyc-2c``."""
    raw = f"{info['hostname']}-{info['cpu']}-{info['cores']}c"
    return re.sub(r"[^a-z0-9]+", "-", raw.lower().replace("(r)", "").replace("(tm)", "")).strip("-")[:60]


def time_warm(fn: Callable[[], object], runs: int = 5, warmup: int = 1) -> dict:
    """Time ``fn()`` after ``warmup`` untimed calls (kernel loading, caches).

    Returns:
        dict with ``median``, ``min``, ``max`` (seconds), ``runs`` (all timed calls)
        and ``warmup`` (the warm-up calls' times, first call included).
    """
    def once() -> float:
        t = time.perf_counter()
        fn()
        return time.perf_counter() - t

    warm = [once() for _ in range(warmup)]
    times = [once() for _ in range(runs)]
    return {"median": statistics.median(times), "min": min(times), "max": max(times), "runs": times, "warmup": warm}


def peak_rss_mb_of(cmd_args: Sequence[str], timeout: float = 600.0) -> dict:
    """Run ``python *cmd_args`` in a fresh process and read the peak RSS it reports.

    The child calls :func:`report_rss` before the measured work (current RSS)
    and after it (peak RSS); see there why the peak is not ``ru_maxrss``.

    Returns:
        dict with ``peak_mb`` and ``before_mb`` (or None), or ``error`` on failure.
    """
    try:
        p = subprocess.run([sys.executable, *cmd_args], cwd=REPO, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return {"error": f"timed out after {timeout:.0f} s"}
    kb = {k: int(v) for k, _, v in (ln.partition("=") for ln in p.stdout.splitlines()) if k in ("RSS_KB", "PEAK_KB")}
    if p.returncode != 0 or "PEAK_KB" not in kb:
        tail = (p.stderr.strip().splitlines() or ["no output"])[-1]
        return {"error": f"exit code {p.returncode}: {tail}"}
    return {"peak_mb": kb["PEAK_KB"] / 1024, "before_mb": kb["RSS_KB"] / 1024 if "RSS_KB" in kb else None}


def report_rss(peak: bool) -> None:
    """Print this process's current (``peak=False``) or peak RSS in KB for :func:`peak_rss_mb_of`.

    The peak is ``VmHWM`` of /proc/self/status, not ``ru_maxrss``: on Linux a
    child's ``ru_maxrss`` starts at its parent's peak (exec carries the forked
    address space's high-water mark over), so it would report the benchmark
    driver's memory. ``ru_maxrss`` is the fallback where /proc is missing.
    """
    if peak:
        kb = status_kb("VmHWM") or resource.getrusage(resource.RUSAGE_SELF).ru_maxrss // (
            1024 if sys.platform == "darwin" else 1)  # bytes on macOS
        print(f"PEAK_KB={kb}", flush=True)
    elif (kb := status_kb("VmRSS")) is not None:
        print(f"RSS_KB={kb}", flush=True)


def write_json(path: str | Path, obj: object) -> Path:
    """Write ``obj`` as indented JSON, creating parent folders."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(obj, indent=2) + "\n")
    return path
