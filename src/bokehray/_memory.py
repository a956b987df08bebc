"""How much memory this process can still use (the readers ask before decoding, the tile driver before planning)."""

from __future__ import annotations

import psutil

__all__ = ["available_bytes"]


def available_bytes() -> int:
    """The memory available to new allocations without swapping (psutil: ``MemAvailable`` on Linux)."""
    try:
        return int(psutil.virtual_memory().available)
    except (OSError, RuntimeError):  # no /proc (a sandbox): do not refuse
        return 1 << 62
