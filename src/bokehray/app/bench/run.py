"""Datasets, the measuring loop, the Pareto front and the reports of ``bokehray bench``.

The loop is built to be a fair referee on a shared, noisy machine:

* every method sees the same inputs (image, disparity, ``K``, ``d_f``, disc aperture);
* per image, each method renders once untimed (warm-up: kernel loading, worker start; this
  render is the one scored), then the timed runs go **round-robin over the methods**, so a
  burst of load from another process hits all of them alike;
* time per image is the median of the warm runs, with their min and max; peak memory is the
  rise of the resident set during the first timed run (``VmHWM`` reset through
  ``/proc/self/clear_refs``), measured in the worker process for out-of-process peers;
* scores depend only on the inputs and the methods, never on timing: reruns give the same
  errors bit for bit (tested).
"""

from __future__ import annotations

import csv
import hashlib
import json
import math
import os
import statistics
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ...data.datasets import perturb_disparity
from ...data.metrics import BAND_PX, PerceptualMetric, discontinuity_band, exposure_align, score
from ...errors import InputError
from .machine import reset_peak_rss, status_kb
from .methods import Method

__all__ = [
    "Case",
    "SynthSplit",
    "blb_cases",
    "ebb_cases",
    "pareto_front",
    "perturb_disparity",
    "run_bench",
    "synth_cases",
    "write_reports",
]

ROBUSTNESS_RADII = (-5, -4, -3, -2, -1, 1, 2, 3, 4, 5)
"""Disparity perturbations in px: negative = erosion (near regions shrink), positive = dilation."""


# --------------------------------------------------------------------------- cases


@dataclass(eq=False)
class Case:
    """One scored image: inputs, ground truth, blur (``k_px`` None: searched per method, EBB)."""

    name: str
    image: np.ndarray
    disparity: np.ndarray
    target: np.ndarray
    k_px: float | None
    focus_disparity: float
    band: np.ndarray = field(repr=False, default=None)  # type: ignore[assignment]
    aligned_image: np.ndarray | None = field(repr=False, default=None)
    exposure_gain: float | None = None
    focus_source: str = "given"

    def __post_init__(self) -> None:
        if self.band is None:
            self.band = discontinuity_band(self.disparity, BAND_PX)


@dataclass(frozen=True)
class SynthSplit:
    """Our synthetic test split: ``bokehray synth`` scenes of a fixed seed, never used for training.

    The seed is far from the training default (0), so no test scene is a training scene.
    """

    scenes: int = 6
    size: int = 320
    blur_levels: tuple[float, ...] = (12.0, 24.0)
    max_spp: int = 128
    seed: int = 900_001

    def key(self) -> str:
        from ... import __version__

        text = json.dumps([self.scenes, self.size, list(self.blur_levels), self.max_spp, self.seed, __version__])
        return hashlib.sha256(text.encode()).hexdigest()[:12]


QUICK_SPLIT = SynthSplit(scenes=2, size=160, blur_levels=(12.0,), max_spp=64)


def default_cache() -> Path:
    env = os.environ.get("BOKEHRAY_CACHE")
    if env:
        return Path(env)
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "bokehray"


def synth_cases(split: SynthSplit, cache: Path, *, workers: int | None = None, progress: bool = True,
                log: Callable[[str], None] = print, executor: str | None = "local",
                scheduler: str | None = None) -> tuple[list[Case], Path]:
    """The synthetic test split, generated once into ``cache`` (BLB layout) and read back."""
    from ...data.datasets import BLBDataset
    from ...data.synth import SynthConfig, generate

    root = Path(cache) / f"bench-synth-{split.key()}"
    done = root / "COMPLETE"
    if not done.is_file():
        log(f"generating the synthetic test split ({split.scenes} scenes, {split.size} px, seed {split.seed}) "
            f"into {root}")
        t = time.perf_counter()
        config = SynthConfig(size=split.size, blur_levels=split.blur_levels, max_spp=split.max_spp)
        generate(config, split.scenes, root, seed=split.seed, workers=workers, progress=progress, overwrite=True,
                 executor=executor, scheduler=scheduler)
        done.write_text(json.dumps({"split": split.__dict__ | {"blur_levels": list(split.blur_levels)},
                                    "seconds": round(time.perf_counter() - t, 1)}) + "\n")
    return _blb(BLBDataset(root)), root


def blb_cases(path: str | os.PathLike, level: int | None = 5, limit: int | None = None) -> list[Case]:
    """A BLB folder (or our synth layout) at blur ``level`` (the BokehMe and BokehDiff papers use 5)."""
    from ...data.datasets import BLBDataset

    return _blb(BLBDataset(path, level=level), limit)


def _blb(ds, limit: int | None = None) -> list[Case]:
    n = len(ds) if limit is None else min(limit, len(ds))
    out = []
    for i in range(n):
        s = ds[i]
        out.append(Case(s.name, s.image, s.disparity, s.target, float(s.k_px), float(s.focus_disparity)))
    return out


def ebb_cases(path: str | os.PathLike, limit: int | None = None, mask_dir: str = "mask") -> list[Case]:
    """EBB Val294-style pairs; focus from ``<root>/<mask_dir>/<stem>.*`` when present, else sharpness."""
    from ...data.datasets import EBBDataset
    from ...photo.read import read_image
    from .ebb import focus_from_mask, focus_from_sharpness

    ds = EBBDataset(path)
    masks = {}
    mdir = Path(path) / mask_dir
    if mdir.is_dir():
        masks = {p.stem: p for p in mdir.iterdir() if p.suffix.lower() in (".png", ".jpg", ".jpeg", ".tif", ".tiff")}
    n = len(ds) if limit is None else min(limit, len(ds))
    out = []
    for i in range(n):
        s = ds[i]
        if s.name in masks:
            d_f, src = focus_from_mask(s.disparity, read_image(masks[s.name])), "salient mask"
        else:
            d_f, src = focus_from_sharpness(s.target, s.disparity), "sharpest region of the ground truth"
        aligned, gain = exposure_align(s.image, s.target)
        out.append(Case(s.name, s.image, s.disparity, s.target, None, d_f, aligned_image=aligned,
                        exposure_gain=gain, focus_source=src))
    return out


# --------------------------------------------------------------------------- measuring


def _nanmean(vals: Sequence[float]) -> float:
    v = [x for x in vals if x is not None and not math.isnan(x)]
    return float(np.mean(v)) if v else math.nan


def run_bench(cases: Sequence[Case], methods: Sequence[Method], *, runs: int = 3,
              robustness_cases: int = 0, robustness_radii: Sequence[int] = ROBUSTNESS_RADII,
              perceptual: Sequence[PerceptualMetric] = (), k_range: tuple[float, float] = (0.0, 64.0),
              log: Callable[[str], None] = print) -> dict:
    """Measure every available method on every case; returns the results dict (see :func:`write_reports`)."""
    if not cases:
        raise InputError("bench: no images to measure")
    if runs < 1:
        raise InputError(f"--runs: expected at least 1, got {runs}")
    skipped: dict[str, str] = {}
    active: list[tuple[Method, Callable]] = []
    for m in methods:
        try:
            reason = m.unavailable()
            if reason is None:
                active.append((m, m.make()))
                continue
        except Exception as exc:  # noqa: BLE001 - a peer that fails to start is skipped, never fatal
            reason = f"{type(exc).__name__}: {exc}"
        skipped[m.name] = reason
        log(f"skipped {m.name}: {reason}")
    rows: list[dict] = []
    robustness: dict[str, dict[str, list[float]]] = {}
    try:
        for ci, case in enumerate(cases):
            log(f"[{ci + 1}/{len(cases)}] {case.name}")
            rows.extend(_measure_case(case, active, runs, perceptual, k_range, skipped, log))
        rob_cases = robustness_subset(cases, robustness_cases)
        for ci, case in enumerate(rob_cases):
            log(f"robustness [{ci + 1}/{len(rob_cases)}] {case.name}")
            _robustness_case(case, [(m, r) for m, r in active if m.robustness and m.name not in skipped], rows,
                             robustness_radii, robustness)
    finally:
        for _, r in active:
            close = getattr(r, "close", None)
            if close:
                close()
    return _summarise(rows, methods, skipped, robustness, robustness_radii, runs)


def robustness_subset(cases: Sequence[Case], n: int) -> list[Case]:
    """``n`` cases evenly spread over the list (so over the scenes, not the first scene's renders)."""
    if n <= 0:
        return []
    if n >= len(cases):
        return list(cases)
    return [cases[int(i)] for i in np.round(np.linspace(0, len(cases) - 1, n))]


def _k_for(case: Case, method: Method, render: Callable, k_range, log) -> tuple[float, int]:
    if case.k_px is not None:
        return case.k_px, 0
    from .ebb import search_k

    img = case.aligned_image if case.aligned_image is not None else case.image
    k, _, evals = search_k(lambda k: render(img, case.disparity, k, case.focus_disparity), case.target,
                           k_range[0], k_range[1])
    log(f"  {method.name}: K = {k:.2f} ({evals} renders searched)")
    return k, evals


def _measure_case(case: Case, active, runs: int, perceptual, k_range, skipped: dict, log) -> list[dict]:  # noqa: C901
    live = [(m, r) for m, r in active if m.name not in skipped]
    rows: dict[str, dict] = {}
    for m, render in live:
        try:
            k, evals = _k_for(case, m, render, k_range, log)
            out = render(case.image, case.disparity, k, case.focus_disparity)  # warm-up, and the scored render
        except Exception as exc:  # noqa: BLE001 - a failing peer is reported and skipped
            skipped[m.name] = f"failed on {case.name}: {type(exc).__name__}: {exc}"
            log(f"skipped {m.name}: {skipped[m.name]}")
            continue
        row = {"case": case.name, "method": m.name, "family": m.family, "k_px": k, "focus_disparity":
               case.focus_disparity, "k_search_renders": evals, **score(out, case.target, case.band)}
        for pm in perceptual:
            row[pm.name] = pm(out, case.target)
        if case.aligned_image is not None:
            aligned = render(case.aligned_image, case.disparity, k, case.focus_disparity)
            row.update({f"aligned_{key}": v for key, v in score(aligned, case.target, case.band).items()})
            for pm in perceptual:
                row[f"aligned_{pm.name}"] = pm(aligned, case.target)
            row["exposure_gain"] = case.exposure_gain
            row["focus_source"] = case.focus_source
        row["times"] = []
        rows[m.name] = row
    for i in range(runs):  # round-robin: load bursts hit every method alike
        for m, render in live:
            if m.name not in rows or m.name in skipped:
                continue
            row = rows[m.name]
            first = i == 0
            rss0 = status_kb("VmRSS") if first and reset_peak_rss() else None
            t = time.perf_counter()
            try:
                render(case.image, case.disparity, row["k_px"], case.focus_disparity)
            except Exception as exc:  # noqa: BLE001
                skipped[m.name] = f"failed on {case.name}: {type(exc).__name__}: {exc}"
                log(f"skipped {m.name}: {skipped[m.name]}")
                continue
            row["times"].append(time.perf_counter() - t)
            inner = getattr(render, "last_inner_seconds", None)  # out-of-process peers: the worker's own time
            if inner is not None:
                row.setdefault("inner_times", []).append(inner)
            if first:
                worker_peak = getattr(render, "last_peak_mb", None)
                hwm = status_kb("VmHWM")
                row["peak_mb"] = worker_peak if worker_peak is not None else (
                    (hwm - rss0) / 1024 if rss0 is not None and hwm is not None else None)
    out = []
    for m, _ in live:
        row = rows.get(m.name)
        if row is None or not row["times"] or m.name in skipped:
            continue
        ts = row.pop("times")
        row.update(time_median=statistics.median(ts), time_min=min(ts), time_max=max(ts), runs=len(ts))
        if "inner_times" in row:
            row["worker_time_median"] = statistics.median(row.pop("inner_times"))
        log(f"  {m.name:16s} {row['time_median']:8.3f} s  PSNR {row['psnr']:6.2f}  band {row['band_psnr']:6.2f}  "
            f"SSIM {row['ssim']:.4f}")
        out.append(row)
    return out


def _robustness_case(case: Case, active, rows: list[dict], radii, robustness: dict) -> None:
    clean = {r["method"]: r for r in rows if r["case"] == case.name}
    for radius in radii:
        d = perturb_disparity(case.disparity, radius)
        for m, render in active:
            if m.name not in clean:
                continue
            k = clean[m.name]["k_px"]
            try:
                out = render(case.image, d, k, case.focus_disparity)
            except Exception:  # noqa: BLE001 - robustness of a failing peer is left out
                continue
            s = score(out, case.target, case.band)
            robustness.setdefault(m.name, {}).setdefault(str(radius), []).append(s["psnr"] - clean[m.name]["psnr"])


# --------------------------------------------------------------------------- summary


def pareto_front(points: dict[str, tuple[float, float]]) -> list[str]:
    """Names whose (time, score) no other point beats: none both at most as slow and at least as good,
    and strictly better in one. Sorted by time."""
    front = []
    for n, (t, s) in points.items():
        dominated = any((t2 <= t and s2 >= s) and (t2 < t or s2 > s) for n2, (t2, s2) in points.items() if n2 != n)
        if not dominated:
            front.append(n)
    return sorted(front, key=lambda n: (points[n][0], -points[n][1]))


def dominators(name: str, points: dict[str, tuple[float, float]], among: Sequence[str]) -> list[str]:
    """Which of ``among`` are both faster (or as fast) and more accurate (or as accurate) than ``name``."""
    t, s = points[name]
    return [n for n in among if n != name and points[n][0] <= t and points[n][1] >= s
            and (points[n][0] < t or points[n][1] > s)]


def _summarise(rows: list[dict], methods: Sequence[Method], skipped: dict, robustness: dict, radii, runs) -> dict:
    summary: dict[str, dict] = {}
    for m in methods:
        mine = [r for r in rows if r["method"] == m.name]
        if not mine or m.name in skipped:
            continue
        keys = [k for k in mine[0] if isinstance(mine[0][k], float) and k not in ("focus_disparity", "exposure_gain")]
        s = {k: _nanmean([r.get(k) for r in mine]) for k in keys}
        s.update(family=m.family, description=m.description, images=len(mine),
                 peak_mb_max=max((r.get("peak_mb") or 0.0) for r in mine) or None)
        if m.name in robustness:
            s["robustness_drop_db"] = {str(r): float(np.mean(robustness[m.name][str(r)]))
                                       for r in radii if str(r) in robustness[m.name]}
        summary[m.name] = s
    points = {n: (s["time_median"], s["psnr"]) for n, s in summary.items()}
    front = pareto_front(points) if points else []
    for n in summary:
        summary[n]["on_pareto_front"] = n in front
    peers = [n for n, s in summary.items() if s["family"] == "peer"]
    preview_check = None
    if "preview" in points:
        beaten_by = dominators("preview", points, peers)
        preview_check = {"on_front": "preview" in front, "peers_faster_and_more_accurate": beaten_by,
                         "holds": not beaten_by}
    return {"summary": summary, "per_image": rows, "skipped": skipped, "pareto_front": front,
            "preview_check": preview_check, "runs_per_image": runs, "robustness_radii": list(radii)}


# --------------------------------------------------------------------------- reports


def _fmt(v, nd=2) -> str:
    return "" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.{nd}f}"


def markdown_table(results: dict) -> str:
    """The summary table of docs/benchmarks.md: one row per method/setting."""
    aligned = any("aligned_psnr" in s for s in results["summary"].values())
    head = "| method | family | time/image s (median) | min-max s | PSNR | band PSNR | SSIM | band SSIM |"
    head += " aligned PSNR | aligned SSIM |" if aligned else ""
    worker = any("worker_time_median" in s for s in results["summary"].values())
    head += " worker s |" if worker else ""
    head += " peak MB | K | Pareto |"
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for n, s in results["summary"].items():
        line = (f"| {n} | {s['family']} | {_fmt(s['time_median'], 3)} | {_fmt(s['time_min'], 3)}-{_fmt(s['time_max'], 3)}"
                f" | {_fmt(s['psnr'])} | {_fmt(s['band_psnr'])} | {_fmt(s['ssim'], 4)} | {_fmt(s['band_ssim'], 4)} |")
        if aligned:
            line += f" {_fmt(s.get('aligned_psnr'))} | {_fmt(s.get('aligned_ssim'), 4)} |"
        if worker:
            line += f" {_fmt(s.get('worker_time_median'), 3)} |"
        line += f" {_fmt(s.get('peak_mb_max'), 0)} | {_fmt(s.get('k_px'), 1)} | {'yes' if s['on_pareto_front'] else ''} |"
        lines.append(line)
    return "\n".join(lines)


def robustness_table(results: dict) -> str:
    radii = results["robustness_radii"]
    rows = [(n, s["robustness_drop_db"]) for n, s in results["summary"].items() if s.get("robustness_drop_db")]
    if not rows:
        return ""
    head = "| method | " + " | ".join(("erode " if r < 0 else "dilate ") + f"{abs(r)}" for r in radii) + " |"
    lines = [head, "|" + "---|" * (len(radii) + 1)]
    for n, drop in rows:
        lines.append(f"| {n} | " + " | ".join(_fmt(drop.get(str(r))) for r in radii) + " |")
    return "\n".join(lines)


def write_reports(results: dict, out: Path, plots: Path, tag: str) -> list[Path]:
    """``bench_<tag>.json``, ``.csv`` (per image), ``.md`` (tables) in ``out``; two PNG plots in ``plots``."""
    out.mkdir(parents=True, exist_ok=True)
    plots.mkdir(parents=True, exist_ok=True)
    written = []
    p = out / f"bench_{tag}.json"
    p.write_text(json.dumps(results, indent=1, default=_jsonable, allow_nan=True) + "\n")
    written.append(p)
    p = out / f"bench_{tag}.csv"
    cols = sorted({k for r in results["per_image"] for k in r}, key=lambda k: (k not in ("case", "method"), k))
    with p.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=cols)
        w.writeheader()
        w.writerows(results["per_image"])
    written.append(p)
    p = out / f"bench_{tag}.md"
    p.write_text(markdown_table(results) + "\n\n" + robustness_table(results) + "\n")
    written.append(p)
    written += _plots(results, plots, tag)
    return written


def _jsonable(o):
    if isinstance(o, (np.generic,)):
        return o.item()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(type(o).__name__)


def _plots(results: dict, plots: Path, tag: str) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    written = []
    summ = results["summary"]
    if summ:
        fig, ax = plt.subplots(figsize=(7.5, 4.8))
        front = results["pareto_front"]
        for i, (n, s) in enumerate(summ.items()):
            colour = "tab:blue" if s["family"] == "bokehray" else "tab:red"
            ax.errorbar(s["time_median"], s["psnr"], xerr=[[s["time_median"] - s["time_min"]],
                        [s["time_max"] - s["time_median"]]], fmt="o", color=colour, ms=6,
                        mfc=colour if n in front else "white", capsize=2)
            ax.annotate(n, (s["time_median"], s["psnr"]), textcoords="offset points", fontsize=8,
                        xytext=((5, 4), (5, -12), (-20, 12))[i % 3])  # neighbours (settings) do not overlap
        fx = [summ[n]["time_median"] for n in front]
        fy = [summ[n]["psnr"] for n in front]
        ax.step(fx, fy, where="post", color="grey", lw=0.8, ls="--", label="Pareto front (filled points)")
        ax.plot([], [], "o", color="tab:blue", label="bokehray")
        ax.plot([], [], "o", color="tab:red", label="peers")
        ax.set_xscale("log")
        ax.set_xlabel("time per image, s (median of warm runs; bars: min-max)")
        ax.set_ylabel("PSNR, dB (sRGB, clipped)")
        ax.set_title(f"bokehray bench: {tag}")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8, loc="best")
        fig.tight_layout()
        p = plots / f"bench_{tag}_pareto.png"
        fig.savefig(p, dpi=100)
        plt.close(fig)
        written.append(p)
    rob = {n: s["robustness_drop_db"] for n, s in summ.items() if s.get("robustness_drop_db")}
    if rob:
        fig, ax = plt.subplots(figsize=(7.5, 4.5))
        radii = results["robustness_radii"]
        for n, drop in rob.items():
            xs = sorted([r for r in radii if str(r) in drop] + [0])  # 0: the clean disparity, no change
            ls = "-" if summ[n]["family"] == "bokehray" else "--"
            ax.plot(xs, [drop[str(r)] if r else 0.0 for r in xs], ls, marker="o", ms=3, label=n)
        ax.axhline(0, color="grey", lw=0.6)
        ax.set_xlabel("disparity perturbation, px (negative: erosion, positive: dilation)")
        ax.set_ylabel("PSNR change vs clean disparity, dB")
        ax.set_title(f"robustness to disparity errors: {tag}")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7, ncol=2)
        fig.tight_layout()
        p = plots / f"bench_{tag}_robustness.png"
        fig.savefig(p, dpi=100)
        plt.close(fig)
        written.append(p)
    return written
