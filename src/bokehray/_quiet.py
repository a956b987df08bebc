"""Warp initialisation without the native "no CUDA driver" line on CPU-only machines."""

from __future__ import annotations

import sys

__all__ = ["init_warp_quietly"]


def init_warp_quietly(debug: bool = False) -> None:
    """Initialise Warp without its native "no CUDA driver" line on CPU-only machines (shown with --debug)."""
    import os

    import warp as wp

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
