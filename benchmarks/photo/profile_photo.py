"""Where the time and the bytes of one ``bokehray render`` go, stage by stage (the table of docs/renderer.md,
"12 MP and 24 MP photos").

Runs the command line in this process with the pipeline's stages wrapped: for each stage its wall time, CPU time
(user + system of the process), minor page faults and its peak RSS (the kernel's high-water mark, reset with
``/proc/self/clear_refs`` at each stage's start, so a stage's peak is its own). Stages nest (a stage's numbers
include its children's); the layers render on worker threads, so a layer's line gives its thread's CPU time.

Usage::

    python benchmarks/photo/profile_photo.py photo.jpg d.png [--json out.json] [--out out.exr]
    python benchmarks/photo/profile_photo.py photo.jpg d.png --threads 1        # one worker (PreviewOptions(threads=1))
    python benchmarks/photo/profile_photo.py photo.jpg d.png --no-fill-lock     # layers fill concurrently (a measurement)
"""

from __future__ import annotations

import argparse
import functools
import importlib
import json
import resource
import sys
import tempfile
import threading
import time
from pathlib import Path


def _hwm_kb() -> int:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("VmHWM:"):
                return int(line.split()[1])
    return 0


def _reset_hwm() -> None:
    try:
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")
    except OSError:
        pass


class Profile:
    def __init__(self) -> None:
        self.rows: list[dict] = []
        self.stack: list[dict] = []
        self.lock = threading.Lock()
        self.main = threading.get_ident()

    def wrap(self, module: str, name: str, label: str, threaded: bool = False) -> None:
        mod = importlib.import_module(module)
        fn = getattr(mod, name)

        @functools.wraps(fn)
        def inner(*a, **k):
            if threading.get_ident() != self.main or threaded:
                t, c = time.perf_counter(), time.thread_time()
                try:
                    return fn(*a, **k)
                finally:
                    with self.lock:
                        self.rows.append({"stage": label, "depth": len(self.stack), "wall_s": time.perf_counter() - t,
                                          "cpu_s": time.thread_time() - c, "thread": True})
            return self.timed(label, fn, *a, **k)

        setattr(mod, name, inner)

    def timed(self, label, fn, *a, **k):
        if self.stack:
            self.stack[-1]["peak_kb"] = max(self.stack[-1]["peak_kb"], _hwm_kb())
        _reset_hwm()
        ru = resource.getrusage(resource.RUSAGE_SELF)
        row = {"stage": label, "depth": len(self.stack), "peak_kb": _hwm_kb(), "t": time.perf_counter(),
               "cpu": ru.ru_utime + ru.ru_stime, "sys": ru.ru_stime, "flt": ru.ru_minflt}
        self.rows.append(row)
        self.stack.append(row)
        try:
            return fn(*a, **k)
        finally:
            self.stack.pop()
            ru = resource.getrusage(resource.RUSAGE_SELF)
            row["peak_kb"] = max(row["peak_kb"], _hwm_kb())
            row.update(wall_s=time.perf_counter() - row.pop("t"), cpu_s=ru.ru_utime + ru.ru_stime - row.pop("cpu"),
                       sys_s=ru.ru_stime - row.pop("sys"), faults=ru.ru_minflt - row.pop("flt"))
            if self.stack:
                self.stack[-1]["peak_kb"] = max(self.stack[-1]["peak_kb"], row["peak_kb"])
            _reset_hwm()

    def table(self) -> str:
        lines = [f"{'stage':44s} {'wall s':>7s} {'cpu s':>7s} {'sys s':>6s} {'faults':>9s} {'peak MB':>8s}"]
        layers = [r for r in self.rows if r.get("thread")]
        for r in self.rows:
            if r.get("thread"):
                continue
            name = "  " * r["depth"] + r["stage"]
            lines.append(f"{name:44s} {r['wall_s']:7.2f} {r['cpu_s']:7.2f} {r['sys_s']:6.2f} {r['faults']:9d} "
                         f"{r['peak_kb'] / 1024:8.0f}")
        by = {}
        for r in layers:
            n, w, c = by.get(r["stage"], (0, 0.0, 0.0))
            by[r["stage"]] = (n + 1, w + r["wall_s"], c + r["cpu_s"])
        for stage, (n, w, c) in by.items():
            lines.append(f"{'(threads) ' + stage + f' x{n}':44s} {w:7.2f} {c:7.2f}")
        return "\n".join(lines)


STAGES = [
    ("bokehray.photo.read", "read_image", "read image (decode, ICC, sRGB LUT)"),
    ("bokehray.photo.read", "read_disparity", "read disparity"),
    ("bokehray.photo.highlights", "reconstruct_highlights", "highlight reconstruction"),
    ("bokehray.pipeline", "render_handed_over", "render"),
    ("bokehray.pipeline", "check_image", "check image"),
    ("bokehray.pipeline", "check_radiance", "check radiance"),
    ("bokehray.pipeline", "check_disparity", "check disparity"),
    ("bokehray.pipeline", "_soft_scene", "soft maps and soft-edge matting"),
    ("bokehray.levels.preview", "border_pad", "border pad"),
    ("bokehray.scene", "copy_tiles", "copy tiles"),
    ("bokehray.scene", "split_scene", "split scene (layers)"),
    ("bokehray.tiling", "choose_tile", "choose tile"),
    ("bokehray.levels.preview", "_render_window", "layers: upload, scatter, composite, finalize"),
    ("bokehray.scene", "build_layer_sources", "fill (layer sources)", True),
    ("bokehray.levels.preview", "route_salient", "routing", True),
    ("bokehray.levels.preview", "render_layer", "layer (fill + scatter + resolve)", True),
    ("bokehray.output.write", "write_image", "write"),
    ("bokehray.output.write", "srgb_codes", "sRGB encode + quantize"),
    ("bokehray.output.write", "encode_pil", "encode (Pillow) + write"),
]


class _TimedLock:
    """The fill lock, with the time each worker waited for it (idle: the other worker was filling)."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.waits: list[float] = []

    def __enter__(self) -> None:
        t = time.perf_counter()
        self.lock.acquire()
        self.waits.append(time.perf_counter() - t)

    def __exit__(self, *exc) -> None:
        self.lock.release()


FILL_LOCKS: list[_TimedLock] = []


def _variants(threads: int | None, no_fill_lock: bool) -> None:
    """The command line's render with another worker count, or without the fill lock (measurements only); with the
    lock, the time the workers waited for it is recorded (``FILL_LOCKS``)."""
    if threads is not None:
        import bokehray.app.render_job as job

        render = job._render

        def with_threads(args, *a, **k):
            args.threads = threads  # what a batch's worker processes set (PreviewOptions(threads=...))
            return render(args, *a, **k)

        job._render = with_threads
    import contextlib
    import dataclasses

    import bokehray.levels.preview as preview

    scatter = preview._Scatter

    def gate():
        if no_fill_lock:
            return contextlib.nullcontext()
        FILL_LOCKS.append(_TimedLock())
        return FILL_LOCKS[-1]

    preview._Scatter = lambda *a, **k: dataclasses.replace(scatter(*a, **k), fill_gate=gate())


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("image")
    ap.add_argument("disparity")
    ap.add_argument("--out", default=None)
    ap.add_argument("--json", default=None)
    ap.add_argument("--threads", type=int, default=None, help="worker threads (default: the command line's)")
    ap.add_argument("--no-fill-lock", action="store_true",
                    help="let layers build their sources concurrently (render_layer's fill lock off: same values)")
    a = ap.parse_args()
    _variants(a.threads, a.no_fill_lock)
    prof = Profile()
    for st in STAGES:
        try:
            prof.wrap(*st)
        except (ImportError, AttributeError) as e:
            print(f"(not wrapped: {st[:2]}: {e})", file=sys.stderr)
    from bokehray.app.cli import main as cli

    out = a.out or str(Path(tempfile.mkdtemp()) / "out.jpg")
    ru0 = resource.getrusage(resource.RUSAGE_SELF)
    prof.timed("total (CLI render)", cli, ["render", a.image, "--disparity", a.disparity, "-o", out, "--quiet"])
    print(prof.table())
    ru = resource.getrusage(resource.RUSAGE_SELF)
    print(f"process: user {ru.ru_utime:.2f} s, sys {ru.ru_stime:.2f} s, minor faults {ru.ru_minflt}, "
          f"max RSS {ru.ru_maxrss / 1024:.0f} MB (since start; import {ru0.ru_maxrss / 1024:.0f} MB)")
    waits = [w for lock in FILL_LOCKS for w in lock.waits]
    if waits:
        print(f"fill lock: {len(waits)} fills, the workers waited {sum(waits):.2f} s for it (longest {max(waits):.2f} s)")
    if a.json:
        Path(a.json).write_text(json.dumps(prof.rows, indent=1))


if __name__ == "__main__":
    main()
