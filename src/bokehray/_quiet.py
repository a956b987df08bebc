"""Warp without its banner: quiet log level whenever Warp is imported, and an init without the native
"no CUDA driver" line on CPU-only machines.

``import bokehray`` does not import Warp (0.6 s): the first module that needs it does, when a render starts.
:func:`quiet_warp_on_import` makes that import set ``warp.config.log_level`` to warnings, whoever triggers it.
"""

from __future__ import annotations

import importlib.abc
import importlib.machinery
import sys

__all__ = ["init_warp_quietly", "quiet_warp_on_import"]


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
    import os

    import warp as wp

    _quiet(wp)
    try:
        fd = sys.stderr.fileno()
    except (AttributeError, OSError, ValueError):  # stderr is not a file (e.g. captured by a test runner)
        fd = None
    if debug or fd is None:
        wp.init()
        return
    sys.stderr.flush()
    saved = os.dup(fd)
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, fd)
        wp.init()
    finally:
        os.dup2(saved, fd)
        os.close(saved)
        os.close(devnull)
