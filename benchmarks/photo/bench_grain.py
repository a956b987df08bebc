"""Grain kept: the high-pass of the blurred backdrop against the photo's, with and without the grain step.

The astronaut portrait (``benchmarks/photo/portrait.py``) at ``--side`` px with sensor-like grain added (seeded Gaussian
noise of ``--noise`` 8-bit codes per channel, as a phone's or a camera's JPEG holds it), written as an 8-bit PNG
with its painted map, is rendered by ``bokehray render`` at its defaults (the eyes' focus, ``--amount 50``) with
and without ``--no-grain``. Measured on the 8-bit outputs: the standard deviation of a 2 px high-pass (the luma
minus a Gaussian of sigma 2 px, in codes) over a box of backdrop between the head and the shuttle model (strongly
blurred: CoC about 32 px at 1024 px), against the same box of the photo. Also saved: 100 % crops (photo, without
grain, with grain) for docs/usage.md.

``--time MP``: the step's cost on a frame of that size (random photo, a CoC of 12 px everywhere: the grain restored
on every pixel, its worst case): medians of three warm runs of planning (measure and the share to restore) and of
the restore, wall and CPU (all threads), with the load.

Usage (from the repository root)::

    python benchmarks/photo/bench_grain.py --figure docs/img/grain_crops.png   # JSON to benchmarks/results/grain.json
    python benchmarks/photo/bench_grain.py --time 12                          # the cost at 12 MP only
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import numpy as np

import bokehray as br
from benchmarks.photo.portrait import portrait
from bokehray.app.cli import main as cli
from bokehray.colour import linear_to_srgb

ROOT = Path(__file__).resolve().parents[2]
BOX_1024 = (620, 40, 700, 200)  # backdrop between the head and the shuttle (x0, y0, x1, y1 at 1024 px)


def highpass_std(codes: np.ndarray, box: tuple[int, int, int, int]) -> float:
    import cv2

    luma = codes.astype(np.float32) @ np.array([0.2126, 0.7152, 0.0722], np.float32)
    hp = luma - cv2.GaussianBlur(luma, (0, 0), 2.0)
    x0, y0, x1, y1 = box
    return float(hp[y0:y1, x0:x1].std())


def time_step(megapixels: float) -> dict:
    """Medians of three warm runs of the grain step's planning and restore on a ``megapixels`` frame."""
    import os
    import statistics
    import time

    from bokehray.photo.grain import plan_grain, restore_grain

    h = int(round((megapixels * 1e6 * 3 / 4) ** 0.5))
    w = int(round(h * 4 / 3))
    img = np.random.default_rng(0).random((h, w, 3), dtype=np.float32)
    coc = np.full((h, w), 12.0, np.float32)
    plan = plan_grain(img, coc)
    rows = {}
    for name, step in (("plan", lambda: plan_grain(img, coc)),
                       ("restore", lambda: restore_grain(img.copy(), plan.grain, plan.removed, dither_bits=8))):
        times = []
        for _ in range(4):
            t, c = time.perf_counter(), time.process_time()
            step()
            times.append((time.perf_counter() - t, time.process_time() - c))
        rows[name] = {"wall_s": round(statistics.median(x[0] for x in times[1:]), 3),
                      "cpu_s": round(statistics.median(x[1] for x in times[1:]), 3)}
    return {"frame": [w, h], "cores": os.cpu_count(), "load": round(os.getloadavg()[0], 1), **rows}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--side", type=int, default=1024)
    ap.add_argument("--noise", type=float, nargs="+", default=[0.6, 1.5], help="grain added, in 8-bit codes")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks/results/grain.json")
    ap.add_argument("--figure", type=Path)
    ap.add_argument("--time", type=float, metavar="MP", help="only time the step on a frame of MP megapixels")
    args = ap.parse_args()
    if args.time:
        print(json.dumps(time_step(args.time)))
        return
    from PIL import Image

    img, d = portrait(args.side)
    s = args.side / 1024
    box = tuple(round(v * s) for v in BOX_1024)
    results = {"side": args.side, "box": box, "runs": []}
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        br.write_disparity(tmp / "d.png", d)
        for noise in args.noise:
            rng = np.random.default_rng(1)
            codes = np.clip(np.round(linear_to_srgb(img) * 255 + rng.normal(0, noise, img.shape)), 0, 255)
            Image.fromarray(codes.astype(np.uint8)).save(tmp / "p.png")
            row = {"noise_codes": noise, "photo": round(highpass_std(codes, box), 3)}
            shots = {"photo": codes.astype(np.uint8)}
            for name, extra in (("without grain", ["--no-grain"]), ("with grain (default)", [])):
                out = tmp / f"{len(extra)}.png"
                assert cli(["render", str(tmp / "p.png"), "--disparity", str(tmp / "d.png"), "-o", str(out), "--quiet",
                            *extra]) == 0
                shots[name] = np.asarray(Image.open(out))
                row[name] = round(highpass_std(shots[name], box), 3)
            row["with grain / photo"] = round(row["with grain (default)"] / row["photo"], 3)
            row["without grain / photo"] = round(row["without grain"] / row["photo"], 3)
            results["runs"].append(row)
            print(row, flush=True)
            if args.figure and noise == args.noise[-1]:
                y0, x0 = round(60 * s), round(500 * s)  # the face's edge and the backdrop, 100 %
                crops = [a[y0 : y0 + 160, x0 : x0 + 240] for a in shots.values()]
                gap = np.full((160, 6, 3), 255, np.uint8)
                strip = np.concatenate([crops[0], gap, crops[1], gap, crops[2]], axis=1)
                args.figure.parent.mkdir(parents=True, exist_ok=True)
                Image.fromarray(strip).save(args.figure)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=1) + "\n")


if __name__ == "__main__":
    main()
