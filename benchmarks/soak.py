"""Randomised soak test: render many random, extreme or degenerate cases and report any failure.

Each case draws an image size (1 x 1 upwards), radiance scale (0 to 1e4, denormals included),
a disparity pattern (constant 0 or 1, random, one-pixel steps, a step edge), K (0 to 1e4),
d_f in [0, 1], an aperture, a quality level, the channel count (grey, RGB, RGBA with alpha
exactly 0 and 1) and, for one case in eight, a forced tile size, and checks: no exception,
finite output, output within the input's range (every pixel is an average of input radiances;
float32 rounding of 1e-5 of the brightest value is allowed), energy conservation for
constant-disparity cases with a zero border, and that the tiled render equals the untiled one.
A failure prints a one-line reproducer (seed and case index).

``--io N`` (issue 18) runs N command-line cases instead, each in a fresh process, on the paths
where the CLI meets the operating system: a SIGTERM or SIGINT at a random moment of a real
render and write (PNG 8/16-bit, TIFF, EXR, JPEG); a disk that fills during the write (a tmpfs
of random size below the output's, root only; skipped otherwise); and extreme values (radiance
up to float32's maximum, highlight boosts up to 1e39, float64 disparity of 1e300). Checked:
the exit status is one of those promised (0; 2 with exactly one ``bokehray: error:`` line;
130/143 after a signal with one line), nothing else reaches stderr (no traceback, no warning,
no native library line), no temporary file is left, and an output that exists is complete.

Usage (from the repository root)::

    python benchmarks/soak.py --cases 5000          # long soak
    python benchmarks/soak.py --cases 200 --seed 1  # the short version CI runs
    python benchmarks/soak.py --io 60 --seed 1      # signals, full disks, extreme values via the CLI
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import numpy as np  # noqa: E402

import bokehray as br  # noqa: E402


def draw_case(rng: np.random.Generator) -> dict:
    h, w = int(rng.choice([1, 2, 3, 7, 16, 33, 64])), int(rng.choice([1, 2, 5, 16, 40, 64]))
    scale = float(rng.choice([0.0, 1e-40, 1e-8, 1.0, 50.0, 1e4]))
    pattern = str(rng.choice(["zero", "one", "random", "steps", "edge", "constant"]))
    k = float(rng.choice([0.0, 1e-6, 0.49, 0.5, 2.0, 9.0, 40.0, 1e4]))
    quality = "raytrace" if rng.random() < 0.15 and k <= 40 and h * w <= 1024 else "preview"
    return {"h": h, "w": w, "scale": scale, "pattern": pattern, "k": k, "d_f": float(rng.choice([0.0, 0.5, 1.0,
            rng.random()])), "blades": int(rng.choice([0, 0, 5, 6])), "curv": float(rng.random()),
            "quality": quality, "border": bool(rng.random() < 0.3), "img_seed": int(rng.integers(1 << 31)),
            "channels": int(rng.choice([3, 3, 1, 4])), "tile": int(rng.choice([16, 24, 40])) if rng.random() < 0.125 else 0}


def run_case(c: dict) -> str | None:
    rng = np.random.default_rng(c["img_seed"])
    h, w = c["h"], c["w"]
    image = (rng.random((h, w, c.get("channels", 3))) * c["scale"]).astype(np.float32)
    if image.shape[2] == 4:
        image[..., 3] = rng.choice([0.0, 1.0, 0.3], (h, w))  # alpha exactly 0 and 1
    d = {"zero": np.zeros((h, w)), "one": np.ones((h, w)), "random": rng.random((h, w)),
         "steps": np.indices((h, w)).sum(0) % 2, "edge": (np.arange(w)[None, :] >= w // 2) * np.ones((h, 1)),
         "constant": np.full((h, w), rng.random())}[c["pattern"]].astype(np.float32)
    margin = 2 * int(np.ceil(c["k"])) + 2  # light lands r px out, where borders renormalise up to r more
    check_energy = c["border"] and c["pattern"] in ("zero", "one", "constant") and min(h, w) > 2 * margin + 2 \
        and c["quality"] == "preview"
    if check_energy:
        image[:margin] = image[-margin:] = 0
        image[:, :margin] = image[:, -margin:] = 0
    ap = br.Aperture(blades=c["blades"], curvature=c["curv"]) if c["blades"] else br.Aperture()
    opts = br.RaytraceOptions(max_spp=16) if c["quality"] == "raytrace" else None
    try:
        out = br.render(image, d, br.BlurParams(c["k"], c["d_f"]), ap, quality=c["quality"], options=opts)
        tiled = None if not c.get("tile") else br.render(image, d, br.BlurParams(c["k"], c["d_f"]), ap,
                                                           quality=c["quality"], options=opts,
                                                           memory=br.MemoryOptions(tile_size=c["tile"]))
    except Exception as e:  # noqa: BLE001 - a soak reports every failure
        return f"exception {type(e).__name__}: {e}"
    if tiled is not None and np.abs(tiled - out).max() > 2e-5 * max(float(np.abs(out).max()), 1e-30):
        return f"tiled render differs from the untiled one by {np.abs(tiled - out).max():.3g}"
    if not np.isfinite(out).all():
        return "non-finite output"
    lo, hi = image.min(axis=(0, 1)), image.max(axis=(0, 1))
    # float32 running sums along a row carry rounding relative to the brightest value in it
    tol = 1e-4 * (1 + np.abs(lo)) + 1e-5 * float(np.abs(image).max())
    if (out < lo - tol).any() or (out > hi + tol).any():
        return f"output outside the input range: [{out.min():.4g}, {out.max():.4g}] vs [{lo.min():.4g}, {hi.max():.4g}]"
    if check_energy and image.sum() > 0:
        rel = abs(float(out.sum()) - float(image.sum())) / float(image.sum())
        if rel > 1e-3:
            return f"energy not conserved: relative error {rel:.2e}"
    return None


# --------------------------------------------------------------------------- --io: the CLI and the OS

_ROOT = Path(__file__).resolve().parent.parent
_ENV = {**os.environ, "PYTHONPATH": os.pathsep.join([str(_ROOT / "src"), str(_ROOT / "kernels"), str(_ROOT / "refiner"),
                                                     os.environ.get("PYTHONPATH", "")])}
_CLI = [sys.executable, "-c", "import sys; from bokehray.app.cli import main; sys.exit(main())"]
_KNOWN = {"renderer produced NaN/Inf": "issue 18.3 (radiance near float32's maximum; tests/test_reliability.py)"}


def _inputs(folder: Path) -> dict:
    """The files every --io case draws from (written once)."""
    pass

    rng = np.random.default_rng(0)
    f = {}
    big = rng.random((1000, 1500, 3)).astype(np.float32)
    f["big"] = br.write_image(folder / "big.png", big)
    f["big_d"] = br.write_disparity(folder / "big_d.png", np.tile(np.linspace(0, 1, 1500, dtype=np.float32), (1000, 1)))
    small = rng.random((96, 128, 3)).astype(np.float32)
    f["small"] = br.write_image(folder / "small.png", small)
    f["small_d"] = br.write_disparity(folder / "small_d.png", np.tile(np.linspace(0, 1, 128, dtype=np.float32), (96, 1)))
    for scale in (1e30, 3e38, 3.4e38):
        img = small.copy()
        img[40:50, 60:70] = scale
        f[f"bright{scale:g}"] = br.write_image(folder / f"bright{scale:g}.exr", img)
    for v in (0.5, 1e300, -1e300, 1e-300):
        d = np.full((96, 128), 0.5)
        d[7, 9] = v
        np.save(folder / f"d64_{v:g}.npy", d)
        f[f"d64_{v:g}"] = folder / f"d64_{v:g}.npy"
    return f


def _hidden(folder: Path) -> list[str]:
    return sorted(n for n in os.listdir(folder) if n.startswith("."))


def _check(rc: int, err: str, out: Path, allowed: set[int], signalled: bool) -> str | None:
    lines = [ln for ln in err.splitlines() if ln.strip()]
    if rc not in allowed:
        return f"exit status {rc} (expected one of {sorted(allowed)}); stderr: {err.strip()[:300]!r}"
    if "Traceback" in err or "Warning" in err or "warning" in err:
        return f"stderr is not one clean line: {err.strip()[:300]!r}"
    if rc == 0 and lines:
        return f"success printed to stderr: {err.strip()[:300]!r}"
    if rc != 0 and rc > 0 and len(lines) != 1:
        return f"{len(lines)} lines on stderr (expected 1): {err.strip()[:300]!r}"
    if rc == 2 and not lines[0].startswith("bokehray: error: "):
        return f"error line does not start with 'bokehray: error: ': {lines[0]!r}"
    if rc in (130, 143) and "no partial output was left" not in lines[0]:
        return f"signal line: {lines[0]!r}"
    if _hidden(out.parent):
        return f"temporary files left: {_hidden(out.parent)}"
    if out.exists():

        try:
            br.read_image(out)
        except Exception as e:  # noqa: BLE001
            return f"output exists but is not a complete image: {e}"
        if rc != 0 and not signalled:
            return "an output file exists after a failure"
    return None


def _run_cli(args: list, sig: int | None = None, delay: float = 0.0) -> tuple[int, str]:
    proc = subprocess.Popen([*_CLI, *map(str, args)], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            env=_ENV)
    if sig is not None:
        try:
            proc.wait(timeout=delay)
        except subprocess.TimeoutExpired:
            proc.send_signal(sig)
    try:
        _, err = proc.communicate(timeout=300)
    except subprocess.TimeoutExpired:
        proc.kill()
        _, err = proc.communicate()
        return -999, err + " (killed after 300 s)"
    return proc.returncode, err


def _tmpfs(folder: Path, kb: int) -> bool:
    return os.geteuid() == 0 and subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={kb}k", "tmpfs", str(folder)],
                                                capture_output=True, check=False).returncode == 0


def run_io(n: int, seed: int) -> int:
    rng = np.random.default_rng(seed)
    work = Path(tempfile.mkdtemp(prefix="bokehray-soak-io-"))
    f = _inputs(work)
    t0 = time.perf_counter()
    starts = []
    for _ in range(3):
        t = time.perf_counter()
        _run_cli(["render", work / "missing.png", "--disparity", f["small_d"], "-o", work / "x.png", "--blur", 1,
                  "--focus", 0.5])
        starts.append(time.perf_counter() - t)
    # interpreter, imports, Warp: a signal before main() meets Python's defaults (allowed, counted apart)
    startup = max(starts)
    counts: dict[str, int] = {}
    failures = known = 0
    for i in range(n):
        kind = str(rng.choice(["signal", "signal", "disk", "values"]))
        out_dir = work / f"case{i}"
        out_dir.mkdir()
        ext = str(rng.choice(["png", "png16", "tif", "exr", "jpg"]))
        out = out_dir / f"o.{ext.replace('16', '')}"
        bits = ["--bit-depth", "16"] if ext == "png16" else []
        case = {"i": i, "kind": kind, "ext": ext}
        mounted = False
        try:
            if kind == "signal":
                sig = int(rng.choice([signal.SIGTERM, signal.SIGINT]))
                delay = float(1.2 * startup + rng.uniform(0.0, 3.5))
                case.update(signal=signal.Signals(sig).name, delay=round(delay, 2))
                rc, err = _run_cli(["render", f["big"], "--disparity", f["big_d"], "-o", out, "--blur", 8, "--focus",
                                    0.5, *bits], sig, delay)
                code = 143 if sig == signal.SIGTERM else 130
                allowed, signalled = {0, code, -sig}, True  # -sig: arrived before main() (Python's default)
                if rc == -sig and "KeyboardInterrupt" in err:  # SIGINT during the interpreter's imports (traceback)
                    counts["signal: before main() (Python's default)"] = counts.get(
                        "signal: before main() (Python's default)", 0) + 1
                    err = ""
            elif kind == "disk":
                kb = int(rng.choice([4, 8, 16, 32]))
                mounted = _tmpfs(out_dir, kb)
                if not mounted:
                    counts["disk (skipped: needs root)"] = counts.get("disk (skipped: needs root)", 0) + 1
                    continue
                case.update(tmpfs_kb=kb)
                rc, err = _run_cli(["render", f["small"], "--disparity", f["small_d"], "-o", out, "--blur", 4,
                                    "--focus", 0.5, *bits])
                allowed, signalled = {0, 2}, False
                if rc == 2 and err.strip() != f"bokehray: error: cannot write {out}: No space left on device":
                    err += " (expected the disk-full line)\nX"
            else:
                img = str(rng.choice(["small", "bright1e+30", "bright3e+38", "bright3.4e+38"]))
                disp = str(rng.choice(["small_d", "d64_0.5", "d64_1e+300", "d64_-1e+300", "d64_1e-300"]))
                boost = str(rng.choice(["0", "4", "1e30", "1e38", "1e39"]))
                quality = str(rng.choice(["preview", "raytrace"]))
                case.update(image=img, disparity=disp, boost=boost, quality=quality)
                rc, err = _run_cli(["render", f[img], "--disparity", f[disp], "-o", out, "--blur", 4, "--focus", 0.5,
                                    "--highlight-boost", boost, "--quality", quality, "--max-spp", 4, *bits])
                allowed, signalled = {0, 2}, False
            problem = _check(rc, err, out, allowed, signalled)
            outcome = f"{kind}: exit {rc}"
            counts[outcome] = counts.get(outcome, 0) + 1
            if problem:
                tag = next((v for k, v in _KNOWN.items() if k in err), None)
                if tag:
                    known += 1
                    print(f"KNOWN case {i}: {tag}: {err.strip()[:160]}")
                else:
                    failures += 1
                    print(f"FAIL case {i} (seed {seed}): {problem}\n  case: {json.dumps(case)}")
        finally:
            if mounted:
                subprocess.run(["umount", str(out_dir)], check=False)
    shutil.rmtree(work, ignore_errors=True)
    print("outcomes: " + ", ".join(f"{k} x{v}" for k, v in sorted(counts.items())))
    print(f"soak --io: {n} cases, {failures} failed, {known} known (issue 18.3), startup {startup:.1f} s "
          f"({time.perf_counter() - t0:.1f} s)")
    return 1 if failures else 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=1000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--io", type=int, default=0, metavar="N",
                    help="run N command-line cases (signals, full disks, extreme values) instead of render cases")
    args = ap.parse_args()
    if args.io:
        return run_io(args.io, args.seed)
    rng = np.random.default_rng(args.seed)
    t0, failures = time.perf_counter(), 0
    for i in range(args.cases):
        case = draw_case(rng)
        problem = run_case(case)
        if problem:
            failures += 1
            print(f"FAIL case {i} (seed {args.seed}): {problem}\n  reproduce: run_case({case})")
    print(f"soak: {args.cases - failures} passed, {failures} failed ({time.perf_counter() - t0:.1f} s)")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
