"""File formats by extension, and the checks on stored values that the readers and the writers share."""

from __future__ import annotations

import errno
import os
from pathlib import Path

import numpy as np

from .errors import InputError

__all__ = ["F32_MAX", "FORMATS", "HALF_MAX", "check_finite", "first_index", "format_of", "range_prefix", "to_float32"]

FORMATS = {
    ".png": "PNG", ".jpg": "JPEG", ".jpeg": "JPEG", ".tif": "TIFF", ".tiff": "TIFF", ".exr": "EXR", ".npy": "NPY",
}  # fmt: skip
HALF_MAX = 65504.0
F32_MAX = float(np.finfo(np.float32).max)


def format_of(
    path: str | os.PathLike[str], allowed: tuple[str, ...], what: str, *, read: bool = True
) -> tuple[Path, str]:
    """Check that ``path`` exists and is a regular file (when reading) and that its extension is one of the
    ``allowed`` formats."""
    p = Path(path)
    try:
        _check_file_kind(p, read)
    except OSError as e:
        if e.errno != errno.ENAMETOOLONG:
            raise
        longest = max(p.parts, key=lambda part: len(os.fsencode(part)))
        raise InputError(f"{p}: {'the file name' if longest == p.name else 'a folder name in it'} is "
                         f"{len(os.fsencode(longest))} bytes long, more than the file system takes (shorten it)") from None
    fmt = FORMATS.get(p.suffix.lower())
    if fmt not in allowed:
        exts = ", ".join(e for e, f in FORMATS.items() if f in allowed)
        action = "reading" if read else "writing"
        raise InputError(f"{p}: unsupported extension {p.suffix!r} for {action} {what}; expected one of {exts}")
    return p, fmt


def _check_file_kind(p: Path, read: bool) -> None:
    if read and not p.exists():
        raise InputError(f"{p}: file does not exist")
    if p.is_dir():
        raise InputError(f"{p}: expected a file, got a directory")
    if read and not p.is_file():  # opening a FIFO waits for a writer forever; a device never ends
        kind = "a named pipe (FIFO)" if p.is_fifo() else "a socket" if p.is_socket() else "a device"
        raise InputError(f"{p}: expected a regular file, got {kind}")


def first_index(mask: np.ndarray) -> tuple[int, ...]:
    """Index of the first True element (row-major), so ``[:2]`` is its (y, x)."""
    return tuple(int(i) for i in np.unravel_index(int(np.argmax(mask)), mask.shape))


def check_finite(a: np.ndarray, prefix: str, *, allow_pos_inf: bool = False) -> None:
    bad = ~np.isfinite(a) & (a != np.inf) if allow_pos_inf else ~np.isfinite(a)
    if bad.any():
        idx = first_index(bad)
        y, x, v = idx[0], idx[1], a[idx]
        kind = "NaN" if np.isnan(v) else ("+Inf" if v > 0 else "-Inf")
        raise InputError(f"{prefix} {kind} at (y, x) = ({y}, {x})")


F32_MAX = float(np.finfo(np.float32).max)


def range_prefix(p: Path) -> str:
    return f"{p}: expected values within float32's range (+-3.4e38), got"


def to_float32(a: np.ndarray, prefix: str, range_prefix: str, *, allow_pos_inf: bool = False) -> np.ndarray:
    """Cast stored samples to float32 after checking them as the file holds them (float32 samples are returned
    as they are, not copied: a 12 MP output's 144 MB).

    NaN/Inf are refused (``+Inf`` too unless ``allow_pos_inf``), and so are finite float64
    values beyond float32's range (1e300 would silently become +Inf): the message quotes the
    value in the file, not what the cast would have made of it.
    """
    check_finite(a, prefix, allow_pos_inf=allow_pos_inf)
    if a.dtype.kind == "f" and a.dtype.itemsize > 4:
        with np.errstate(invalid="ignore"):
            big = np.isfinite(a) & (np.abs(a) > F32_MAX)
        if big.any():
            idx = first_index(big)
            raise InputError(f"{range_prefix} {float(a[idx]):.4g} at (y, x) = ({idx[0]}, {idx[1]})")
    with np.errstate(over="ignore"):  # only +Inf (allowed) can get here unconverted; nothing overflows
        return a.astype(np.float32, copy=False)  # float32 already: itself (its callers only read it, or own it)
