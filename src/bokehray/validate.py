"""Validation at the public boundary: the one place that checks arrays and argument types.

Every check raises :class:`~bokehray.errors.InputError` with the argument's name and
what was expected, so callers (the API, the readers, the datasets, the PISA masks,
the ray tracer, the refiner) report bad input the same way.
"""

from __future__ import annotations

import math
import os
from numbers import Integral, Real

import numpy as np

from ._memory import available_bytes
from .errors import InputError, ResourceError

__all__ = [
    "MAX_RADIANCE",
    "array_shape",
    "check_bool",
    "check_disparity",
    "check_finite",
    "check_image",
    "check_int",
    "check_number",
    "check_path",
    "check_radiance",
    "check_type",
    "first_bad_index",
    "fits_in_memory",
    "number_text",
    "real",
    "shown",
]  # fmt: skip

MAX_RADIANCE = 1e36
"""Largest radiance any level renders: the preview's prefix sums and the ray tracer's ray averages add up to a few
hundred values in float32 (max 3.4e38), so beyond this a render could overflow. Refused up front, for every level."""


def first_bad_index(mask: np.ndarray) -> tuple[int, ...]:
    """Index of the first True element of ``mask`` (row-major), so ``[:2]`` is its (y, x)."""
    return tuple(int(i) for i in np.unravel_index(int(np.argmax(mask)), mask.shape))


def check_finite(a: np.ndarray, name: str, axes: str = "(y, x)") -> None:
    """Raise if ``a`` holds NaN or Inf, naming the first bad index as ``axes``."""
    bad = ~np.isfinite(a)
    if bad.any():
        raise InputError(f"{name}: expected finite values, got NaN/Inf at {axes} = {first_bad_index(bad)}")


def check_type(value: object, types: type | tuple[type, ...], name: str, what: str) -> None:
    """Raise unless ``value`` is an instance of ``types``; ``what`` names the expected type for the message."""
    if not isinstance(value, types):
        raise InputError(f"{name}: expected {what}, got {type(value).__name__}")


def check_bool(value: object, name: str) -> bool:
    """``True`` or ``False`` (NumPy's too), nothing else: ``"yes"``, ``1`` or ``None`` would each be taken for one."""
    if not isinstance(value, (bool, np.bool_)):
        raise InputError(f"{name}: expected True or False, got {shown(value)}"[:200])
    return bool(value)


def array_shape(value: object, name: str) -> tuple:
    """``np.shape(value)``; a ragged nested list (rows of different lengths), which NumPy refuses with a ValueError,
    is an :class:`InputError` naming ``name``."""
    try:
        return np.shape(value)
    except ValueError:
        raise InputError(f"{name}: expected an array, got a ragged {type(value).__name__} (its rows differ in "
                         "length)") from None


def check_path(value: object, name: str = "path") -> None:
    """A file path: ``str`` or an ``os.PathLike`` giving one (not None, a number or bytes, which pathlib refuses
    with a TypeError)."""
    try:
        text = os.fspath(value)  # type: ignore[call-overload]
    except TypeError:
        text = None
    if not isinstance(text, str):
        got = (type(value).__name__ if text is None or isinstance(value, bytes)
               else f"{type(value).__name__} giving {type(text).__name__}")
        raise InputError(f"{name}: expected a file path (str or os.PathLike), got {got}")


def check_int(value: object, name: str, lo: int | None = None, hi: int | None = None) -> int:
    """An integer (not a bool, not a float that happens to be whole) within [lo, hi]."""
    if isinstance(value, bool) or not isinstance(value, Integral):
        raise InputError(f"{name}: expected an integer, got {value!r}")
    v = int(value)
    if (lo is not None and v < lo) or (hi is not None and v > hi):
        raise InputError(f"{name}: expected an integer in [{lo if lo is not None else '-inf'}, "
                         f"{hi if hi is not None else 'inf'}], got {shown(v)}")
    return v


def shown(value: object) -> str:
    """``repr(value)``, or a short description of an integer too long to print (10**400 has 401 digits)."""
    if isinstance(value, Integral) and not isinstance(value, bool):
        digits = len(str(abs(int(value)))) if abs(int(value)) < 10 ** 4000 else "4000+"
        if digits == "4000+" or digits > 40:
            return f"an integer of {digits} digits"
    return repr(value)


def number_text(value: float) -> str:
    """A refused number as it was given, not rounded: the shortest text that reads back as the same float
    (``1.0000001``, not ``:g``'s ``1``; ``1e-05``; a whole number without ``.0``)."""
    v = float(value)
    return str(int(v)) if v.is_integer() and abs(v) < 1e16 else repr(v)


def real(value: object, name: str, *, inf: bool = False) -> float:
    """``value`` as a float: a real number (not a bool, not a string, not None), finite unless ``inf`` allows
    +-inf; an integer beyond float's range (``10**400``) is refused like an infinity, not an OverflowError."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, Real):
        raise InputError(f"{name}: expected a number, got {shown(value)}")
    try:
        v = float(value)
    except (OverflowError, ValueError):
        v = math.nan
    if math.isnan(v) or (math.isinf(v) and not inf):
        raise InputError(f"{name}: expected {'a number (inf allowed)' if inf else 'a finite number'}, "
                         f"got {shown(value)}")
    return v


def check_number(value: object, name: str, lo: float | None = None, *, lo_open: bool = False) -> float:
    """A finite real number (not a bool, not a string) >= ``lo`` (> ``lo`` with ``lo_open``)."""
    v = real(value, name)
    if lo is not None and (v <= lo if lo_open else v < lo):
        raise InputError(f"{name}: expected a finite value {'>' if lo_open else '>='} {lo:g}, got {value!r}")
    return v


def check_image(image: np.ndarray, name: str = "image", channels: tuple[int, ...] = (1, 3, 4)) -> np.ndarray:
    """Validate a scene-linear image: H x W (as H x W x 1) or H x W x C with C in ``channels``, floating point,
    finite. Returns it as contiguous float32 (no copy when it already is)."""
    if not isinstance(image, np.ndarray) and not hasattr(image, "__array__"):
        raise InputError(f"{name}: expected a NumPy array, got {type(image).__name__}")
    a = np.asarray(image)
    if a.ndim == 2 and 1 in channels:
        a = a[..., None]
    if a.ndim != 3 or a.shape[2] not in channels:
        raise InputError(f"{name}: expected H x W x C with C in {channels}, got shape {np.shape(image)}")
    if a.shape[0] < 1 or a.shape[1] < 1:
        raise InputError(f"{name}: expected a non-empty image, got shape {a.shape}")
    if not np.issubdtype(a.dtype, np.floating):
        raise InputError(
            f"{name}: expected floating-point scene-linear values, got dtype {a.dtype}; "
            "decode integer images with bokehray.read_image"
        )
    a = np.ascontiguousarray(a, np.float32)
    check_finite(a, name, "(y, x, c)")
    return a


def check_radiance(image: np.ndarray, name: str = "image") -> None:
    """Refuse radiance beyond :data:`MAX_RADIANCE` (a finite float32 near its maximum would overflow a render)."""
    peak = 0.0
    if image.size:  # |image|.max() as max(max, -min): the same value (NaN stays NaN), no frame-sized |image|
        hi, lo = float(image.max()), float(image.min())
        peak = hi if hi != hi else max(hi, -lo)
    if peak > MAX_RADIANCE:
        raise InputError(f"{name}: radiance up to {peak:.3g}; renders sum values in float32 and need them within "
                         f"+-{MAX_RADIANCE:g} (scale the image down)")


def check_disparity(disparity: np.ndarray, shape_hw: tuple[int, int], name: str = "disparity") -> np.ndarray:
    """Validate a disparity map: shape ``shape_hw``, finite, within [0, 1]. Returns float32."""
    if not isinstance(disparity, np.ndarray) and not hasattr(disparity, "__array__"):
        raise InputError(f"{name}: expected a NumPy array, got {type(disparity).__name__}")
    d = np.asarray(disparity)
    if d.ndim == 3 and d.shape[2] == 1:
        d = d[..., 0]
    if d.shape != tuple(shape_hw):
        raise InputError(
            f"{name}: expected shape {tuple(shape_hw)} (the image's H x W), got {d.shape}; "
            "resize it first (CLI: --resize-disparity)"
        )
    if not (np.issubdtype(d.dtype, np.floating) or np.issubdtype(d.dtype, np.integer)):
        raise InputError(f"{name}: expected a numeric array, got dtype {d.dtype}")
    d = np.asarray(d, np.float32)
    check_finite(d, name)
    lo, hi = float(d.min()), float(d.max())
    if lo < 0.0 or hi > 1.0:
        raise InputError(
            f"{name}: expected finite values in [0, 1] (1 = nearest), got [{lo:.4g}, {hi:.4g}]; "
            "normalise it, or convert metric depth with bokehray.disparity_from_depth"
        )
    return np.ascontiguousarray(d)


def fits_in_memory(shape: tuple[int, ...], bytes_per_px: float, what: str) -> None:
    """Refuse work on an ``H x W (x C)`` array from its shape alone, before anything is copied, when its peak
    (``bytes_per_px`` times the pixels) exceeds the memory available now: a broadcast view of 1e10 pixels takes
    no memory until a function touches it, and then NumPy's raw ``MemoryError`` (or the machine's swap) would
    answer instead. ``what`` starts the message (it names the argument or the file)."""
    if len(shape) < 2 or not all(isinstance(v, (int, np.integer)) for v in shape[:2]):
        return  # the caller's own shape check says what is wrong
    h, w = int(shape[0]), int(shape[1])
    need, have = h * w * bytes_per_px, available_bytes()
    if need > have:
        raise ResourceError(f"{what}: {w} x {h} px needs about {int(need) >> 20:,} MB, but only {have >> 20:,} MB "
                            "of memory is available")
