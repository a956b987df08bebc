"""The default focus on a portrait at 12 MP: the eyes of the nearest face against the subject search.

The astronaut portrait with its painted map (``benchmarks/photo/portrait.py``: the head painted at 0.839 behind the chest
at 0.859) scaled to ``--side`` (3464: 12.0 MP) is rendered with the preview at the default blur (``--amount 50``),
focused (a) by the subject search alone (``subject_focus``: the chest) and (b) by the default focus
(``default_focus``: the eyes of the nearest face). *Eye detail* is the mean Sobel gradient magnitude of the sRGB
luma (8-bit codes) in the eyes' box, in the render over the same in the photo: 100 % is the photo's own sharpness.
Also timed: the face and eye detection at that size (the median of 3 runs). ``--noise N`` adds seeded Gaussian
grain of N 8-bit codes to the upscaled photo (a 512 px photo scaled up holds no detail finer than its 7 px
pixels; a camera's 12 MP file has grain and detail at every scale).

Usage (from the repository root)::

    python benchmarks/photo/bench_eyes.py            # JSON to benchmarks/results/eyes.json
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import numpy as np

import bokehray as br
from benchmarks.photo.portrait import EYES_512, portrait
from bokehray.colour import linear_to_srgb
from bokehray.photo.subject import AMOUNT_DEFAULT, default_focus, k_from_amount, subject_focus

ROOT = Path(__file__).resolve().parents[2]


def eye_detail(img: np.ndarray, box: tuple[int, int, int, int]) -> float:
    from scipy.ndimage import sobel

    x0, y0, x1, y1 = box
    luma = linear_to_srgb(np.clip(img[y0:y1, x0:x1, :3], 0, 1)) @ np.array([0.2126, 0.7152, 0.0722]) * 255.0
    return float(np.hypot(sobel(luma, 0), sobel(luma, 1))[1:-1, 1:-1].mean())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--side", type=int, default=3464)
    ap.add_argument("--noise", type=float, default=0.0, help="grain added to the photo, in 8-bit codes")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    img, d = portrait(args.side)
    if args.noise > 0:
        from bokehray.colour import srgb_to_linear

        codes = linear_to_srgb(img) * 255.0 + np.random.default_rng(2).normal(0, args.noise, img.shape)
        img = srgb_to_linear(np.clip(np.round(codes), 0, 255) / 255.0).astype(np.float32)
    out_path = args.out or ROOT / f"benchmarks/results/eyes{f'-noise{args.noise:g}' if args.noise else ''}.json"
    s = args.side / 512
    box = tuple(round(v * s) for v in EYES_512)
    k = k_from_amount(AMOUNT_DEFAULT, *d.shape)
    times = []
    for _ in range(3):
        t = time.perf_counter()
        eyes = default_focus(img, d)
        times.append(time.perf_counter() - t)
    subject = subject_focus(d)
    base = eye_detail(img, box)
    result = {"side": args.side, "noise_codes": args.noise, "megapixels": round(args.side**2 / 1e6, 2), "K_px": round(k, 2),
              "detect_seconds_median": round(sorted(times)[1], 3), "eyes_box": box, "input_eye_detail": round(base, 3)}
    for name, focus in (("subject search (chest)", subject), ("default focus (eyes)", eyes)):
        t = time.perf_counter()
        out = br.render(img, d, br.BlurParams(k, focus.d_f))
        result[name] = {"d_f": round(focus.d_f, 4), "at": [focus.x, focus.y], "line": focus.describe(),
                        "coc_at_eyes_px": round(k * abs(float(np.median(d[box[1]:box[3], box[0]:box[2]])) - focus.d_f), 2),
                        "eye_detail_share": round(eye_detail(out, box) / base, 4),
                        "render_seconds": round(time.perf_counter() - t, 1)}
        print(name, result[name], flush=True)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    out_path.write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
