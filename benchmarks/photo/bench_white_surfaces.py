"""Clipped white surfaces are not lights: the highlight reconstruction on a white helmet and a white shirt.

Two display-referred inputs, each rendered with the preview at the default blur (``--amount 50``) and the default
focus, written as 8-bit sRGB, with

* no reconstruction (``--no-highlight-reconstruction``),
* every clipped region with a white core taken for a light (the rule before white surfaces were told apart:
  ``LIGHT_MAX_SHARE = 1``),
* the reconstruction of lights only (the default: ``bokehray.photo.highlights.is_light``).

Counted: *bright coloured pixels*, those with CIELAB L* >= 70 and chroma C*ab > 25 (pink, cyan and green specks on
a white rim are such pixels) within 8 px (at 512 px; scaled with the side) of a clipped pixel, in the input and
in each output; and the mean brightness (linear) of the output over
the clipped pixels' neighbourhood, where a white surface taken for a light glows.

Inputs: the astronaut portrait (``benchmarks/photo/portrait.py``; its white helmet rim and visor clip) at ``--side``, and a
synthetic white shirt: a clipped fabric of radiance 1.0-1.9 (folds) with a faint warm cast, in front of a grey
backdrop, with photo noise, stored as 8-bit sRGB.

Usage (from the repository root)::

    python benchmarks/photo/bench_white_surfaces.py          # JSON to benchmarks/results/white_surfaces.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import numpy as np

import bokehray as br
from benchmarks.photo.portrait import portrait
from bokehray.colour import linear_to_srgb, srgb_to_linear
from bokehray.photo import highlights
from bokehray.photo.subject import AMOUNT_DEFAULT, default_focus, k_from_amount

ROOT = Path(__file__).resolve().parents[2]


def codes8(img: np.ndarray) -> np.ndarray:
    return np.round(linear_to_srgb(np.clip(img[..., :3], 0.0, 1.0)) * 255.0).astype(np.uint8)


def bright_coloured(img: np.ndarray, near: np.ndarray) -> int:
    """Pixels of the 8-bit sRGB image with L* >= 70 and C*ab > 25, among the pixels ``near`` the clipped ones."""
    from skimage.color import rgb2lab

    lab = rgb2lab(codes8(img))
    return int(((lab[..., 0] >= 70) & (np.hypot(lab[..., 1], lab[..., 2]) > 25) & near).sum())


def white_shirt(side: int = 512) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(5)
    yy, xx = np.mgrid[:side, :side] / side
    shirt = (np.abs(xx - 0.5) < 0.28) & (yy > 0.3)
    folds = 1.45 + 0.45 * np.sin(18 * xx + 4 * yy) * np.cos(7 * yy)
    hdr = np.where(shirt[..., None], folds[..., None] * np.array([1.0, 0.94, 0.86]), 0.18)
    codes = np.round(linear_to_srgb(np.clip(hdr, 0, 1)) * 255 + rng.normal(0, 1.2, hdr.shape))
    img = srgb_to_linear(np.clip(codes, 0, 255) / 255.0).astype(np.float32)
    d = np.where(shirt, 0.8, 0.2).astype(np.float32)
    return img, d


def measure(img: np.ndarray, d: np.ndarray) -> dict:
    k = k_from_amount(AMOUNT_DEFAULT, *d.shape)
    blur = br.BlurParams(k, default_focus(img, d).d_f)
    clipped = (img[..., :3] >= highlights.CLIP_LEVEL).any(axis=2)
    near = highlights.dilate8(clipped, max(8, round(8 * d.shape[0] / 512)))  # 8 px at 512, scaled with the side
    result = {"input": {"bright_coloured": bright_coloured(img, near)}}
    share = highlights.LIGHT_MAX_SHARE
    variants = {"no reconstruction": None, "every white-cored region a light (before)": 1.0,
                "lights only (default)": share}
    try:
        for name, light_share in variants.items():
            src = img
            if light_share is not None:
                highlights.LIGHT_MAX_SHARE = light_share
                src, found = highlights.reconstruct_highlights(img)
            out = br.render(src, d, blur)
            result[name] = {"bright_coloured": bright_coloured(out, near),
                            "mean_at_clipped": round(float(out[clipped].mean()), 4),
                            "lights": 0 if light_share is None else found}
    finally:
        highlights.LIGHT_MAX_SHARE = share
    base = max(1, result["input"]["bright_coloured"])
    for name in variants:
        result[name]["x_input"] = round(result[name]["bright_coloured"] / base, 2)
    return result


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--side", type=int, default=1024)
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks/results/white_surfaces.json")
    args = ap.parse_args()
    results = {"side": args.side, "astronaut portrait": measure(*portrait(args.side)),
               "white shirt": measure(*white_shirt(args.side))}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=1) + "\n")
    print(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
