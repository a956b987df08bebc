"""Where a measurement was taken, and the peak memory of a stretch of work (Linux /proc).

Shared by ``bokehray bench`` and the scripts under ``benchmarks/``. These probes read /proc themselves: psutil (which
``bokehray`` uses for the memory available) has no peak resident size of a stretch of work (``VmHWM`` and its reset
through ``/proc/self/clear_refs``) and no CPU model name.
"""

from __future__ import annotations

import datetime
import os
import platform
import re
import socket
import subprocess
from pathlib import Path

__all__ = ["git_commit", "machine_info", "reset_peak_rss", "status_kb"]


def _read(path: str) -> str:
    try:
        return Path(path).read_text()
    except OSError:
        return ""


def status_kb(field: str) -> int | None:
    """A ``kB`` field of /proc/self/status (``VmRSS``, ``VmHWM``), or None where there is none."""
    m = re.search(rf"^{field}:\s*(\d+) kB", _read("/proc/self/status"), re.M)
    return int(m.group(1)) if m else None


def reset_peak_rss() -> bool:
    """Reset the peak RSS (``VmHWM``) to the current RSS (Linux >= 4.0), so the next peak is the next work's."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
        return True
    except OSError:
        return False


def git_commit(where: str | os.PathLike[str] | None = None) -> str:
    """The short commit (``+dirty`` with uncommitted changes to tracked files) of the checkout holding ``where``
    (default: this code's), or ``unknown``."""
    here = Path(__file__).parent if where is None else Path(where)
    if not here.is_dir():
        return "unknown"
    try:
        def git(*args: str) -> subprocess.CompletedProcess:
            return subprocess.run(["git", *args], cwd=here, capture_output=True, text=True)

        out, dirty = git("rev-parse", "--short", "HEAD"), git("status", "--porcelain", "--untracked-files=no").stdout
        return out.stdout.strip() + ("+dirty" if dirty.strip() else "") if out.returncode == 0 else "unknown"
    except OSError:
        return "unknown"


def machine_info() -> dict:
    """Describe the machine and software the numbers were taken on (load included: other jobs skew timings)."""
    import numpy
    import warp

    model = re.search(r"^model name\s*:\s*(.+)$", _read("/proc/cpuinfo"), re.M)
    mem = re.search(r"^MemTotal:\s*(\d+) kB", _read("/proc/meminfo"), re.M)
    return {
        "hostname": socket.gethostname(),
        "cpu": model.group(1).strip() if model else platform.processor() or "unknown",
        "cores": os.cpu_count(),
        "load_avg_1_5_15": [round(x, 2) for x in os.getloadavg()],
        "ram_gb": round(int(mem.group(1)) / 2**20, 1) if mem else None,
        "os": platform.platform(),
        "python": platform.python_version(),
        "numpy": numpy.__version__,
        "warp": warp.__version__,
        "git_commit": git_commit(),
        "date": datetime.datetime.now().astimezone().isoformat(timespec="seconds"),
    }
