"""One render thread for the page: the newest request wins, a preview is never cancelled by a refinement, memory
stays bounded.

Three kinds of job share the thread. **Previews** (the live proxy) come first: a new preview supersedes the
pending preview and refinement at once and makes the running one of either stale, which notices at its next
check (after each depth layer of the preview renderer, and before encoding) and abandons. **Refinements** (the
sharp version for the screen, asked for only once the preview of the same state is shown) run when no preview
waits; a new refinement supersedes the pending and running refinement but never a preview. **Exports** queue
(``max_exports``) and are never abandoned for the page, but they are no wall: at each of their checks (between
depth layers, or bands of rows of the ray tracer) the worker runs any waiting preview or refinement inline, so
the page stays live during a long export, and they stop when the server stops (:class:`Stopped`).

At any time the worker holds at most one running job (plus one inline), one pending preview, one pending
refinement and ``max_exports`` exports; a superseded request is answered at once with :class:`Superseded`.
:meth:`RenderWorker.progress` says how far the running refinement or export is.
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


class Stopped(Exception):
    """The server is stopping: the job was abandoned (an export too)."""


class Busy(Exception):
    """Too many exports are queued."""


KINDS = ("preview", "full", "export")


@dataclass
class _Job:
    fn: Callable[[Callable[..., None]], object]
    generation: int
    kind: str
    future: Future = field(default_factory=Future)
    done: int = 0
    total: int = 0


class RenderWorker:
    """Runs jobs ``fn(check)`` on one daemon thread; ``check(done=None, total=None)`` raises :class:`Superseded`
    when the job is stale (:class:`Stopped` when the worker closes) and records its progress."""

    def __init__(self, max_exports: int = 2) -> None:
        self._lock = threading.Condition()
        self._gen = {"preview": 0, "full": 0}
        self._pending: dict[str, _Job | None] = {"preview": None, "full": None}
        self._exports: deque[_Job] = deque()
        self._max_exports = max_exports
        self._stop = False
        self._current: list[_Job] = []  # the running job, then the one run inline at its check, if any
        self.counts = {"submitted": 0, "started": 0, "finished": 0, "superseded": 0, "abandoned": 0, "max_held": 0,
                       "inline": 0}
        self._thread = threading.Thread(target=self._loop, name="bokehray-view-render", daemon=True)
        self._thread.start()

    def submit(self, fn: Callable[[Callable[..., None]], object], kind: str = "preview") -> Future:
        """Queue an interactive job (``kind`` "preview" or "full"); see the module's docstring for who supersedes
        whom."""
        if kind not in ("preview", "full"):
            raise ValueError(f"kind: expected 'preview' or 'full', got {kind!r}")
        with self._lock:
            if self._stop:
                fut: Future = Future()
                fut.set_exception(Stopped())
                return fut
            # a preview is a new state: the refinement of the old one is stale too
            for k in (("preview", "full") if kind == "preview" else ("full",)):
                self._gen[k] += 1
            job = _Job(fn, self._gen[kind], kind)
            old = [self._pending[k] for k in (("preview", "full") if kind == "preview" else ("full",))]
            if kind == "preview":
                self._pending["full"] = None
            self._pending[kind] = job
            old = [o for o in old if o is not None]
            self.counts["submitted"] += 1
            self.counts["superseded"] += len(old)
            self._note_held()
            self._lock.notify()
        for o in old:
            o.future.set_exception(Superseded())
        return job.future

    def submit_export(self, fn: Callable[[Callable[..., None]], object]) -> Future:
        with self._lock:
            if self._stop:
                raise Stopped()
            if len(self._exports) >= self._max_exports:
                raise Busy(f"{len(self._exports)} exports are already queued; wait for them")
            job = _Job(fn, 0, "export")
            self._exports.append(job)
            self.counts["submitted"] += 1
            self._note_held()
            self._lock.notify()
        return job.future

    def _note_held(self) -> None:
        held = len(self._current) + sum(j is not None for j in self._pending.values()) + len(self._exports)
        self.counts["max_held"] = max(self.counts["max_held"], held)

    def queued(self) -> int:
        with self._lock:
            return sum(j is not None for j in self._pending.values()) + len(self._exports)

    def progress(self) -> dict:
        """What runs now: ``{"kind", "done", "total"}`` of each running job (outermost first)."""
        with self._lock:
            return {"running": [{"kind": j.kind, "done": j.done, "total": j.total} for j in self._current],
                    "queued": {"preview": self._pending["preview"] is not None,
                               "full": self._pending["full"] is not None, "exports": len(self._exports)}}

    def stop_soon(self) -> None:
        """Safe from a signal handler: the running job (an export too) stops at its next check, and
        :meth:`close` is called on another thread to answer what waits."""
        self._stop = True
        threading.Thread(target=self.close, args=(0,), name="bokehray-view-close", daemon=True).start()

    def close(self, timeout: float | None = 5.0) -> None:
        with self._lock:
            self._stop = True
            waiting = [j for j in self._pending.values() if j is not None] + list(self._exports)
            self._pending = {"preview": None, "full": None}
            self._exports = deque()
            self._lock.notify()
        for job in waiting:
            if not job.future.done():
                job.future.set_exception(Stopped())
        if timeout is None or timeout > 0:
            self._thread.join(timeout)

    def _trim(self) -> None:
        """Give the freed pages of past renders back to the system (glibc only; when no job waits).

        Without it the allocator keeps the freed buffers of renders of varying sizes and RSS creeps up
        with the number of renders (benchmarks/page/soak_view.py: docs/view.md); with it RSS is flat.
        """
        if _malloc_trim is None:
            return
        with self._lock:
            if any(j is not None for j in self._pending.values()) or self._exports:  # only when idle
                return
        t = time.perf_counter()
        _malloc_trim(0)
        self.counts["trim_ms_max"] = max(self.counts.get("trim_ms_max", 0.0), (time.perf_counter() - t) * 1e3)

    def _check(self, job: _Job) -> Callable[..., None]:
        def check(done: int | None = None, total: int | None = None) -> None:
            if done is not None:
                job.done, job.total = int(done), int(total or 0)
            if self._stop:
                raise Stopped()
            if job.kind != "export":
                if job.generation != self._gen[job.kind]:
                    raise Superseded()
            elif len(self._current) == 1:  # an export: serve the page in between (not from an inline job)
                self._run_inline()
        return check

    def _take_interactive(self) -> _Job | None:
        """The next preview, else the next refinement (with the lock held)."""
        for kind in ("preview", "full"):
            job = self._pending[kind]
            if job is not None:
                self._pending[kind] = None
                return job
        return None

    def _run_inline(self) -> None:
        while True:
            with self._lock:
                job = self._take_interactive()
                if job is None:
                    return
                self.counts["inline"] += 1
            self._run(job)

    def _run(self, job: _Job) -> None:
        with self._lock:
            self.counts["started"] += 1
            self._current.append(job)
        try:
            if not job.future.set_running_or_notify_cancel():  # the request went away before it started
                return
            result = None
            try:
                result = job.fn(self._check(job))
            except Superseded:
                with self._lock:
                    self.counts["abandoned"] += 1
                # a fresh exception: the raised one's traceback holds the abandoned render's frames and arrays,
                # which are freed here, on this thread, not whenever the request's thread lets go of it
                job.future.set_exception(Superseded())
            except Stopped:
                job.future.set_exception(Stopped())
            except BaseException as e:  # noqa: BLE001 - handed to the request that asked
                job.future.set_exception(e.with_traceback(None))
            else:
                with self._lock:
                    self.counts["finished"] += 1
                job.future.set_result(result)
            result = None
        finally:
            with self._lock:
                self._current.remove(job)

    def _loop(self) -> None:
        while True:
            with self._lock:
                while not self._stop and self._take_peek() is None:
                    self._lock.wait()
                if self._stop:
                    return
                job = self._take_interactive() or self._exports.popleft()
            self._run(job)
            job = None  # hold nothing between jobs
            self._trim()

    def _take_peek(self) -> _Job | None:
        return self._pending["preview"] or self._pending["full"] or (self._exports[0] if self._exports else None)
