"""CPU time of ``bokehray.thin_depth.restore_thin`` (and of the ramp snap after it) on the demo scene at a given size,
its exact map and the map blurred by 4 px at 1536 px wide (scaled with the width).

    python research/soft_thin/cost.py 1536 1024      # 1.5 MP
    python research/soft_thin/cost.py 4224 2816      # 12 MP
"""

from __future__ import annotations

import sys
import time

import numpy as np
from scipy import ndimage

from bokehray.app.demo import build_demo_scene
from bokehray.ramps import snap_ramps
from bokehray.thin_depth import restore_thin


def main() -> int:
    w, h = int(sys.argv[1]), int(sys.argv[2])
    sc = build_demo_scene(w, h)
    for kind in ("exact", "gauss4"):
        d = sc.disparity
        if kind != "exact":
            d = ndimage.gaussian_filter(d, 4.0 * w / 1536, mode="nearest").astype(np.float32)
        s = (30 * (d - 0.1)).astype(np.float32)  # K = 30, focus 0.1
        t0, c0 = time.perf_counter(), time.process_time()
        out, n = restore_thin(sc.image, s, bounds=(-3.0, 27.0))
        t1, c1 = time.perf_counter(), time.process_time()
        snap_ramps(sc.image, out)
        t2, c2 = time.perf_counter(), time.process_time()
        print(f"{w}x{h} {kind}: thin depth {t1 - t0:.2f} s wall {c1 - c0:.2f} CPU-s, {n} px moved; "
              f"ramp snap after it {t2 - t1:.2f} s wall {c2 - c1:.2f} CPU-s", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
