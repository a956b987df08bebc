"""How much memory this process can still use (no dependencies: the readers use it before decoding)."""

from __future__ import annotations

import os
import re
from pathlib import Path

__all__ = ["available_bytes"]


def available_bytes() -> int:
    """``MemAvailable`` of /proc/meminfo (Linux), else the free physical pages; a huge number if unknown."""
    try:
        m = re.search(r"^MemAvailable:\s*(\d+) kB", Path("/proc/meminfo").read_text(), re.M)
        if m:
            return int(m.group(1)) * 1024
    except OSError:
        pass
    try:
        return int(os.sysconf("SC_AVPHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return 1 << 62  # unknown: do not refuse
