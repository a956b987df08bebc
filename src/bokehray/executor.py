"""One executor seam for batch work: a local process pool, or Dask distributed.

``bokehray render`` on folders, ``bokehray synth`` and ``bokehray bench`` (its synthetic split) hand their tasks
to :func:`make_executor` and never see which engine runs them:

* ``local`` (default): a pool of ``spawn``-ed worker processes on this machine (one task per worker at a time);
  ``workers=1`` runs the tasks in this process.
* ``dask``: Dask distributed. Without ``scheduler`` it starts a ``LocalCluster`` of ``workers`` single-threaded
  worker processes on 127.0.0.1 and stops it at the end; with ``scheduler="tcp://host:8786"`` it joins an
  existing cluster (whose workers must import ``bokehray`` and see the output folder). ``dask`` is imported here
  and nowhere else, only when asked (an import-linter contract in ``pyproject.toml`` checks it).

A task is ``fn(task)`` for a top-level function ``fn`` and a picklable ``task`` (seed and index, or input path and
settings), so its result does not depend on the engine or the worker that ran it. Workers write their outputs
themselves, atomically (:func:`bokehray.output.atomic.atomic_write`), and return a small summary. An exception raised by
``fn`` is the task's failure (one line, never retried: the same input fails the same way); a worker process that
dies mid-task (killed, out of memory, a crash in native code) leaves only a temporary file behind and the task is
run again, up to ``retries`` times, on a fresh worker.
"""

from __future__ import annotations

import argparse
import os
import re
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

from .errors import BokehrayError, InputError

__all__ = ["EXECUTORS", "Executor", "Outcome", "add_executor_args", "check_executor_args", "check_scheduler", "make_executor", "run_task"]

EXECUTORS = ("local", "dask")
DEFAULT_RETRIES = 3


@dataclass
class Outcome:
    """What became of one task: its ``value``, or ``error`` (one line); ``attempts`` counts worker deaths + 1."""

    index: int
    value: Any = None
    error: str | None = None
    attempts: int = 1

    @property
    def ok(self) -> bool:
        return self.error is None


_READY = False


def run_task(fn: Callable[[Any], Any], task: Any) -> tuple[str, Any]:
    """Run one task in the current process: ``("ok", value)`` or ``("error", one line)``.

    Exceptions are turned into text here, in the worker, so nothing unpicklable travels back and the engines
    never retry a task that failed on its input.
    """
    global _READY
    if not _READY:
        from ._quiet import init_warp_quietly

        init_warp_quietly()
        _READY = True
    try:
        return "ok", fn(task)
    except BokehrayError as e:
        return "error", str(e)
    except MemoryError:
        return "error", "out of memory"
    except Exception as e:  # noqa: BLE001 - one bad task is reported, never stops the batch
        return "error", f"{type(e).__name__}: {e}".splitlines()[0]


class Executor:
    """Runs tasks; ``map`` yields an :class:`Outcome` per task as each one ends (in completion order)."""

    name = "?"

    def __init__(self, workers: int, retries: int) -> None:
        self.workers = workers
        self.retries = retries

    def map(self, fn: Callable[[Any], Any], tasks: Sequence[Any]) -> Iterator[Outcome]:
        raise NotImplementedError

    def describe(self) -> str:
        return f"{self.name} ({self.workers} worker{'s' if self.workers != 1 else ''})"

    def close(self) -> None:
        pass

    def __enter__(self) -> Executor:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class InlineExecutor(Executor):
    """``local`` with one worker: the tasks run in this process, one after another."""

    name = "local"

    def map(self, fn, tasks):
        for i, task in enumerate(tasks):
            status, value = run_task(fn, task)
            yield Outcome(i, value) if status == "ok" else Outcome(i, error=value)


class LocalExecutor(Executor):
    """A pool of spawned worker processes; a pool broken by a dying worker is replaced and its tasks rerun.

    At most ``workers`` tasks are in flight, so the tasks charged with an attempt when a worker dies are the
    ones that were running, not the queue behind them.
    """

    name = "local"

    def __init__(self, workers: int, retries: int) -> None:
        super().__init__(workers, retries)
        self._pool = None

    def _new_pool(self):
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        from ._quiet import init_warp_quietly

        return ProcessPoolExecutor(max_workers=self.workers, mp_context=multiprocessing.get_context("spawn"),
                                   initializer=init_warp_quietly)

    def map(self, fn, tasks):  # noqa: C901
        from concurrent.futures import FIRST_COMPLETED, wait
        from concurrent.futures.process import BrokenProcessPool

        todo = list(range(len(tasks)))[::-1]  # a stack: lowest index first
        attempts = [0] * len(tasks)
        running: dict = {}
        while todo or running:
            if self._pool is None:
                self._pool = self._new_pool()
            while todo and len(running) < self.workers:
                i = todo.pop()
                attempts[i] += 1
                running[self._pool.submit(run_task, fn, tasks[i])] = i
            finished, _ = wait(running, return_when=FIRST_COMPLETED)
            broken = False
            for fut in finished:
                i = running.pop(fut)
                try:
                    status, value = fut.result()
                except BrokenProcessPool:
                    broken = True
                    if attempts[i] > self.retries:
                        yield Outcome(i, error=f"its worker process died {attempts[i]} times", attempts=attempts[i])
                    else:
                        todo.append(i)
                    continue
                yield (Outcome(i, value, attempts=attempts[i]) if status == "ok"
                       else Outcome(i, error=value, attempts=attempts[i]))
            if broken:  # every task still in the broken pool is lost: rerun them on a fresh one
                for fut, i in list(running.items()):
                    try:
                        status, value = fut.result()
                        yield (Outcome(i, value, attempts=attempts[i]) if status == "ok"
                               else Outcome(i, error=value, attempts=attempts[i]))
                    except BrokenProcessPool:
                        if attempts[i] > self.retries:
                            yield Outcome(i, error=f"its worker process died {attempts[i]} times",
                                          attempts=attempts[i])
                        else:
                            todo.append(i)
                running.clear()
                self._pool.shutdown(wait=True, cancel_futures=True)
                self._pool = None

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None


class DaskExecutor(Executor):
    """Dask distributed: a LocalCluster on 127.0.0.1 started here, or an existing scheduler."""

    name = "dask"

    def __init__(self, workers: int, retries: int, scheduler: str | None) -> None:
        super().__init__(workers, retries)
        import logging

        try:
            import dask
            from distributed import Client, LocalCluster
        except ImportError as e:
            raise InputError(f"--executor dask needs its extra: pip install 'bokehray[distributed]' ({e})") from None
        self._cluster = None
        # a task whose worker dies is rescheduled by the scheduler; this many deaths make it fail (KilledWorker)
        self._config = dask.config.set({"distributed.scheduler.allowed-failures": retries})
        self._config.__enter__()
        try:
            if scheduler:
                try:
                    self.client = Client(scheduler, timeout="20s")
                except (OSError, TimeoutError, ValueError) as e:  # ValueError: an address Dask cannot parse
                    why = str(e).splitlines()[0] if str(e) else type(e).__name__
                    raise InputError(f"--scheduler {scheduler}: cannot reach the Dask scheduler ({why})") from None
                self.workers = max(1, len(self.client.scheduler_info().get("workers", {})))
                self.address = scheduler
            else:
                self._cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                             host="127.0.0.1",
                                             dashboard_address="127.0.0.1:0", silence_logs=logging.ERROR)
                self.client = Client(self._cluster)
                self.address = self._cluster.scheduler_address
        except BaseException:
            self._shutdown()
            raise

    def describe(self) -> str:
        where = "a local cluster" if self._cluster is not None else "the cluster"
        return f"dask ({self.workers} worker{'s' if self.workers != 1 else ''}, {where} at {self.address})"

    def map(self, fn, tasks):
        from distributed import as_completed

        futures = {self.client.submit(run_task, fn, task, pure=False): i for i, task in enumerate(tasks)}
        for fut in as_completed(futures):
            i = futures[fut]
            try:
                status, value = fut.result()
            except Exception as e:  # noqa: BLE001 - KilledWorker (died `retries` times) or a lost connection
                name = type(e).__name__
                msg = (f"its worker process died {self.retries} times" if name == "KilledWorker"
                       else f"{name}: {e}".splitlines()[0])
                yield Outcome(i, error=msg, attempts=self.retries if name == "KilledWorker" else 1)
                continue
            finally:
                fut.release()
            yield Outcome(i, value) if status == "ok" else Outcome(i, error=value)

    def _shutdown(self) -> None:
        client = getattr(self, "client", None)
        if client is not None:
            client.close()
            self.client = None
        if self._cluster is not None:
            self._cluster.close()
            self._cluster = None
        if self._config is not None:
            self._config.__exit__(None, None, None)
            self._config = None

    def close(self) -> None:
        self._shutdown()


def add_executor_args(p: argparse.ArgumentParser, *, workers_help: str = "worker processes (default: all cores)",
                      workers: bool = True) -> None:
    """``--executor``, ``--scheduler`` (and ``--workers``) of every command that runs batch work."""
    g = p.add_argument_group("executor (docs/scale.md)")
    g.add_argument("--executor", choices=EXECUTORS, default=None,  # None: local (a command can tell it was given)
                   help="local: a process pool on this machine (default); dask: Dask distributed (extra "
                   "'distributed'), a local cluster on 127.0.0.1 unless --scheduler is given")
    g.add_argument("--scheduler", metavar="ADDRESS", help="dask: an existing scheduler, e.g. tcp://10.0.0.5:8786")
    if workers:
        g.add_argument("--workers", type=int, default=None, help=workers_help)


_SCHEDULER = re.compile(r"(?:tcp://)?(?P<host>[A-Za-z0-9_.-]+|\[[0-9A-Fa-f:.]+\]):(?P<port>[0-9]{1,5})")


def check_scheduler(address: object) -> str:
    """A Dask scheduler address as bokehray can reach it: ``tcp://HOST:PORT`` (or ``HOST:PORT``), nothing more.

    Other protocols (``tls://`` needs certificates, ``ucx://`` and ``inproc://`` other transports) and anything
    after the port are refused here, in one line, before Dask sees them; so is an empty address, which would
    otherwise mean "no scheduler" and start a local cluster unasked.
    """
    text = address if isinstance(address, str) else None
    m = _SCHEDULER.fullmatch(text) if text else None
    if m is None or not 1 <= int(m["port"]) <= 65535:
        raise InputError(f"--scheduler: expected a Dask scheduler address tcp://HOST:PORT (e.g. "
                         f"tcp://10.0.0.5:8786), got {address!r}")
    return text


def check_executor_args(kind: str | None = None, *, workers: int | None = None,
                        scheduler: str | None = None) -> None:
    """The checks of :func:`make_executor`'s flags, which a command runs before it writes anything."""
    kind = kind or "local"
    if kind not in EXECUTORS:
        raise InputError(f"--executor: expected one of {', '.join(EXECUTORS)}, got {kind!r}")
    if workers is not None and workers < 1:
        raise InputError(f"--workers: expected at least 1, got {workers}")
    if scheduler is not None:
        check_scheduler(scheduler)
        if kind != "dask":
            raise InputError("--scheduler needs --executor dask")


def make_executor(kind: str | None = None, *, workers: int | None = None, scheduler: str | None = None,
                  retries: int = DEFAULT_RETRIES, tasks: int | None = None) -> Executor:
    """The executor ``kind`` (``local``, the default, or ``dask``) with ``workers`` processes (default: all cores).

    ``tasks``: how many tasks will run (a pool is never larger). ``scheduler``: the address of an existing Dask
    scheduler (``dask`` only). ``retries``: how often a task whose worker died is run again.
    """
    check_executor_args(kind, workers=workers, scheduler=scheduler)
    if retries < 0:
        raise InputError(f"retries: expected >= 0, got {retries}")
    n = workers or os.cpu_count() or 1
    if tasks is not None:
        n = max(1, min(n, tasks))
    if kind == "dask":
        return DaskExecutor(n, retries, scheduler)
    return InlineExecutor(n, retries) if n == 1 else LocalExecutor(n, retries)
