"""Randomised soak test: render many random, extreme or degenerate cases and report any failure.

Each case draws an image size (1 x 1 upwards), radiance scale (0 to 1e4, denormals included),
a disparity pattern (constant 0 or 1, random, one-pixel steps, a step edge), K (0 to 1e4),
d_f in [0, 1], an aperture, a quality level, the channel count (grey, RGB, RGBA with alpha
exactly 0 and 1) and, for one case in eight, a forced tile size, and checks: no exception,
finite output, output within the input's range (every pixel is an average of input radiances;
float32 rounding of 1e-5 of the brightest value is allowed), energy conservation for
constant-disparity cases with a zero border, and that the tiled render equals the untiled one.
A failure prints a one-line reproducer (seed and case index).

Usage (from the repository root)::

    python benchmarks/soak.py --cases 5000          # long soak
    python benchmarks/soak.py --cases 200 --seed 1  # the short version CI runs
"""

from __future__ import annotations

import argparse
import sys
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


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=1000)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
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
