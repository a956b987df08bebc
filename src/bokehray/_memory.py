"""How much memory this process can still use (the readers ask before decoding, the tile driver before planning),
and the bands of rows whole-frame passes work in so that their temporaries stay small."""

from __future__ import annotations

from collections.abc import Iterator

import psutil

__all__ = ["BAND_PX", "available_bytes", "row_bands"]

BAND_PX = 1 << 18
"""Pixels (or values) a band of a whole-frame pass holds: its temporaries (float32, int64) stay a few MB where the
whole frame's would be 4 to 8 bytes a pixel (hundreds of MB at 12 MP)."""


def row_bands(h: int, w: int) -> Iterator[tuple[int, int]]:
    """``(y0, y1)`` of consecutive bands of rows of an ``h x w`` frame, about :data:`BAND_PX` pixels each (one row
    at least)."""
    rows = max(1, BAND_PX // max(1, w))
    for y0 in range(0, h, rows):
        yield y0, min(h, y0 + rows)


def available_bytes() -> int:
    """The memory available to new allocations without swapping (psutil: ``MemAvailable`` on Linux)."""
    try:
        return int(psutil.virtual_memory().available)
    except (OSError, RuntimeError):  # no /proc (a sandbox): do not refuse
        return 1 << 62
