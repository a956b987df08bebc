"""PISA stress: masks against the float64 oracle and attention in float32/16/bf16 against float64, on random extremes.

Reports the worst errors found and any non-finite output (there must be none).

    python benchmarks/robustness/stress_pisa.py --cases 200 --out benchmarks/results/stress-pisa.json
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/common.py
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tests"))

from common import REPO, machine_info, write_json


def random_disparity(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    kind = rng.integers(4)
    if kind == 0:  # two depths with a step, values at the singular ends 0 and 1
        d = np.full((h, w), rng.choice([0.0, 1e-7, 0.3]), np.float32)
        d[rng.integers(h):, rng.integers(w):] = rng.choice([1.0, 1 - 1e-7, 0.9])
        return d
    if kind == 1:
        return rng.uniform(0, 1, (h, w)).astype(np.float32)
    if kind == 2:
        return np.full((h, w), rng.choice([0.0, 1.0, 0.5]), np.float32)
    return np.clip(np.linspace(0, 1, w)[None, :] + 0.0 * np.arange(h)[:, None], 0, 1).astype(np.float32)


def masks_case(rng: np.random.Generator) -> dict:
    from bokehray_refiner.pisa import PisaMaskOptions, pisa_masks
    from reference import pisa_ref as ref

    h, w = int(rng.integers(1, 8)), int(rng.integers(1, 8))
    d = random_disparity(rng, h, w)
    d_f = float(rng.choice([0.0, 1.0, rng.uniform()]))
    k = float(rng.choice([0.0, 1e-6, 1.0, 5.0, 50.0]))
    model = str(rng.choice(["thin_lens", "paper"]))
    hardness = float(rng.choice([1.0, 10.0, 1e6, 1e12]))
    opts = PisaMaskOptions(collinear=model, hardness=hardness, max_window=4, n_sources=2, n_steps=4)
    m = pisa_masks(d, d_f, k, opts)
    coc, vis = m.numpy()
    inside = ref.window_to_dense(np.ones_like(coc), m.window) > 0
    c_err = np.abs(ref.window_to_dense(coc, m.window) - ref.coc_dense(d, d_f, k, opts.slope))[inside]
    v_ref = ref.visibility_dense(d, d_f, k, n_sources=2, n_steps=4, model=model)
    v_err = np.abs(ref.window_to_dense(vis, m.window) - v_ref)[inside]
    return {"finite": bool(np.isfinite(coc).all() and np.isfinite(vis).all()),
            "coc_max_abs": float(c_err.max(initial=0.0)), "vis_mismatch": int((v_err > 1e-6).sum()),
            "pairs": int(inside.sum())}


def attention_case(rng: np.random.Generator) -> dict:
    import torch
    from bokehray_refiner.attention import pisa_attention

    n, w = int(rng.integers(2, 9)), int(rng.integers(0, 4))
    n_off = (2 * w + 1) ** 2
    scale = float(rng.choice([1.0, 10.0, 100.0, 1e3, 1e4]))
    g = torch.Generator().manual_seed(int(rng.integers(1 << 30)))
    q = torch.randn(1, 2, n, n, 8, generator=g, dtype=torch.float64) * scale
    k = torch.randn(1, 2, n, n, 8, generator=g, dtype=torch.float64)
    v = torch.randn(1, 2, n, n, 4, generator=g, dtype=torch.float64)
    c = torch.rand(1, n, n, n_off, generator=g, dtype=torch.float64)
    c[c < 0.3] = float(rng.choice([0.0, 1e-38, 1e-20]))  # masked or nearly masked entries
    c[:, 0, 0] = 0.0  # one fully masked column
    vis = torch.rand(1, n, n, n_off, generator=g, dtype=torch.float64)
    ref = pisa_attention(q, k, v, c, vis, w)
    out = {}
    for name, dt in (("float32", torch.float32), ("float16", torch.float16), ("bfloat16", torch.bfloat16)):
        # the inputs as that dtype holds them: rounding q and k is not the attention's error
        qd, kd, vd = q.to(dt), k.to(dt), v.to(dt)
        exact = pisa_attention(qd.double(), kd.double(), vd.double(), c, vis, w)
        got = pisa_attention(qd, kd, vd, c.float(), vis.float(), w).double()
        denom = max(float(exact.abs().max()), 1e-30)
        out[name] = {"finite": bool(torch.isfinite(got).all()), "rel": float((got - exact).abs().max()) / denom}
    out["column_sums_ok"] = bool(torch.isfinite(ref).all())
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=200)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=str(REPO / "benchmarks/results/stress-pisa.json"))
    args = ap.parse_args()
    rng = np.random.default_rng(args.seed)
    masks = [masks_case(rng) for _ in range(args.cases)]
    attn = [attention_case(rng) for _ in range(args.cases)]
    summary = {
        "mask_cases": len(masks),
        "mask_pairs": sum(m["pairs"] for m in masks),
        "mask_nonfinite": sum(not m["finite"] for m in masks),
        "coc_worst_abs_error": max(m["coc_max_abs"] for m in masks),
        "visibility_mismatches": sum(m["vis_mismatch"] for m in masks),
        "attention_cases": len(attn),
    }
    for name in ("float32", "float16", "bfloat16"):
        summary[f"{name}_worst_rel_error"] = max(a[name]["rel"] for a in attn)
        summary[f"{name}_nonfinite"] = sum(not a[name]["finite"] for a in attn)
    print("\n".join(f"{k}: {v}" for k, v in summary.items()))
    write_json(args.out, {"machine": machine_info(), "seed": args.seed, "summary": summary})


if __name__ == "__main__":
    main()
