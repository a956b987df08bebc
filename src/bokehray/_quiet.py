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

All of them step aside with ``debug=True`` (the CLI's ``--debug``), which :func:`init_warp_quietly`
remembers for :func:`native_stderr_quiet`.
"""

from __future__ import annotations

import contextlib
import importlib.abc
import importlib.machinery
import os
import sys
import warnings
from collections.abc import Iterator

__all__ = ["collect_warnings", "init_warp_quietly", "native_stderr_quiet", "quiet_warp_on_import"]

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

    def create_module(self, spec):  # noqa: ANN001 - the importlib protocol
        return self._inner.create_module(spec)

    def exec_module(self, module) -> None:  # noqa: ANN001
        self._inner.exec_module(module)
        _quiet(module)


class _QuietFinder(importlib.abc.MetaPathFinder):
    """Finds ``warp`` as the other finders do, and wraps its loader so the module is quietened once loaded."""

    def find_spec(self, name, path=None, target=None):  # noqa: ANN001
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
