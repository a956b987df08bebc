"""Wall and CPU time of ``bokehray.thin_depth.restore_thin`` (and of the ramp snap after it), the best of a few runs.

    python research/soft_thin/cost.py 1536 1024      # the demo at 1.5 MP: its exact map and its map blurred by 4 px
    python research/soft_thin/cost.py 4224 2816      # the same at 12 MP (the blur scaled with the width: 11 px)
    python research/soft_thin/cost.py edge12         # the 12 MP soft-map render's own input (as bench_guard's):
                                                     # the demo at 1500 x 1000 zoomed to 4000 x 3000, its map
                                                     # blurred by 6 px, amount 50, focus on the subject
    python research/soft_thin/cost.py edge12 --module /path/to/thin_depth.py   # another version of the module
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
import time

import numpy as np
from scipy import ndimage

from bokehray import scene
from bokehray.app.demo import build_demo_scene
from bokehray.ramps import snap_ramps


def demo_inputs(w: int, h: int):
    """(name, photo, signed CoC, CoC bounds): the demo's exact map and its map blurred by 4 px at 1536 px wide."""
    sc = build_demo_scene(w, h)
    for kind in ("exact", "gauss4"):
        d = sc.disparity
        if kind != "exact":
            d = ndimage.gaussian_filter(d, 4.0 * w / 1536, mode="nearest").astype(np.float32)
        yield kind, sc.image, (30 * (d - 0.1)).astype(np.float32), (-3.0, 27.0)  # K = 30, focus 0.1


def edge12_inputs():
    """The 12 MP soft map as the pipeline sees it (the capped signed CoC)."""
    import bokehray as br
    from bokehray.photo.subject import k_from_amount, subject_focus

    sc = build_demo_scene(1500, 1000)
    z = (3000 / 1000, 4000 / 1500)
    img = np.clip(ndimage.zoom(sc.image, (*z, 1), order=1), 0, None).astype(np.float32)
    d = np.clip(ndimage.gaussian_filter(ndimage.zoom(sc.disparity, z, order=0), 6.0), 0, 1).astype(np.float32)
    blur = br.BlurParams(k_from_amount(50.0, *d.shape), subject_focus(d).d_f)
    bounds = (float(blur.signed_coc(np.float32(0.0))), float(blur.signed_coc(np.float32(1.0))))
    yield "edge12 soft", img, scene.cap_coc(blur.signed_coc(d)), bounds


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("size", nargs="+", help="W H, or edge12")
    ap.add_argument("--module", help="a thin_depth.py to time instead of the installed one")
    ap.add_argument("--runs", type=int, default=3)
    args = ap.parse_args()
    if args.module:
        spec = importlib.util.spec_from_file_location("bokehray.thin_other", args.module)  # its relative imports
        mod = importlib.util.module_from_spec(spec)
        sys.modules["bokehray.thin_other"] = mod
        spec.loader.exec_module(mod)
        restore_thin = mod.restore_thin
    else:
        from bokehray.thin_depth import restore_thin
    inputs = edge12_inputs() if args.size[0] == "edge12" else demo_inputs(int(args.size[0]), int(args.size[1]))
    for kind, image, s, bounds in inputs:
        walls, cpus = [], []
        for _ in range(args.runs):
            t0, c0 = time.perf_counter(), time.process_time()
            out, n = restore_thin(image, s, bounds=bounds)
            walls.append(time.perf_counter() - t0)
            cpus.append(time.process_time() - c0)
        t1, c1 = time.perf_counter(), time.process_time()
        snap_ramps(image, out)
        t2, c2 = time.perf_counter(), time.process_time()
        print(f"{image.shape[1]}x{image.shape[0]} {kind}: thin depth {min(walls):.3f} s wall {min(cpus):.3f} CPU-s "
              f"(best of {args.runs}), {n} px moved; ramp snap after it {t2 - t1:.2f} s wall {c2 - c1:.2f} CPU-s",
              flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
