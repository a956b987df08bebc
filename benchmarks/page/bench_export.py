"""What an export from the page costs against the command line's render of the same picture.

**Protocol.** A 12 MP JPEG (the demo scene at 4000 x 3000, display-referred) and its 16-bit disparity PNG are
written once, and one ``bokehray view`` process is started on them (warm: the page is open, as when a user
exports). For each of ``--reps`` repetitions, with a focus point of its own (a new picture: the page's cache of its
last full render does not answer it), the page's export is asked for (``POST /api/export``, PNG) and timed from
the request to the answer; then the command the page shows for that export is run as a fresh process, timed from
its start to its exit (start-up, reading, every stage, writing). The two alternate, which goes first alternating
too, so that load drifts hit both alike. The figure is the ratio export / command line of each pair, and its
median; the target is at most 1.10 (an export costs no more than the command line's render plus 10 %).

The export's progress (``GET /api/progress``) is polled while it runs; the benchmark records how many distinct
progress states the page could have shown.

Usage (from the repository root)::

    python benchmarks/page/bench_export.py              # about four minutes on 2 cores
    python benchmarks/page/bench_export.py --quick      # 3 MP, 2 repetitions

Writes ``benchmarks/results/export--<machine>.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import statistics
import subprocess
import sys
import tempfile
import threading
import time
import urllib.parse
import urllib.request
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from benchmarks import common
from benchmarks.page.bench_view import CLI, write_photo

TARGET_RATIO = 1.10


def _post(url: str, body: dict) -> dict:
    req = urllib.request.Request(url, data=json.dumps(body).encode(), headers={"Content-Type": "application/json"},
                                 method="POST")
    with urllib.request.urlopen(req, timeout=900) as r:
        return json.loads(r.read())


def _poll_progress(url: str, stop: threading.Event, seen: list) -> None:
    while not stop.is_set():
        try:
            with urllib.request.urlopen(url + "api/progress", timeout=10) as r:
                state = r.read().decode()
        except OSError:
            state = None
        if state is not None and (not seen or seen[-1] != state):
            seen.append(state)
        stop.wait(0.1)


def export_once(url: str, params: dict) -> tuple[float, str, int]:
    """One export from the page: seconds from the request to the answer, the command shown, progress states."""
    stop, seen = threading.Event(), []
    poller = threading.Thread(target=_poll_progress, args=(url, stop, seen), daemon=True)
    poller.start()
    t = time.perf_counter()
    try:
        answer = _post(url + "api/export", {"params": params, "format": "png"})
    finally:
        seconds = time.perf_counter() - t
        stop.set()
        poller.join()
    Path(answer["path"]).unlink()
    return seconds, answer["command"], len(seen)


def shown_command(url: str, params: dict) -> str:
    """The command the page shows for ``params`` (from its live preview's answer, as the page reads it)."""
    req = urllib.request.Request(url + "api/render", data=json.dumps({**params, "stage": "preview"}).encode(),
                                 headers={"Content-Type": "application/json"}, method="POST")
    with urllib.request.urlopen(req, timeout=300) as r:
        r.read()
        return urllib.parse.unquote(r.headers["X-Bokehray-Command"])


def command_once(command: str, out: Path) -> float:
    """The page's shown command as a fresh process, writing to ``out``: seconds from its start to its exit."""
    args = shlex.split(command)
    assert args[:2] == ["bokehray", "render"], command
    args[args.index("-o") + 1] = str(out)
    t = time.perf_counter()
    subprocess.run([sys.executable, "-c", CLI, *args[1:]], check=True, stdout=subprocess.DEVNULL)
    seconds = time.perf_counter() - t
    out.unlink()
    return seconds


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="3 MP, 2 repetitions")
    ap.add_argument("--reps", type=int, default=4, help="export / command pairs (default 4)")
    ap.add_argument("--out", default=str(common.REPO / "benchmarks" / "results"), help="folder of the JSON")
    args = ap.parse_args()
    w, h = (2000, 1500) if args.quick else (4000, 3000)
    reps = 2 if args.quick else args.reps
    tmp = Path(tempfile.mkdtemp(prefix="bench-export-"))
    photo, disp = write_photo(tmp, w, h)
    result: dict = {"benchmark": "export", "quick": args.quick, "machine": common.machine_info(),
                    "commit": common.git_commit(), "image": [w, h], "megapixels": round(w * h / 1e6, 2),
                    "reps": reps, "target_ratio": TARGET_RATIO, "load_avg_at_start": list(os.getloadavg())}
    proc = subprocess.Popen([sys.executable, "-c", CLI, "view", str(photo), "--disparity", str(disp), "--quiet",
                             "--export-dir", str(tmp)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        line = proc.stdout.readline()
        if not line.startswith("bokehray view: http"):
            raise RuntimeError(line + proc.stderr.read())
        url = line.split()[2]
        pairs = []
        for r in range(reps):
            params = {"focus_at": [int(w * (0.3 + 0.4 * r / max(1, reps - 1))), int(h * 0.6)]}
            if r % 2 == 0:
                export_s, command, states = export_once(url, params)
                cli_s = command_once(command, tmp / "cli.png")
            else:
                cli_s = command_once(shown_command(url, params), tmp / "cli.png")
                export_s, _, states = export_once(url, params)
            pairs.append({"params": params, "export_s": round(export_s, 3), "command_s": round(cli_s, 3),
                          "ratio": round(export_s / cli_s, 3), "progress_states": states})
            print(f"rep {r}: export {export_s:.2f} s, command line {cli_s:.2f} s, ratio {export_s / cli_s:.2f}, "
                  f"{states} progress states", flush=True)
    finally:
        proc.terminate()
        proc.wait(60)
    ratios = [p["ratio"] for p in pairs]
    result.update(pairs=pairs, median_export_s=statistics.median(p["export_s"] for p in pairs),
                  median_command_s=statistics.median(p["command_s"] for p in pairs),
                  median_ratio=statistics.median(ratios), load_avg_at_end=list(os.getloadavg()))
    verdict = "within" if result["median_ratio"] <= TARGET_RATIO else "OVER"
    print(f"export / command line: median {result['median_ratio']:.2f} ({verdict} the {TARGET_RATIO:.2f} target); "
          f"export {result['median_export_s']:.2f} s, command {result['median_command_s']:.2f} s")
    tag = common.machine_tag(result["machine"]) + ("-quick" if args.quick else "")
    print(f"wrote {common.write_json(Path(args.out) / f'export--{tag}.json', result)}")
    import shutil

    shutil.rmtree(tmp, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
