"""The page's focus after a click on a busy machine: how long until the focused region shows at screen resolution.

A 12 MP portrait (the astronaut with its painted map, ``benchmarks/photo/portrait.py``, ``--side`` 3464) is opened as
``bokehray view`` opens it; ``--busy`` processes spin on the CPU meanwhile (a page used beside two busy
processes). For ``--clicks`` clicks spread over the frame, the page's server-side sequence is timed as the worker
runs it: the preview at the ladder's proxy (the ladder moves as it does on the page), then the focus crop at the
screen's size (``--screen`` px on the long side, 1029 as in a 1400 x 950 browser window), then the sharp version
at that size. Reported per click: the seconds to the proxy, to the focus crop (proxy + crop: the focus is
judgeable at screen resolution) and to the sharp version, and the proxy's size; medians and maxima. The browser's own time (the request, decoding, drawing:
tens of ms) is not in these numbers.

Usage (from the repository root)::

    python benchmarks/page/bench_view_focus.py          # JSON to benchmarks/results/view_focus.json
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from benchmarks.photo.portrait import portrait

ROOT = Path(__file__).resolve().parents[2]


def _spin(stop) -> None:
    x = 0
    while not stop.is_set():
        for _ in range(100_000):
            x = (x * 1103515245 + 12345) & 0x7FFFFFFF


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--side", type=int, default=3464)
    ap.add_argument("--screen", type=int, default=1029)
    ap.add_argument("--clicks", type=int, default=8)
    ap.add_argument("--busy", type=int, default=2)
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks/results/view_focus.json")
    args = ap.parse_args()
    from bokehray._quiet import init_warp_quietly
    from bokehray.app.view.session import ViewSession

    init_warp_quietly(False)
    img, d = portrait(args.side)
    s = ViewSession(img, d)
    s.warm_up()
    stop = multiprocessing.Event()
    spinners = [multiprocessing.Process(target=_spin, args=(stop,), daemon=True) for _ in range(args.busy)]
    for p in spinners:
        p.start()
    rows = []
    try:
        for i in range(args.clicks):
            x = int((0.15 + 0.7 * ((i * 0.618) % 1)) * s.w)
            y = int((0.15 + 0.7 * ((i * 0.382) % 1)) * s.h)
            p = s.parse({"focus_at": [x, y]})
            t0 = time.perf_counter()
            _, meta = s.render_preview(p)
            t1 = time.perf_counter()
            _, cmeta = s.focus_crop(p, long_side=args.screen)
            t2 = time.perf_counter()
            s.full_display(p, long_side=args.screen)
            t3 = time.perf_counter()
            f = meta["factor"]
            rows.append({"click": [x, y], "proxy": [-(-s.w // f), -(-s.h // f)], "to_proxy_s": round(t1 - t0, 3),
                         "to_focus_crop_s": round(t2 - t0, 3), "crop_s": round(t2 - t1, 3),
                         "to_sharp_s": round(t3 - t0, 3), "screen_factor": cmeta["factor"]})
            print(rows[-1], flush=True)
    finally:
        stop.set()
        for p in spinners:
            p.join(5)

    def stat(key):
        v = [r[key] for r in rows]
        return {"median": round(statistics.median(v), 3), "max": round(max(v), 3)}

    result = {"side": args.side, "screen": args.screen, "busy_processes": args.busy,
              "summary": {k: stat(k) for k in ("to_proxy_s", "crop_s", "to_focus_crop_s", "to_sharp_s")},
              "clicks": rows}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps(result["summary"], indent=1))


if __name__ == "__main__":
    main()
