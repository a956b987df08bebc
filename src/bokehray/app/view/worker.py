"""One render thread for the page: the newest request wins, memory stays bounded.

Interactive jobs (live previews and full-resolution refinements) share one
slot: submitting a job supersedes the pending one at once and makes the running
one stale, which it notices at its next check (after each depth layer of the
preview renderer, and before encoding) and abandons. Exports queue behind the
current job and are never abandoned. At any time the worker holds at most one
running job, one pending interactive job and ``max_exports`` exports; a
superseded request is answered at once with :class:`Superseded`.
"""

from __future__ import annotations

import sys
import threading
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass, field

__all__ = ["Busy", "RenderWorker", "Superseded"]


def _libc_malloc_trim():
    if not sys.platform.startswith("linux"):
        return None
    try:
        import ctypes

        fn = ctypes.CDLL("libc.so.6").malloc_trim
    except (OSError, AttributeError):  # musl or another libc: nothing to trim with
        return None
    fn.argtypes, fn.restype = [ctypes.c_size_t], ctypes.c_int
    return fn


_malloc_trim = _libc_malloc_trim()


class Superseded(Exception):
    """A newer request replaced this one before or while it rendered."""


class Busy(Exception):
    """Too many exports are queued."""


@dataclass
class _Job:
    fn: Callable[[Callable[[], None]], object]
    generation: int
    interactive: bool
    future: Future = field(default_factory=Future)


class RenderWorker:
    """Runs jobs ``fn(check)`` on one daemon thread; ``check()`` raises :class:`Superseded` when the job is stale."""

    def __init__(self, max_exports: int = 2) -> None:
        self._lock = threading.Condition()
        self._generation = 0
        self._pending: _Job | None = None
        self._exports: deque[_Job] = deque()
        self._max_exports = max_exports
        self._stop = False
        self.counts = {"submitted": 0, "started": 0, "finished": 0, "superseded": 0, "abandoned": 0, "max_held": 0}
        self._running = 0
        self._thread = threading.Thread(target=self._loop, name="bokehray-view-render", daemon=True)
        self._thread.start()

    def submit(self, fn: Callable[[Callable[[], None]], object]) -> Future:
        """Queue an interactive job; the pending one (if any) is superseded, the running one becomes stale."""
        with self._lock:
            self._generation += 1
            job = _Job(fn, self._generation, True)
            old, self._pending = self._pending, job
            self.counts["submitted"] += 1
            self._note_held()
            if old is not None:
                self.counts["superseded"] += 1
            self._lock.notify()
        if old is not None:
            old.future.set_exception(Superseded())
        return job.future

    def submit_export(self, fn: Callable[[Callable[[], None]], object]) -> Future:
        with self._lock:
            if len(self._exports) >= self._max_exports:
                raise Busy(f"{len(self._exports)} exports are already queued; wait for them")
            job = _Job(fn, 0, False)
            self._exports.append(job)
            self.counts["submitted"] += 1
            self._note_held()
            self._lock.notify()
        return job.future

    def _note_held(self) -> None:
        held = self._running + (self._pending is not None) + len(self._exports)
        self.counts["max_held"] = max(self.counts["max_held"], held)

    def queued(self) -> int:
        with self._lock:
            return (self._pending is not None) + len(self._exports)

    def close(self, timeout: float | None = 5.0) -> None:
        with self._lock:
            self._stop = True
            pending, self._pending = self._pending, None
            exports, self._exports = list(self._exports), deque()
            self._generation += 1
            self._lock.notify()
        for job in ([pending] if pending else []) + exports:
            job.future.set_exception(Superseded())
        self._thread.join(timeout)

    def _trim(self) -> None:
        """Give the freed pages of past renders back to the system (glibc only; when no job waits).

        Without it the allocator keeps the freed buffers of renders of varying sizes and RSS creeps up
        with the number of renders (benchmarks/soak_view.py: docs/view.md); with it RSS is flat.
        """
        if _malloc_trim is None:
            return
        with self._lock:
            if self._pending is not None or self._exports:  # only when idle: nobody waits for the 1-50 ms
                return
        t = time.perf_counter()
        _malloc_trim(0)
        self.counts["trim_ms_max"] = max(self.counts.get("trim_ms_max", 0.0), (time.perf_counter() - t) * 1e3)

    def _check(self, job: _Job) -> Callable[[], None]:
        def check() -> None:
            if job.interactive and (job.generation != self._generation or self._stop):
                raise Superseded()
        return check

    def _loop(self) -> None:
        while True:
            with self._lock:
                while not self._stop and self._pending is None and not self._exports:
                    self._lock.wait()
                if self._stop:
                    return
                if self._exports:
                    job = self._exports.popleft()
                else:
                    job, self._pending = self._pending, None
                self.counts["started"] += 1
                self._running = 1
            if not job.future.set_running_or_notify_cancel():  # the request went away before it started
                with self._lock:
                    self._running = 0
                continue
            result = None
            try:
                result = job.fn(self._check(job))
            except Superseded:
                with self._lock:
                    self.counts["abandoned"] += 1
                # a fresh exception: the raised one's traceback holds the abandoned render's frames and arrays,
                # which are freed here, on this thread, not whenever the request's thread lets go of it
                job.future.set_exception(Superseded())
            except BaseException as e:  # noqa: BLE001 - handed to the request that asked
                job.future.set_exception(e.with_traceback(None))
            else:
                with self._lock:
                    self.counts["finished"] += 1
                job.future.set_result(result)
            with self._lock:
                self._running = 0
            job = result = None  # hold nothing between jobs
            self._trim()
