"""Large host buffers reused across a render's layers instead of allocated (and zeroed by the kernel, page by page)
anew for each one.

Every layer of the preview allocates its sources, pyramids and routing arrays at its box size and frees them when
it is composited. A fresh block of that size comes from the kernel as untouched pages: each first touch is a page
fault and a zeroed page (at 12 MP: 2.4 million faults, a third of the render's CPU time in the kernel). Within
:func:`reuse_buffers`, Warp's CPU allocator keeps freed blocks of ``MIN_BYTES`` or more and hands them to later
requests that fit (the smallest block at least as large, at most ``FIT`` times as large); a request that no block
fits first releases cached blocks (the smallest first) until what is held, in use and cached, with the new block,
is within the most ever asked for at once, so that the cache does not raise the peak beyond what the render needed
without it. Contents are not preserved: ``wp.zeros`` clears what it gets, as before; nothing here
changes a value.
"""

from __future__ import annotations

import bisect
import mmap
import threading
from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np
import warp as wp

__all__ = ["LAZY_MIN_BYTES", "MIN_BYTES", "CachingHostAllocator", "is_lazy", "lazy_for", "lazy_zeros", "release_cached",
           "reuse_buffers"]

MIN_BYTES = 1 << 20
LAZY_MIN_BYTES = 32 << 20
"""A layer (or a window) whose ``(h, w)`` vec4 plane is smaller than this (2 MP) zeroes its arrays at once (``wp.zeros``;
:func:`lazy_for`): a lazily zeroed mapping takes a page fault for each page first written, which a 1.5 MP render
paid for nothing (t32/tFFT 14.5 against 12.2, 19 % more CPU, on the quiet 2-core VM); at 12 MP the pages it never
takes are worth it (docs/design/memory-model.md)."""
"""Blocks below this go straight to the C allocator (which reuses small blocks itself)."""
FIT = 4
"""A cached block serves a request of at least 1 / FIT of its size (its unused tail is not touched again)."""
SLACK = 64
"""A new block is ``1 / SLACK`` larger than asked (rounded up to 64 KiB), so that a later request a little larger
(a pyramid buffer's two spare columns on a box the size of a freed plane) still fits it. The tail is address space
only: no page of it is touched unless a later array uses it."""


class CachingHostAllocator:
    """A Warp CPU allocator (``allocate(size)`` / ``deallocate(ptr, size)``) over ``inner`` that caches large
    freed blocks while :attr:`active`."""

    def __init__(self, inner) -> None:
        self.inner = inner
        self.memory_kind = getattr(inner, "memory_kind", None)
        self.deallocate_requires_context_guard = False
        self.lock = threading.Lock()
        self.sizes: dict[int, int] = {}  # pointer -> its block's size, for every block this allocator handed out
        self.free: list[tuple[int, int]] = []  # cached (size, pointer), sorted
        self.active = True
        self.hits = self.misses = 0
        self.in_use = 0  # bytes of the blocks handed out
        self.requested = self.peak = 0  # bytes asked for by the arrays alive (now, at most): the need without a cache

    def allocate(self, size_in_bytes: int) -> int:
        if size_in_bytes < MIN_BYTES:
            return self.inner.allocate(size_in_bytes)
        with self.lock:
            i = bisect.bisect_left(self.free, (size_in_bytes, 0))
            if i < len(self.free) and self.free[i][0] <= FIT * size_in_bytes:
                size, ptr = self.free.pop(i)
                self.hits += 1
                self._take(ptr, size, size_in_bytes)
                return ptr
            self.misses += 1
            # make room first: what is held (blocks in use and cached) stays within the most ever asked for at
            # once (the peak without the cache) or what is in use with this block, whichever is more
            cached = sum(size for size, _ in self.free)
            limit = max(self.peak, self.in_use + size_in_bytes)
            while self.free and self.in_use + cached + size_in_bytes > limit:
                size, ptr = self.free.pop(0)  # the smallest first: the least likely to fit a later request
                cached -= size
                self.inner.deallocate(ptr, size)
        block = -(-(size_in_bytes + size_in_bytes // SLACK) // (1 << 16)) << 16
        ptr = self.inner.allocate(block)
        with self.lock:
            self._take(ptr, block, size_in_bytes)
        return ptr

    def _take(self, ptr: int, size: int, asked: int) -> None:
        self.sizes[ptr] = size
        self.in_use += size
        self.requested += asked
        self.peak = max(self.peak, self.requested)

    def deallocate(self, ptr: int, size_in_bytes: int) -> None:
        with self.lock:
            size = self.sizes.pop(ptr, None)
            if size is not None:
                self.in_use -= size
                self.requested -= size_in_bytes
                if self.active:
                    bisect.insort(self.free, (size, ptr))
                    return
        self.inner.deallocate(ptr, size_in_bytes if size is None else size)

    def release(self) -> int:
        """Hand the cached blocks back to ``inner`` (caching goes on for blocks freed later); returns their bytes."""
        with self.lock:
            blocks, self.free = self.free, []
        for size, ptr in blocks:
            self.inner.deallocate(ptr, size)
        return sum(size for size, _ in blocks)

    def close(self) -> None:
        """Stop caching and release the cached blocks (blocks still in use are released when their arrays go)."""
        with self.lock:
            self.active = False
        self.release()


_install = threading.Lock()


@contextmanager
def reuse_buffers(device: str) -> Iterator[CachingHostAllocator | None]:
    """Within the block, Warp arrays allocated on CPU ``device`` reuse large freed blocks (nothing on CUDA devices,
    whose memory pool does this already, nor inside another ``reuse_buffers`` of the same device)."""
    dev = wp.get_device(device)
    with _install:
        if not dev.is_cpu or isinstance(dev.default_allocator, CachingHostAllocator):
            cache = None
        else:
            cache = CachingHostAllocator(dev.default_allocator)
            dev.default_allocator = cache
    try:
        yield cache
    finally:
        if cache is not None:
            with _install:
                dev.default_allocator = cache.inner
            cache.close()


def release_cached(device: str) -> int:
    """Release the blocks the CPU ``device``'s cache (:func:`reuse_buffers`) keeps, if one is installed; returns their
    bytes (0: none, or not a CPU device). A large layer's fill buffers are reused by the next layer's fill only, and
    kept until then they lay beside the peak of the layers in work (at 12 MP: 140-190 MB of the 1.7 GB peak,
    docs/design/memory-model.md); released when the fill is done, they come back as fresh pages at the next fill."""
    alloc = wp.get_device(device).default_allocator
    return alloc.release() if isinstance(alloc, CachingHostAllocator) else 0


_LAYOUTS = {wp.vec4: (np.float32, 4), float: (np.float32, 1), wp.float32: (np.float32, 1), wp.uint8: (np.uint8, 1)}


def lazy_for(h: int, w: int) -> bool:
    """Whether the arrays of a layer's box (or a window) of ``h x w`` are worth lazily zeroed pages."""
    return 16 * h * w >= LAZY_MIN_BYTES


def lazy_zeros(shape: tuple[int, ...], dtype, device: str, lazy: bool = True) -> wp.array:
    """``wp.zeros(shape, dtype, device)`` whose pages are taken only where they are written.

    On the CPU a large array is a fresh private anonymous mapping (zero pages from the kernel, never cleared by a
    write): memory is taken, and faulted in, only for the pages a kernel writes, and pages only read stay the
    kernel's shared zero page. For arrays mostly left zero: the routing's per-level planes, each allocated at the
    finest level's size while level ``k`` writes only the first ``1 / 2^k`` of the rows and of each row. Values are
    those of ``wp.zeros``. Not ``lazy`` (:func:`lazy_for`), small arrays and CUDA devices: ``wp.zeros``.
    """
    dev = wp.get_device(device)
    layout = _LAYOUTS.get(dtype)  # (numpy scalar type, lanes)
    nbytes = int(np.prod(shape)) * layout[1] * np.dtype(layout[0]).itemsize if layout else 0
    if not lazy or not dev.is_cpu or nbytes < MIN_BYTES:
        return wp.zeros(shape, dtype=dtype, device=device)
    mm = mmap.mmap(-1, nbytes, flags=mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS)
    host = np.frombuffer(mm, dtype=layout[0]).reshape(*shape, *((layout[1],) if layout[1] > 1 else ()))
    arr = wp.array(host, dtype=dtype, device=device, copy=False)  # aliases ``host`` (and keeps it)
    if arr.ptr != host.ctypes.data:  # not aliased after all: a copy, of zeros
        return arr
    arr._lazy_host = host  # the mapping lives as long as the array
    return arr


def is_lazy(a: wp.array) -> bool:
    """Whether ``a`` came from :func:`lazy_zeros` as a lazily zeroed mapping (its pages not yet taken)."""
    return hasattr(a, "_lazy_host")
