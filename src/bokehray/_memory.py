"""How much memory this process can still use (the readers ask before decoding, the tile driver before planning),
and the bands of rows whole-frame passes work in so that their temporaries stay small."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import psutil

__all__ = ["BAND_PX", "UNLIMITED", "address_space_headroom", "available_bytes", "cgroup_headroom", "row_bands"]

UNLIMITED = 1 << 62
"""What :func:`available_bytes` and its parts say where nothing limits the process."""

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
    """The memory available to new allocations without swapping or being killed: the machine's (psutil:
    ``MemAvailable`` on Linux), or less where the process is held to less: its control group's limit (a container,
    a systemd unit, a CI job) or its address-space limit (``ulimit -v``), whichever leaves the least."""
    try:
        have = int(psutil.virtual_memory().available)
    except (OSError, RuntimeError):  # no /proc (a sandbox): do not refuse
        have = UNLIMITED
    return min(have, cgroup_headroom(), address_space_headroom())


def cgroup_headroom(root: Path = Path("/sys/fs/cgroup"), membership: Path = Path("/proc/self/cgroup")) -> int:
    """What the process's memory control group still allows: its limit less its usage (v2's ``memory.max`` and
    ``memory.current``, v1's ``memory.limit_in_bytes`` and ``memory.usage_in_bytes``, in the group's folder or, in a
    namespace that shows the group as its root, at the root); :data:`UNLIMITED` where there is none or it cannot be
    read."""
    try:
        lines = membership.read_text().splitlines()
    except OSError:
        return UNLIMITED
    for line in lines:
        parts = line.split(":", 2)
        if len(parts) != 3:
            continue
        _, controllers, path = parts
        if controllers == "":  # v2: one unified hierarchy
            bases, names = (root / path.lstrip("/"), root), ("memory.max", "memory.current")
        elif "memory" in controllers.split(","):
            bases, names = (root / "memory" / path.lstrip("/"), root / "memory"), ("memory.limit_in_bytes",
                                                                                  "memory.usage_in_bytes")
        else:
            continue
        for base in bases:
            try:
                limit, used = ((base / name).read_text().strip() for name in names)
            except OSError:
                continue
            if limit.isdigit() and used.isdigit() and int(limit) < UNLIMITED:
                return max(0, int(limit) - int(used))
            break  # read, and no limit ("max", or v1's page-rounded 2^63)
    return UNLIMITED


def address_space_headroom() -> int:
    """What the address-space limit (``RLIMIT_AS``, ``ulimit -v``) leaves beyond the process's present size;
    :data:`UNLIMITED` where there is none."""
    try:
        import resource

        soft, _ = resource.getrlimit(resource.RLIMIT_AS)
        if soft == resource.RLIM_INFINITY:
            return UNLIMITED
        with open("/proc/self/status") as f:
            size_kb = next(int(line.split()[1]) for line in f if line.startswith("VmSize:"))
        return max(0, soft - size_kb * 1024)
    except (ImportError, OSError, StopIteration, ValueError):
        return UNLIMITED
