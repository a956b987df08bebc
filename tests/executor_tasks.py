"""Task functions for tests/core/test_executor.py: top-level, so spawned pool workers and Dask workers import them
(this folder is on their sys.path, as on the test process's)."""

from __future__ import annotations

import hashlib
import os
import signal
from pathlib import Path

import numpy as np

from bokehray.errors import InputError
from bokehray.output.atomic import atomic_write


def digest(task: tuple[int, int]) -> str:
    """A pure function of (seed, index)."""
    seed, index = task
    a = np.random.default_rng(np.random.SeedSequence([seed, index])).random(1000)
    return hashlib.sha256(a.tobytes()).hexdigest()


def fail_on_odd(index: int) -> int:
    if index % 2:
        raise InputError(f"task {index}: bad input")
    return index


def write_or_die(task: tuple[str, int, bool]) -> dict:
    """Write OUT/out_<i>.bin (64 KiB) atomically; with ``die``, the first attempt kills its own process halfway
    through the write (a marker file remembers the attempt), so the output is left as a temporary only."""
    folder, index, die = task
    out = Path(folder) / f"out_{index}.bin"
    data = bytes([index % 256]) * 65536
    marker = Path(folder) / f"attempted_{index}"
    first = not marker.exists()
    marker.touch()

    def encode(tmp: str) -> None:
        with open(tmp, "wb") as fh:
            fh.write(data[: len(data) // 2])
            fh.flush()
            if die and first:
                os.kill(os.getpid(), signal.SIGKILL)
            fh.write(data[len(data) // 2:])

    atomic_write(out, encode)
    return {"index": index, "pid": os.getpid()}


def always_die(index: int) -> None:
    os.kill(os.getpid(), signal.SIGKILL)
