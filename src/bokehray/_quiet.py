"""Keeping native libraries' and Python's side output off the CLI's stderr.

- :func:`quiet_warp_on_import`: ``import bokehray`` does not import Warp (slow to import): the first module that needs
  it does, when a render starts; this makes that import set ``warp.config.log_level`` to warnings (no banner
  or per-module load lines), whoever triggers it.
- :func:`init_warp_quietly`: Warp initialisation without the native "no CUDA driver" line on
  CPU-only machines.
- :func:`native_stderr_quiet`: hides what native code writes to file descriptor 2 inside a
  block (Warp prints two ``Warp CUDA error`` lines for every ``get_device("cuda")`` on a machine
  without a driver, before raising the exception that says the same).
- :func:`collect_warnings`: the CLI's record of Python warnings during a command, so that an
  error stays one line (``--debug`` shows them as they happen).

- :func:`native_output`: captures what native code writes to file descriptors 1 and 2 inside a block, as lines
  (OpenEXR prints its errors there, libpng its warnings), for the readers to judge.
- :func:`library_log`: collects a Python library's log records (tifffile's damaged-tag lines) inside a block
  instead of letting logging's last resort print them.
- :func:`command_stderr`: the CLI's guard around a whole command: whatever native code writes to descriptor 2
  (a C library's warning, Warp's CUDA lines, a worker process's output) goes nowhere, while Python's
  ``sys.stderr`` (bokehray's own one-line errors, warnings and progress bars) keeps the terminal; and log
  records no handler takes are dropped, not printed by logging's last resort.
- :func:`progress_bar`: a tqdm bar on a terminal; on a stderr that is no terminal (a file, a CI log) no
  carriage-return frames: nothing, or a plain line now and then.

All of them except the two capturing ones step aside with ``debug=True`` (the CLI's ``--debug``), which
:func:`init_warp_quietly` remembers for :func:`native_stderr_quiet`.
"""

from __future__ import annotations

import contextlib
import importlib.abc
import importlib.machinery
import io
import logging
import os
import sys
import tempfile
import time
import warnings
from collections.abc import Iterator
from typing import Any

__all__ = ["collect_warnings", "command_stderr", "init_warp_quietly", "library_log", "native_output",
           "native_stderr_quiet", "progress_bar", "quiet_warp_on_import"]

_show_native = False


@contextlib.contextmanager
def native_stderr_quiet(debug: bool | None = None) -> Iterator[None]:
    """Send file descriptor 2 to /dev/null inside the block (not with ``debug``, nor when stderr is no file)."""
    debug = _show_native if debug is None else debug
    try:
        fd = sys.stderr.fileno()
    except (AttributeError, OSError, ValueError):  # stderr is not a file (e.g. captured by a test runner)
        fd = None
    if debug or fd is None:
        yield
        return
    sys.stderr.flush()
    saved = os.dup(fd)
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, fd)
        yield
    finally:
        os.dup2(saved, fd)
        os.close(saved)
        os.close(devnull)


def _quiet(wp: object) -> None:
    config = getattr(wp, "config", None)
    if config is not None and hasattr(wp, "LOG_WARNING"):
        config.log_level = wp.LOG_WARNING  # no banner or per-module load lines


class _QuietLoader(importlib.abc.Loader):
    def __init__(self, inner: importlib.abc.Loader) -> None:
        self._inner = inner

    def create_module(self, spec):
        return self._inner.create_module(spec)

    def exec_module(self, module) -> None:
        self._inner.exec_module(module)
        _quiet(module)


class _QuietFinder(importlib.abc.MetaPathFinder):
    """Finds ``warp`` as the other finders do, and wraps its loader so the module is quietened once loaded."""

    def find_spec(self, name, path=None, target=None):
        if name != "warp":
            return None
        spec = importlib.machinery.PathFinder.find_spec(name, path)
        if spec is not None and spec.loader is not None:
            spec.loader = _QuietLoader(spec.loader)
        return spec


def quiet_warp_on_import() -> None:
    """Set Warp's log level to warnings now if it is imported, else as soon as it is (idempotent)."""
    if "warp" in sys.modules:
        _quiet(sys.modules["warp"])
    elif not any(isinstance(f, _QuietFinder) for f in sys.meta_path):
        sys.meta_path.insert(0, _QuietFinder())


def init_warp_quietly(debug: bool = False) -> None:
    """Initialise Warp without its native "no CUDA driver" line on CPU-only machines (shown with --debug)."""
    global _show_native
    _show_native = debug
    import warp as wp

    _quiet(wp)
    with native_stderr_quiet(debug):
        wp.init()


@contextlib.contextmanager
def collect_warnings(debug: bool = False) -> Iterator[list[warnings.WarningMessage]]:
    """Record Python warnings raised inside the block instead of printing them (each distinct one once).

    With ``debug`` nothing is recorded and warnings print as usual. The caller decides what to
    show: the CLI drops them when the command fails (its error line says what went wrong) and
    prints each as one ``bokehray: warning:`` line when it succeeds.
    """
    if debug:
        yield []
        return
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("default")
        seen: list[warnings.WarningMessage] = []
        try:
            yield seen
        finally:
            keys = set()
            for w in caught:
                key = (w.category, str(w.message))
                if key not in keys:
                    keys.add(key)
                    seen.append(w)


def _flush_c_streams() -> None:
    with contextlib.suppress(Exception):
        import ctypes

        ctypes.CDLL(None).fflush(None)


@contextlib.contextmanager
def native_output() -> Iterator[list[str]]:
    """Capture what native code writes to file descriptors 1 and 2 inside the block.

    Yields a list that holds the captured lines once the block ends. The descriptors are
    process-wide, so output of other threads during the block is captured too (a short read).
    """
    lines: list[str] = []
    sys.stdout.flush()
    sys.stderr.flush()
    saved = [os.dup(1), os.dup(2)]
    printed = io.StringIO()  # Python bindings print their warnings with print()
    with tempfile.TemporaryFile() as sink:
        try:
            os.dup2(sink.fileno(), 1)
            os.dup2(sink.fileno(), 2)
            with contextlib.redirect_stdout(printed), contextlib.redirect_stderr(printed):
                yield lines
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
            _flush_c_streams()  # C/C++ stdout is buffered: flush it into the sink, not onto the terminal later
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            for fd in saved:
                os.close(fd)
            sink.seek(0)
            text = sink.read().decode("utf-8", "replace") + printed.getvalue()
            lines.extend(ln.strip() for ln in text.splitlines() if ln.strip())


@contextlib.contextmanager
def library_log(name: str) -> Iterator[list[str]]:
    """Collect the log messages of the library logger ``name`` (e.g. ``tifffile``) inside the block instead of
    letting them reach stderr; yields their list."""
    messages: list[str] = []

    class Collect(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            messages.append(record.getMessage())

    log = logging.getLogger(name)
    handler, propagate = Collect(), log.propagate
    log.addHandler(handler)
    log.propagate = False
    try:
        yield messages
    finally:
        log.removeHandler(handler)
        log.propagate = propagate


@contextlib.contextmanager
def command_stderr(debug: bool = False) -> Iterator[None]:
    """One CLI command's stderr: bokehray's own lines only.

    Descriptor 2 is pointed at /dev/null for the block and ``sys.stderr`` at a duplicate of the real one, so
    what Python prints (errors, warnings, progress bars, a traceback with ``--debug``) still arrives and what
    native libraries print straight to descriptor 2 does not (libpng's ``PNG warning: iCCP: ...`` on a file
    that decodes fine; worker processes inherit the same descriptor). A root logging handler that drops
    records keeps library loggers (tifffile) from logging's last resort, which prints to stderr. With
    ``debug``, or when stderr is no file (a test runner capturing it), nothing changes.
    """
    try:
        fd = sys.stderr.fileno()
    except (AttributeError, OSError, ValueError):
        fd = None
    if debug or fd != 2:
        yield
        return
    drop = logging.NullHandler()
    root = logging.getLogger()
    root.addHandler(drop)
    previous = sys.stderr
    previous.flush()
    saved = os.dup(2)
    devnull = os.open(os.devnull, os.O_WRONLY)
    stream = io.TextIOWrapper(io.FileIO(saved, "w", closefd=False), encoding=previous.encoding,
                              errors=previous.errors, line_buffering=True)
    try:
        os.dup2(devnull, 2)
        sys.stderr = stream
        yield
    finally:
        with contextlib.suppress(Exception):
            stream.flush()
        sys.stderr = previous
        os.dup2(saved, 2)
        os.close(saved)
        os.close(devnull)
        root.removeHandler(drop)


PLAIN_PROGRESS_EVERY_S = 30.0
"""Off a terminal, a bar that asks for lines prints one at most this often (a CI log of a long run)."""


class _PlainProgress:
    """What a batch or ``synth`` uses for a progress bar when stderr is no terminal: tqdm would redraw itself
    there with carriage returns, a long smear in a log file. This prints ``<desc>: N of TOTAL (P%)`` on its own
    line at most every :data:`PLAIN_PROGRESS_EVERY_S` seconds (``lines``), or nothing."""

    def __init__(self, total: int, desc: str, lines: bool) -> None:
        self.n, self.total, self.desc, self.lines = 0, total, desc, lines
        self.last = time.monotonic()

    def update(self, k: int = 1) -> None:
        self.n += k
        now = time.monotonic()
        if self.lines and self.n < self.total and now - self.last >= PLAIN_PROGRESS_EVERY_S:
            self.last = now
            print(f"{self.desc}: {self.n} of {self.total} ({100 * self.n // max(self.total, 1)}%)", file=sys.stderr)

    @staticmethod
    def write(s: str, file: Any = None) -> None:
        print(s, file=sys.stdout if file is None else file)

    def __enter__(self) -> _PlainProgress:
        return self

    def __exit__(self, *exc: object) -> None:
        return None


def progress_bar(total: int, desc: str, unit: str, *, enabled: bool = True, lines: bool = False) -> Any:
    """A progress bar on stderr for ``total`` items: tqdm's when stderr is a terminal, else one that draws no
    frames (:class:`_PlainProgress`; with ``lines``, a plain line every :data:`PLAIN_PROGRESS_EVERY_S` seconds at
    most). Disabled (``enabled=False``, ``--quiet``) it prints nothing either way. Both have ``update()``,
    ``write(s, file=)`` and work as context managers."""
    if enabled and sys.stderr.isatty():
        from tqdm import tqdm

        return tqdm(total=total, desc=desc, unit=unit, file=sys.stderr)
    return _PlainProgress(total, desc, enabled and lines)
