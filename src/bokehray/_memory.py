"""How much memory this process can still use (the readers ask before decoding, the tile driver before planning),
the bands of rows whole-frame passes work in so that their temporaries stay small, and the C heap held to what is
in use (:func:`bound_heap`)."""

from __future__ import annotations

import ctypes
import platform
from collections.abc import Iterator
from pathlib import Path

import psutil

__all__ = ["BAND_PX", "HEAP_MMAP_BYTES", "UNLIMITED", "address_space_headroom", "available_bytes", "bound_heap",
           "cgroup_headroom", "on_cores", "row_bands", "small_pages"]

UNLIMITED = 1 << 62
"""What :func:`available_bytes` and its parts say where nothing limits the process."""

BAND_PX = 1 << 18
"""Pixels (or values) a band of a whole-frame pass holds: its temporaries (float32, int64) stay a few MB where the
whole frame's would be 4 to 8 bytes a pixel (hundreds of MB at 12 MP)."""


HEAP_MMAP_BYTES = 4 << 20
"""Blocks of this size or more are mapped on their own by glibc's ``malloc`` and unmapped when freed (its
``M_MMAP_THRESHOLD``, fixed by :func:`bound_heap`). Left to itself glibc raises the threshold to the largest block
freed so far (up to 32 MB): a render's temporaries of 1 to 32 MB then come from the heaps of the threads that
allocate them, and what is freed between blocks still in use stays in the process. A 6 MP render on a map that is
depth edges everywhere grew by 1158 MB with the moving threshold and by 820 MB with 4 MB (medians of fresh
processes), in about the same CPU time (19.1-19.9 s against 19.4 s; the exact map 8.5-8.7 s against 8.1-8.4 s);
1 MB gave 851 MB for more page faults (one run each: 1.42 M, 4 MB 1.27 M, glibc's 0.86 M;
docs/design/memory-model.md)."""
M_MMAP_THRESHOLD = -3
"""glibc's ``mallopt`` parameter (malloc.h)."""
_heap = {"bounded": False}


def _glibc() -> ctypes.CDLL | None:
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return None
    try:
        libc = ctypes.CDLL("libc.so.6")
        return libc if hasattr(libc, "mallopt") and hasattr(libc, "malloc_trim") else None
    except OSError:
        return None


def bound_heap() -> bool:
    """Hold the C heap to what is in use, where it is glibc's: the first call fixes ``malloc``'s mapping threshold
    at :data:`HEAP_MMAP_BYTES` for the process, and every call hands the heaps' free pages back to the system
    (``malloc_trim``: the frame's transients freed by then do not stay in the process beside the next stage's
    arrays). A render calls it as it starts and before its layers; it changes no value. Returns whether the
    threshold is fixed (False where the C library is not glibc: nothing is done)."""
    libc = _glibc()
    if libc is None:
        return False
    if not _heap["bounded"]:
        _heap["bounded"] = bool(libc.mallopt(M_MMAP_THRESHOLD, HEAP_MMAP_BYTES))
    libc.malloc_trim(0)
    return _heap["bounded"]


def small_pages() -> bool:
    """Turn off NumPy's huge-page hint (``madvise(MADV_HUGEPAGE)`` on arrays of 4 MB or more) for the process,
    unless ``NUMPY_MADVISE_HUGEPAGE`` is set in the environment (then the user's choice stands). The command line and
    the page call it before they read (their processes are the renderer's; ``bokehray.render`` in a caller's process
    leaves the hint alone: docs/design/command-stages.md says why): on the 2-core development VM (transparent huge pages on
    ``madvise``) a 12 MP command took 15.9-16.4 CPU-s without the hint and 18.2-20.8 with it (system time 3.2-3.6
    against 5.2-7.4 s), the peak RSS unchanged within the noise (1475-1480 against 1417-1506 MiB), for 40 % more page
    faults of 4 KB (docs/design/command-stages.md). It changes no value. Returns whether the hint is off."""
    import os

    if "NUMPY_MADVISE_HUGEPAGE" in os.environ:
        return os.environ["NUMPY_MADVISE_HUGEPAGE"].strip() == "0"
    try:
        from numpy._core import multiarray
    except ImportError:  # NumPy 1.x
        from numpy.core import multiarray
    hint = getattr(multiarray, "_set_madvise_hugepage", None)
    if hint is None:
        return False
    hint(False)
    return True


def row_bands(h: int, w: int) -> Iterator[tuple[int, int]]:
    """``(y0, y1)`` of consecutive bands of rows of an ``h x w`` frame, about :data:`BAND_PX` pixels each (one row
    at least)."""
    rows = max(1, BAND_PX // max(1, w))
    for y0 in range(0, h, rows):
        yield y0, min(h, y0 + rows)


def on_cores(run, spans: list[tuple[int, int]]) -> list:
    """``run(a, b)`` for each of ``spans`` (independent parts of a frame: bands of rows), spread over the CPU's cores
    on a thread pool (NumPy's loops, Pillow's colour transforms release the GIL), the results in order."""
    import os

    workers = min(len(spans), os.cpu_count() or 1)
    if workers <= 1:
        return [run(*span) for span in spans]
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(max_workers=workers) as pool:
        return [f.result() for f in [pool.submit(run, *span) for span in spans]]


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
