"""Memory of ``bokehray view`` under a long storm of requests: does RSS follow the number of requests?

Starts the server on the demo scene (480 x 320, proxy 160 px, display 240 px), then fires ``--storms``
rounds of 200 render requests from 8 client threads as fast as they go (every fifth a full-resolution
refinement, so renders are abandoned mid-way all the time) and records the RSS of the process after each
round. Bounded means the series flattens; a leak grows with the rounds.

Usage::

    python benchmarks/page/soak_view.py                 # 30 rounds = 6000 requests, about 3 minutes on 2 cores
    python benchmarks/page/soak_view.py --storms 5      # smoke run

Writes ``benchmarks/results/view-soak.json``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import urllib.error
import urllib.request
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from benchmarks import common


def _post(url: str, body: dict) -> int:
    req = urllib.request.Request(url, data=json.dumps(body).encode(), headers={"Content-Type": "application/json"},
                                 method="POST")
    try:
        with urllib.request.urlopen(req, timeout=120) as r:
            r.read()
            return r.status
    except urllib.error.HTTPError as e:
        e.read()
        return e.code


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--storms", type=int, default=30, help="rounds of 200 requests (default 30)")
    ap.add_argument("--out", default=str(common.REPO / "benchmarks" / "results"), help="folder of the JSON")
    args = ap.parse_args()

    import warp

    warp.config.log_level = warp.LOG_WARNING
    from bokehray.app.demo import build_demo_scene
    from bokehray.app.view.server import ViewServer
    from bokehray.app.view.session import ProxyLadder, ViewSession

    sc = build_demo_scene(width=480, height=320)
    session = ViewSession(sc.image, sc.disparity, proxy_long_side=160, display_long_side=240)
    session.ladder = ProxyLadder(1)
    rows = []
    t0 = time.perf_counter()
    with ViewServer(session) as server:
        url = server.url + "api/render"

        def one(i: int, k: int) -> int:
            stage = "full" if i % 5 == 0 else "preview"
            return _post(url, {"blur": 5 + (i % 30), "focus": ((i + k) % 97) / 96, "stage": stage})

        for k in range(args.storms):
            with ThreadPoolExecutor(8) as pool:
                statuses = list(pool.map(one, range(200), [k] * 200))
            rows.append({"requests": 200 * (k + 1), "rss_mb": round((common.status_kb("VmRSS") or 0) / 1024, 1),
                         "ok": statuses.count(200), "superseded": statuses.count(409),
                         "other": len(statuses) - statuses.count(200) - statuses.count(409),
                         **{f"worker_{a}": b for a, b in server.worker.counts.items()}})
            print(f"{rows[-1]['requests']:6d} requests  RSS {rows[-1]['rss_mb']:7.1f} MB  started "
                  f"{rows[-1]['worker_started']}  abandoned {rows[-1]['worker_abandoned']}", flush=True)
    rss = [r["rss_mb"] for r in rows]
    half = len(rss) // 2
    result = {"benchmark": "view-soak", "machine": common.machine_info(), "rows": rows,
              "wall_seconds": round(time.perf_counter() - t0, 1),
              "rss_first_mb": rss[0], "rss_max_mb": max(rss), "rss_last_mb": rss[-1],
              "rss_growth_second_half_mb": round(max(rss[half:]) - max(rss[:half]), 1) if half else None,
              "errors": sum(r["other"] for r in rows)}
    path = common.write_json(Path(args.out) / "view-soak.json", result)
    print(f"RSS {rss[0]:.0f} -> max {max(rss):.0f} MB over {rows[-1]['requests']} requests; growth of the second half "
          f"over the first {result['rss_growth_second_half_mb']} MB; wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
