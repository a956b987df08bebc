"""Randomised soak test: render many random, extreme or degenerate cases and report any failure.

Each case draws an image size (1 x 1 upwards), radiance scale (0 to 1e4, denormals included),
a disparity pattern (constant 0 or 1, random, one-pixel steps, a step edge), K (0 to 1e4),
d_f in [0, 1], an aperture, a quality level, the channel count (grey, RGB, RGBA with alpha
exactly 0 and 1), for one case in eight a forced tile size and for one in eight a single depth layer
(``max_layers=1``: near and far pixels in one layer), and checks: no exception,
finite output, output within the input's range (every pixel is an average of input radiances;
float32 rounding of 1e-5 of the brightest value is allowed), energy conservation for
constant-disparity cases with a zero border, and that the tiled render equals the untiled one.
A failure prints a one-line reproducer (seed and case index).

``--io N`` runs N command-line cases instead, each in a fresh process, on the paths
where the CLI meets the operating system: a SIGTERM or SIGINT at a random moment of a real
render and write (PNG 8/16-bit, TIFF, EXR, JPEG); a disk that fills during the write (a tmpfs
of random size below the output's, root only; skipped otherwise); and extreme values (radiance
up to float32's maximum, highlight boosts up to 1e39, float64 disparity of 1e300). Checked:
the exit status is one of those promised (0; 2 with exactly one ``bokehray: error:`` line;
130/143 after a signal with one line), nothing else reaches stderr (no traceback, no warning,
no native library line), no temporary file is left, and an output that exists is complete.

Three kinds of ``--io`` case cover batches, Dask and depth models (docs/robustness.md, "Batches, sweeps and Dask"):
**batch** (focal sweeps whose values %.3f or %g would not tell apart, sweeps with a value out of range,
malformed manifest rows, SIGTERM or SIGINT in the middle of a ``--workers 2`` batch), **dask** (malformed
``--scheduler`` addresses; with ``distributed`` installed, one real local cluster now and then) and
**depth-model** (the tiny Depth Anything and DPT checkpoints of tests/cli_io/test_depth_model.py, intact or with
weights of another ``model_type``, a broken ``preprocessor_config.json``, a 100 000 px input or 100 000 declared
layers; skipped without torch and transformers). Checked: exit 0 with one frame per sweep value and a GIF of as
many frames, or exit 2 with one ``bokehray: error:`` line and nothing written, or after a signal 143/130 with
one line whose count is the frames on disk.

Three more kinds: **periodic** (the default focus of 513-2500 px maps of 1-4 px stripes or checkerboards, half of
them nearest: d 1 holding about half the frame), **strip** (20 000 and 60 000 x 2 px strips at the default amount,
maps of 1-px edges everywhere or of noise: exit 0 with a complete output where the budget holds the render, or exit
2, one line, nothing written, and a peak RSS below ``STRIP_RSS_LIMIT_MB``, measured with ``wait4``; the child's address space is capped at 8 GB to protect the machine)
and **page** (``bokehray view`` exporting a 1.5 MP render at amount 100, then Ctrl-C, SIGTERM or SIGHUP 0-4 s later:
exit 128 + the signal's number, the one line ``bokehray view: stopped``, the export answered 503, or 200 when it finished first, nothing
half-written; the seconds from the signal to the exit are printed).

Usage (from the repository root)::

    python benchmarks/robustness/soak.py --cases 5000          # long soak
    python benchmarks/robustness/soak.py --cases 200 --seed 1  # the short version CI runs
    python benchmarks/robustness/soak.py --io 60 --seed 1      # signals, full disks, extreme values via the CLI
    python benchmarks/robustness/soak.py --io 60 --seed 1 --kinds batch,dask,depth-model  # batches, Dask, depth models
    python benchmarks/robustness/soak.py --io 30 --seed 4 --kinds periodic,strip,page      # periodic maps, strips, the page
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

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import numpy as np

import bokehray as br


def draw_case(rng: np.random.Generator) -> dict:
    h, w = int(rng.choice([1, 2, 3, 7, 16, 33, 64])), int(rng.choice([1, 2, 5, 16, 40, 64]))
    scale = float(rng.choice([0.0, 1e-40, 1e-8, 1.0, 50.0, 1e4]))
    pattern = str(rng.choice(["zero", "one", "random", "steps", "edge", "constant"]))
    k = float(rng.choice([0.0, 1e-6, 0.49, 0.5, 2.0, 9.0, 40.0, 1e4]))
    quality = "raytrace" if rng.random() < 0.15 and k <= 40 and h * w <= 1024 else "preview"
    return {"h": h, "w": w, "scale": scale, "pattern": pattern, "k": k, "d_f": float(rng.choice([0.0, 0.5, 1.0,
            rng.random()])), "blades": int(rng.choice([0, 0, 5, 6])), "curv": float(rng.random()),
            "quality": quality, "border": bool(rng.random() < 0.3), "img_seed": int(rng.integers(1 << 31)),
            "channels": int(rng.choice([3, 3, 1, 4])), "tile": int(rng.choice([16, 24, 40])) if rng.random() < 0.125 else 0,
            "max_layers": 1 if rng.random() < 0.125 else 8}


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
    layers = br.LayerOptions(max_layers=c.get("max_layers", 8))  # 1: near and far pixels in one layer
    try:
        out = br.render(image, d, br.BlurParams(c["k"], c["d_f"]), ap, quality=c["quality"], options=opts,
                        layers=layers)
        tiled = None if not c.get("tile") else br.render(image, d, br.BlurParams(c["k"], c["d_f"]), ap,
                                                           quality=c["quality"], options=opts, layers=layers,
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

_ROOT = Path(__file__).resolve().parents[2]
_ENV = {**os.environ, "PYTHONPATH": os.pathsep.join([str(_ROOT / "src"), str(_ROOT / "kernels"), str(_ROOT / "refiner"),
                                                     os.environ.get("PYTHONPATH", "")])}
_CLI = [sys.executable, "-c", "import sys; from bokehray.app.cli import main; sys.exit(main())"]
_KNOWN = {"renderer produced NaN/Inf": "a known defect: radiance near float32's maximum (tests/stress/test_reliability.py)"}


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
    (folder / "photos").mkdir()
    f["photos_small"] = br.write_image(folder / "photos" / "small.png", small)
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


def _check(rc: int, err: str, out: Path, allowed: set[int], signalled: bool) -> str | None:  # noqa: C901
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


IO_KINDS = ("signal", "disk", "values", "batch", "dask", "depth-model", "periodic", "strip", "page")
_BAD_SCHEDULERS = ("notaurl", "inproc://x", "tls://127.0.0.1:1", "ucx://127.0.0.1:1", "tcp://127.0.0.1:8786/../x", "",
                   "tcp://127.0.0.1:0", "tcp://[::1:8786")
_BAD_MANIFESTS = {"extra field": "image,disparity\nsmall.png,small_d.png,extra\n",
                  "missing field": "image,disparity\nsmall.png\n",
                  "header only": "image,disparity\n", "no columns": "photo,map\nsmall.png,small_d.png\n",
                  "binary": "\x00\xff\xfe,\x00\n"}


def _depth_models(folder: Path) -> dict | None:
    """The tiny checkpoints of tests/cli_io/test_depth_model.py and their broken variants; None without the extra."""
    try:
        import torch
        import transformers
    except ImportError:
        return None
    transformers.logging.set_verbosity_error()
    transformers.utils.logging.disable_progress_bar()
    from bokehray.photo.depth_model import tiny_configs

    torch.manual_seed(0)
    cfg, dpt = tiny_configs()
    transformers.DepthAnythingForDepthEstimation(cfg).eval().save_pretrained(folder / "da")
    transformers.DPTForDepthEstimation(dpt).eval().save_pretrained(folder / "dpt")
    variants = {"da": (None, None), "dpt": (None, None),
                "da as dpt": (lambda c: c.update(model_type="dpt"), None),
                "dpt as da": (lambda c: c.update(model_type="depth_anything"), None),
                "processor a list": (None, [56, 56]), "size '56'": (None, {"size": "56"}),
                "image_mean of 1": (None, {"image_mean": [0.5]}),
                "size 100000": (None, {"size": {"height": 100000, "width": 100000}}),
                "100000 layers": (lambda c: c["backbone_config"].update(num_hidden_layers=100000), None)}
    out = {}
    for name, (edit, pre) in variants.items():
        src = folder / ("dpt" if name.startswith("dpt") else "da")
        dst = folder / name.replace(" ", "_").replace("'", "")
        if dst != src:
            shutil.copytree(src, dst)
        if edit is not None:
            c = json.loads((dst / "config.json").read_text())
            edit(c)
            (dst / "config.json").write_text(json.dumps(c))
        if pre is not None:
            (dst / "preprocessor_config.json").write_text(json.dumps(pre))
        out[name] = dst
    return out


def _check_batch(rc: int, err: str, out: Path, allowed: set[int], frames: int | None) -> str | None:  # noqa: C901
    """A batch's promises: exit 0 with ``frames`` frames and a GIF of as many; 2 with one error line and nothing
    written; 130/143 after a signal with one line whose count is the frames on disk."""
    lines = [ln for ln in err.splitlines() if ln.strip()]
    if rc not in allowed:
        return f"exit status {rc} (expected one of {sorted(allowed)}); stderr: {err.strip()[:300]!r}"
    if "Traceback" in err or "arning" in err:
        return f"stderr is not clean: {err.strip()[:300]!r}"
    pngs = sorted(out.glob("*.png")) if out.is_dir() else []
    if _hidden(out) if out.is_dir() else False:
        return f"temporary files left: {_hidden(out)}"
    if rc == 0:
        if lines:
            return f"success printed to stderr: {err.strip()[:300]!r}"
        if frames is not None:
            from PIL import Image

            gifs = sorted(out.glob("*.gif"))
            if len(pngs) != frames or len(gifs) != 1:
                return f"{len(pngs)} frames and GIFs {[g.name for g in gifs]} for {frames} sweep values"
            # Pillow merges identical consecutive frames into one of their summed duration: count the time
            with Image.open(gifs[0]) as gif:
                shown = 0
                for k in range(gif.n_frames):
                    gif.seek(k)
                    shown += gif.info["duration"]
            if abs(shown - frames * round(1000 / 6)) > 10 * frames:  # GIF stores durations in 10 ms units
                return f"the GIF shows {shown} ms for {frames} frames of {round(1000 / 6)} ms"
    elif rc == 2:
        if len(lines) != 1 or not lines[0].startswith("bokehray: error: "):
            return f"not one error line: {err.strip()[:300]!r}"
        if pngs:
            return f"files written before the refusal: {[p.name for p in pngs]}"
    elif rc in (130, 143):
        words = "terminated (SIGTERM)" if rc == 143 else "interrupted"
        head = f"bokehray: {words} after {len(pngs)} of "
        if len(lines) != 1 or not lines[0].startswith(head):
            return f"signal line {lines!r}; expected it to start {head!r} ({len(pngs)} frames on disk)"
    return None


def _sweep_case(case: dict, rng: np.random.Generator, f: dict, out: Path, common: list):
    """A focal sweep whose values lie closer than a frame's name can tell apart: it must still write them all."""
    flag, values = [("--focus", "0.1,0.1004"), ("--focus", f"0.1:0.9:{int(rng.integers(2, 40))}"),
                    ("--blur", "24,24.0000001"), ("--focus", "0.25,0.2500001,0.25000001")][int(rng.integers(4))]
    other = ["--blur", 4] if flag == "--focus" else ["--focus", 0.5]
    case.update(sweep=f"{flag}={values}")
    n = len(values.split(",")) if ":" not in values else int(values.split(":")[2])
    rc, err = _run_cli(["render", f["small"], "--disparity", f["small_d"], "-o", out, f"{flag}={values}", *other,
                        *common])
    return case, (rc, err), _check_batch(rc, err, out, {0}, n)


def _refused_batch_case(case: dict, what: str, rng: np.random.Generator, f: dict, out: Path, common: list):
    """A sweep out of range or a bad manifest: refused in one line, nothing written."""
    if what == "out of range":
        sweep = str(rng.choice(["--focus=0:2:3", "--focus=-0.5,0.5", "--blur=-1,4", "--blur=4,1e6"]))
        other = ["--blur", 4] if sweep.startswith("--focus") else ["--focus", 0.5]
        case.update(sweep=sweep)
        rc, err = _run_cli(["render", f["small"], "--disparity", f["small_d"], "-o", out, sweep, *other, *common])
        return case, (rc, err), _check_batch(rc, err, out, {2}, None)
    name = str(rng.choice(sorted(_BAD_MANIFESTS)))
    manifest = out.parent / f"{out.name}.csv"
    manifest.write_text(_BAD_MANIFESTS[name], errors="surrogateescape")
    case.update(manifest=name)
    rc, err = _run_cli(["render", f["small"].parent / "photos", "--disparity", manifest, "-o", out,
                        "--blur", 4, "--focus", 0.5, *common])
    return case, (rc, err), _check_batch(rc, err, out, {2}, None)


def _signalled_batch_case(case: dict, rng: np.random.Generator, f: dict, out: Path, startup: float):
    """A sweep stopped by SIGTERM or SIGINT at a random moment: its exit code and line, its frames on disk."""
    sig = int(rng.choice([signal.SIGTERM, signal.SIGINT]))
    delay = float(1.5 * startup + rng.uniform(0.0, 6.0))
    case.update(signal=signal.Signals(sig).name, delay=round(delay, 2))
    rc, err = _run_cli(["render", f["big"], "--disparity", f["big_d"], "-o", out, "--blur", 8,
                        "--focus", "0.1:0.9:6", "--workers", 2, "--quiet"], sig, delay)
    code = 143 if sig == signal.SIGTERM else 130
    if rc == -sig:  # before main() installed its handlers: Python's default, as the single-file cases count it
        return case, (rc, ""), None
    return case, (rc, err), _check_batch(rc, err, out, {0, code}, 6 if rc == 0 else None)


def _batch_case(rng: np.random.Generator, f: dict, out: Path, startup: float):
    common = ["--workers", 1, "--quiet"]
    what = str(rng.choice(["close sweep", "close sweep", "out of range", "manifest", "signal"]))
    case = {"kind": "batch", "what": what}
    if what == "close sweep":
        return _sweep_case(case, rng, f, out, common)
    if what in ("out of range", "manifest"):
        return _refused_batch_case(case, what, rng, f, out, common)
    return _signalled_batch_case(case, rng, f, out, startup)


def _dask_case(rng: np.random.Generator, f: dict, out: Path):
    """A local Dask cluster (it must render), or a scheduler address that is wrong (refused, nothing made)."""
    try:
        import distributed  # noqa: F401
    except ImportError:
        return None
    if rng.random() < 0.15:
        case = {"kind": "dask", "what": "local cluster"}
        rc, err = _run_cli(["render", f["small"], "--disparity", f["small_d"], "-o", out, "--blur", 4,
                            "--focus", "0.3,0.6", "--executor", "dask", "--workers", 2, "--quiet"])
        return case, (rc, err), _check_batch(rc, err, out, {0}, 2)
    address = str(rng.choice(_BAD_SCHEDULERS))
    case = {"kind": "dask", "scheduler": address}
    rc, err = _run_cli(["render", f["small"], "--disparity", f["small_d"], "-o", out, "--blur", 4,
                        "--focus", "0.3,0.6", "--executor", "dask", f"--scheduler={address}", "--quiet"])
    problem = _check_batch(rc, err, out, {2}, None) or (f"{out} was created" if out.exists() else None)
    return case, (rc, err), problem


def _depth_model_case(rng: np.random.Generator, f: dict, out: Path, models: dict):
    """A depth-model checkpoint, good or broken: rendered, or refused naming its folder."""
    name = str(rng.choice(sorted(models)))
    case = {"kind": "depth-model", "checkpoint": name}
    target = out / "o.png"
    out.mkdir()
    rc, err = _run_cli(["render", f["small"], "--depth-model", models[name], "-o", target, "--blur", 4,
                        "--focus", 0.5, "--quiet"])
    good = name in ("da", "dpt")
    problem = _check(rc, err, target, {0} if good else {2}, False)
    if problem is None and not good and str(models[name]) not in err:
        problem = f"the error does not name the checkpoint folder: {err.strip()!r}"
    return case, (rc, err), problem


def _extras_case(kind: str, rng: np.random.Generator, f: dict, out: Path, models: dict | None,
                 startup: float) -> tuple[dict, tuple[int, str], str | None] | None:
    """One batch, dask or depth-model case: (case, (exit, stderr), problem), or None when it cannot run here."""
    if kind == "batch":
        return _batch_case(rng, f, out, startup)
    if kind == "dask":
        return _dask_case(rng, f, out)
    return None if models is None else _depth_model_case(rng, f, out, models)


# --------------------------------------------------------------------------- --io: periodic maps, strips, the page

STRIP_RSS_LIMIT_MB = 1024
"""A strip the budget cannot hold is refused before this much is allocated (docs/robustness.md)."""
PAGE_EXIT_S = 2.0
"""The page stops this soon after Ctrl-C, SIGTERM or SIGHUP, whatever stage its export is in (reported; a case
fails only past HANG_S, a busy machine's hang detector)."""
HANG_S = 90.0
_VIEW_STOPPED = "bokehray view: stopped"


def _periodic_case(rng: np.random.Generator) -> tuple[dict, str | None]:
    """The default focus of a map of 1-4 px stripes or a checkerboard above 512 px, half of it nearest: it must see
    both halves (a regular subsampling grid saw one phase: "100 % at d 0")."""
    from bokehray.photo.subject import subject_focus

    side, period = int(rng.integers(513, 2500)), int(rng.integers(1, 5))
    pattern = str(rng.choice(["columns", "rows", "checker"]))
    yy, xx = np.mgrid[:side, :side]
    phase = {"columns": xx, "rows": yy, "checker": xx + yy}[pattern]
    d = ((phase // period) % 2).astype(np.float32)
    s = subject_focus(d)
    case = {"kind": "periodic", "side": side, "period": period, "pattern": pattern}
    if s.d_f != 1.0 or not 0.4 < s.share < 0.6:
        return case, f"default focus d_f {s.d_f:g} holding {s.share:.0%} of the frame (expected d 1, about half)"
    return case, None


def _run_measured(args: list, limit_gb: float = 8.0) -> tuple[int, str, float]:
    """The CLI in a child whose address space is capped (a safety net for this machine), and its peak RSS in MB."""
    import resource

    def cap() -> None:
        resource.setrlimit(resource.RLIMIT_AS, (int(limit_gb * 2**30),) * 2)

    proc = subprocess.Popen([*_CLI, *map(str, args)], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            env=_ENV, preexec_fn=cap)
    deadline = time.monotonic() + 300
    while True:  # reaped here, not by Popen: wait4 gives the child's peak RSS
        pid, status, usage = os.wait4(proc.pid, os.WNOHANG)
        if pid:
            break
        if time.monotonic() > deadline:
            proc.kill()
        time.sleep(0.05)
    proc.returncode = os.waitstatus_to_exitcode(status)
    return proc.returncode, proc.stderr.read(), usage.ru_maxrss / 1024


def _strip_case(rng: np.random.Generator, folder: Path) -> tuple[dict, tuple[int, str], str | None]:
    """A W x 2 strip at the default amount (a CoC of thousands of px), with a map of 1-px edges everywhere or of
    noise: rendered (exit 0, where the budget holds it) or refused in one line (exit 2) before STRIP_RSS_LIMIT_MB is
    allocated."""
    w = int(rng.choice([20000, 60000]))
    kind = str(rng.choice(["checker", "noise"]))
    img, d = folder / f"strip{w}.png", folder / f"strip{w}_{kind}.png"
    if not img.exists():
        br.write_image(img, np.random.default_rng(w).random((2, w, 3)).astype(np.float32))
    if not d.exists():
        x = np.indices((2, w)).sum(0)
        br.write_disparity(d, ((x % 2) if kind == "checker" else np.random.default_rng(1).random((2, w))).astype(np.float32))
    out = folder / "strip-out.png"
    rc, err, peak = _run_measured(["render", img, "--disparity", d, "-o", out])
    case = {"kind": "strip", "width": w, "map": kind, "peak_rss_mb": round(peak)}
    # a strip is all border: a checkerboard puts half of its border on the nearest values, which the reversed-map
    # check rightly says (bokehray's own one-line warning, not a failure here)
    err = "\n".join(ln for ln in err.splitlines() if not ln.startswith("bokehray: warning: ") or
                     "the map looks reversed" not in ln)
    problem = _check(rc, err, out, {0, 2}, False)
    if problem is None and rc == 2 and peak > STRIP_RSS_LIMIT_MB:
        problem = f"refused after a peak of {peak:.0f} MB (more than {STRIP_RSS_LIMIT_MB} MB)"
    out.unlink(missing_ok=True)
    return case, (rc, err), problem


def _page_export(url: str, answers: dict) -> None:
    import urllib.error
    import urllib.request

    body = json.dumps({"params": {"amount": 100}, "format": "exr"}).encode()
    req = urllib.request.Request(url + "api/export", data=body, headers={"Content-Type": "application/json"})
    try:
        with urllib.request.urlopen(req, timeout=HANG_S) as r:
            answers["export"] = r.status
    except urllib.error.HTTPError as e:
        answers["export"] = e.code
    except OSError as e:  # the server went before it answered
        answers["export"] = f"no answer ({e})"


def _page_case(rng: np.random.Generator, f: dict, out: Path) -> tuple[dict, tuple[int, str], str | None]:
    """``bokehray view`` exporting a 1.5 MP render at amount 100; Ctrl-C, SIGTERM or SIGHUP at a random moment of the
    export (its edge estimate, matting, planning or layers). Checked: exit 128 + the signal's number, the one line ``bokehray view: stopped``,
    the export answered 503 (or 200 when it finished first), no file half-written; the seconds from the signal to
    the exit are reported."""
    import threading

    out.mkdir()
    sig = int(rng.choice([signal.SIGINT, signal.SIGTERM, signal.SIGHUP]))
    delay = float(rng.uniform(0.0, 4.0))
    edges = bool(rng.random() < 0.5)  # a patch of 1-px depth edges: seconds of edge estimate and matting
    if edges and "big_edges_d" not in f:
        d = np.tile(np.linspace(0, 1, 1500, dtype=np.float32), (1000, 1))
        d[300:700, 500:1000] = np.random.default_rng(2).random((400, 500)) > 0.5
        f["big_edges_d"] = br.write_disparity(out.parent / "big_edges_d.png", d)
    proc = subprocess.Popen([*_CLI, "view", str(f["big"]), "--disparity", str(f["big_edges_d" if edges else "big_d"]),
                             "--export-dir", str(out)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=_ENV)
    case: dict = {"kind": "page", "signal": signal.Signals(sig).name, "delay": round(delay, 2), "edges": edges}
    answers: dict = {}
    try:
        line = proc.stdout.readline()
        if not line.startswith("bokehray view: http://"):
            proc.kill()
            return case, (proc.wait(), proc.stderr.read()), f"no URL printed: {line!r}"
        t = threading.Thread(target=_page_export, args=(line.split()[2], answers), daemon=True)
        t.start()
        time.sleep(delay)
        t_sig = time.monotonic()
        proc.send_signal(sig)
        try:
            _, err = proc.communicate(timeout=HANG_S)
        except subprocess.TimeoutExpired:
            proc.kill()
            _, err = proc.communicate()
            return case, (-999, err), f"still running {HANG_S:g} s after {case['signal']}"
        case["exit_s"] = round(time.monotonic() - t_sig, 2)
        t.join(HANG_S)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    case["export"] = answers.get("export")
    problem = None
    if proc.returncode != 128 + int(sig) or err.strip() != _VIEW_STOPPED:
        problem = (f"exit {proc.returncode}, stderr {err.strip()[:300]!r} (expected {128 + int(sig)} and "
                   f"{_VIEW_STOPPED!r})")
    elif answers.get("export") not in (200, 503):
        problem = f"the export was answered {answers.get('export')!r} (expected 503, or 200 when done first)"
    elif answers.get("export") == 503 and list(out.iterdir()):
        problem = f"files left by an abandoned export: {sorted(p.name for p in out.iterdir())}"
    return case, (proc.returncode, err), problem


def _map_or_page_case(kind: str, rng: np.random.Generator, f: dict, out: Path
                     ) -> tuple[dict, tuple[int, str], str | None]:
    """One periodic, strip or page case: (case, (exit, stderr), problem)."""
    if kind == "periodic":
        case, problem = _periodic_case(rng)
        return case, (0, ""), problem
    if kind == "strip":
        return _strip_case(rng, out.parent)
    return _page_case(rng, f, out)


def run_io(n: int, seed: int, kinds: tuple[str, ...] = IO_KINDS) -> int:  # noqa: C901
    rng = np.random.default_rng(seed)
    work = Path(tempfile.mkdtemp(prefix="bokehray-soak-io-"))
    f = _inputs(work)
    models = _depth_models(work / "models") if "depth-model" in kinds else None
    draw = [k for k in ("signal", "signal", "disk", "values", "batch", "batch", "dask", "depth-model", "periodic",
                        "strip", "page", "page") if k in kinds]
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
    page_exits: list[float] = []
    failures = known = 0
    for i in range(n):
        kind = str(rng.choice(draw))
        if kind in ("periodic", "strip", "page"):
            case, (rc, err), problem = _map_or_page_case(kind, rng, f, work / f"case{i}")
            outcome = f"{kind}: exit {rc}" + (f" ({case['export']})" if kind == "page" else "")
            counts[outcome] = counts.get(outcome, 0) + 1
            if "exit_s" in case:
                page_exits.append(case["exit_s"])
            if problem:
                failures += 1
                print(f"FAIL case {i} (seed {seed}): {problem}\n  case: {json.dumps(case)}")
            continue
        if kind in ("batch", "dask", "depth-model"):
            ran = _extras_case(kind, rng, f, work / f"case{i}", models, startup)
            if ran is None:
                counts[f"{kind} (skipped: needs its extra)"] = counts.get(f"{kind} (skipped: needs its extra)", 0) + 1
                continue
            case, (rc, err), problem = ran
            outcome = f"{kind}: exit {rc}"
            counts[outcome] = counts.get(outcome, 0) + 1
            if problem:
                failures += 1
                print(f"FAIL case {i} (seed {seed}): {problem}\n  case: {json.dumps(case)}")
            continue
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
                case.update(image=img, disparity=disp, boost=boost)
                rc, err = _run_cli(["render", f[img], "--disparity", f[disp], "-o", out, "--blur", 4, "--focus", 0.5,
                                    "--highlight-boost", boost, *bits])
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
    if page_exits:
        print(f"page: exit after the signal in {min(page_exits):.2f}..{max(page_exits):.2f} s (median "
              f"{float(np.median(page_exits)):.2f} s, {sum(t > PAGE_EXIT_S for t in page_exits)} of {len(page_exits)} "
              f"over {PAGE_EXIT_S:g} s)")
    print(f"soak --io: {n} cases, {failures} failed, {known} known defects, startup {startup:.1f} s "
          f"({time.perf_counter() - t0:.1f} s)")
    return 1 if failures else 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=1000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--io", type=int, default=0, metavar="N",
                    help="run N command-line cases (signals, full disks, extreme values, batches, Dask, depth "
                    "models) instead of render cases")
    ap.add_argument("--kinds", default=",".join(IO_KINDS),
                    help=f"--io: the kinds of case to draw from (default: all of {','.join(IO_KINDS)})")
    args = ap.parse_args()
    if args.io:
        kinds = tuple(k for k in args.kinds.split(",") if k)
        if not kinds or set(kinds) - set(IO_KINDS):
            ap.error(f"--kinds: expected some of {','.join(IO_KINDS)}, got {args.kinds!r}")
        return run_io(args.io, args.seed, kinds)
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
