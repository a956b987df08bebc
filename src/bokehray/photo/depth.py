"""Depth maps as people have them: relative maps, reversed maps, integer codes, missing depth.

* **Relative maps** (:func:`normalize_relative`): min-max between the 0.5th and 99.5th percentiles, clipped to
  [0, 1]; ``invert`` flips a near-is-dark map.
* **Reversed maps** (:func:`looks_reversed`): a map whose frame border (5 % bands) is nearer than its centre
  (the middle ninth) by more than ``REVERSED_MARGIN`` is probably near-is-dark.
* **Metric depth** (:func:`read_depth`): float files hold metres, integer files codes times ``scale``; depth
  <= 0 (no measurement: depth cameras write 0) and +/-inf are infinitely far (``bokehray.lens.disparity_from_depth``).

docs/conventions.md and docs/usage.md say the same for users.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from .._memory import on_cores, row_bands
from ..errors import InputError
from ..formats import first_index, format_of
from ..validate import check_path

__all__ = ["BORDER_NEAR", "NORMALIZE_PERCENTILES", "REVERSED_MARGIN", "looks_reversed", "missing_depth_share",
           "normalize_bounds", "normalize_relative", "read_depth", "subsample"]

NORMALIZE_PERCENTILES = (0.5, 99.5)
"""The robust min and max of ``--normalize``, in percent."""

REVERSED_MARGIN = 0.2
"""How much nearer (in normalised disparity) the frame border must be than the centre to call a map reversed."""

BORDER_NEAR = 0.85
"""A frame border whose median disparity is at least this sits on the nearest values."""

def subsample(d: np.ndarray, most: int = 512) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``d`` on a grid of at most ``most`` samples along its longer side: ``(samples, rows, cols)``, the samples
    ``d[rows][:, cols]``. Each sample is a pixel of its ``step x step`` block at an offset drawn per row and per
    column (a fixed seed: the same map gives the same samples); a regular grid (``d[::step, ::step]``) saw one phase
    of a map with a period dividing the step (1-2 px stripes or a checkerboard above 512 px read as all at one
    depth). Maps of at most ``most`` px a side are taken whole."""
    step = max(1, int(math.ceil(max(d.shape) / most)))
    rng = np.random.default_rng(0x5EED)

    def picks(n: int) -> np.ndarray:
        starts = np.arange(0, n, step)
        return starts + (rng.random(len(starts)) * np.minimum(step, n - starts)).astype(np.int64)

    rows, cols = picks(d.shape[0]), picks(d.shape[1])
    return d[np.ix_(rows, cols)], rows, cols


def looks_reversed(disparity: np.ndarray) -> tuple[bool, str]:
    """Does the map look near-is-dark? Returns ``(reversed, why)``.

    Two cues, either of which flags the map (medians over the frame's 5 % border bands and its middle ninth):

    * the border is nearer than the centre by more than ``REVERSED_MARGIN`` (a subject farther than all that
      surrounds it), or
    * the border sits on the nearest values (median >= ``BORDER_NEAR``) while at least 2 % of the frame is
      farther by more than ``REVERSED_MARGIN`` (a background nearer than the things in front of it).

    In a photo the border is usually background or ground, rarely nearer than everything else; shots through
    a close frame (a window, foliage all round) can trip it, which is why this is a warning, not an error.
    """
    d = np.asarray(disparity, np.float32)
    s, _, _ = subsample(d)
    h, w = s.shape
    by, bx = max(1, h // 20), max(1, w // 20)
    border = np.concatenate([s[:by].ravel(), s[-by:].ravel(), s[by:-by, :bx].ravel(), s[by:-by, -bx:].ravel()])
    centre = s[h // 3 : h - h // 3, w // 3 : w - w // 3]
    b, c = float(np.median(border)), float(np.median(centre))
    if b - c > REVERSED_MARGIN:
        return True, f"the frame border is nearer than its centre (median disparity {b:.2f} vs {c:.2f})"
    farther = float(np.mean(s < b - REVERSED_MARGIN))
    if b >= BORDER_NEAR and farther >= 0.02:
        return True, (f"the frame border sits on the nearest values (median disparity {b:.2f}) with "
                      f"{farther:.0%} of the frame behind it")
    return False, ""


def normalize_bounds(values: np.ndarray, source: str = "disparity") -> tuple[float, float, str]:
    """The values :func:`normalize_relative` maps to 0 and 1, and how they were found: the 0.5th and 99.5th
    percentiles, or the min and max where those two are equal (a map mostly at one value). Non-finite values and a
    constant map are refused."""
    v = np.asarray(values).reshape(-1) if np.ndim(values) == 0 else np.asarray(values)
    if not _all_finite(v):
        raise InputError(f"{source}: --normalize needs finite values; NaN or Inf found")
    lo, hi = percentiles(v, NORMALIZE_PERCENTILES)
    how = f"{NORMALIZE_PERCENTILES[0]:g}th..{NORMALIZE_PERCENTILES[1]:g}th percentiles"
    if not hi > lo:
        lo, hi = float(np.float64(v.min())), float(np.float64(v.max()))
        how = "min..max: the percentiles are equal"
    if not hi > lo:
        raise InputError(f"{source}: the map is constant ({lo:g}): nothing to normalise, every pixel is at one depth")
    return lo, hi, how


def percentiles(values: np.ndarray, q: tuple[float, ...]) -> tuple[float, ...]:
    """``np.percentile(np.asarray(values, np.float64), q)`` of finite real values, bit for bit, without the float64
    copy of the frame: the order statistics NumPy's linear method reads are found by one partition in the values'
    own dtype (the conversion to float64 keeps their order) and interpolated as NumPy does (its ``_lerp``). At
    12 MP a float32 map's two percentiles cost a partition of 48 MB instead of a 96 MB copy and its partition."""
    a = np.asarray(values)
    if a.size == 0 or a.dtype.kind not in "fiu":
        return tuple(float(x) for x in np.percentile(np.asarray(a, np.float64), q))
    a = a.ravel()
    n = a.size
    virtual = (n - 1) * np.true_divide(np.asarray(q, np.float64), 100)
    prev = np.floor(virtual)
    prev[virtual >= n - 1] = -1  # NumPy's bounds: past the last index, the largest value
    prev[virtual < 0] = 0
    prev_i = prev.astype(np.intp)
    next_i = np.where(prev_i == -1, -1, prev_i + 1).astype(np.intp)
    part = np.partition(a, np.unique(np.concatenate([prev_i, next_i]) % n))
    lo, hi = part[prev_i].astype(np.float64), part[next_i].astype(np.float64)
    gamma = np.asarray(virtual - prev_i, np.float64)
    diff = hi - lo
    out = lo + diff * gamma
    np.subtract(hi, diff * (1 - gamma), out=out, where=gamma >= 0.5)
    return tuple(float(x) for x in out)


def _all_finite(v: np.ndarray) -> bool:
    """No NaN or Inf in ``v`` (integers always), a band of rows at a time (no frame-sized mask)."""
    if v.dtype.kind != "f":
        return True
    return all(bool(np.isfinite(v[a:b]).all()) for a, b in _row_bands(v))


def _row_bands(v: np.ndarray) -> list[tuple[int, int]]:
    """:func:`bokehray._memory.row_bands` of a map of one or more dimensions (a band of its first axis)."""
    return list(row_bands(v.shape[0], int(np.prod(v.shape[1:], dtype=np.int64)))) or [(0, 0)]


def normalize_relative(values: np.ndarray, *, invert: bool = False, source: str = "disparity",
                       with_bounds: bool = False) -> np.ndarray | tuple[np.ndarray, tuple[float, float, str]]:
    """A relative map of any range (e.g. a monocular model's inverse depth) to disparity in [0, 1].

    Min-max between the 0.5th and 99.5th percentiles of the finite values, clipped to [0, 1], so a few outliers
    do not squash the rest; ``invert`` flips it for near-is-dark maps. Non-finite values are refused. With
    ``with_bounds``, ``(d, (lo, hi, how))``: the bounds it used and how they were found (:func:`normalize_bounds`).

    The arithmetic is float64's, a band of rows at a time, the bands on the CPU's cores (NumPy's loops release the
    GIL): the values of the whole-frame expression, without its frame-sized float64 temporaries.
    """
    v = np.asarray(values)
    bounds = normalize_bounds(v, source)
    lo, hi, _ = bounds
    out = np.empty(v.shape, np.float32)

    def band(a: int, b: int) -> None:
        d = np.subtract(v[a:b], lo, dtype=np.float64)
        np.divide(d, hi - lo, out=d)
        np.clip(d, 0.0, 1.0, out=d)
        if invert:
            np.subtract(1.0, d, out=d)
        out[a:b] = d

    on_cores(band, _row_bands(v))
    return (out, bounds) if with_bounds else out


def missing_depth_share(depth_m: np.ndarray) -> float:
    """The share of pixels without a depth: <= 0 (no measurement) or infinite (sky), which render infinitely far."""
    z = np.asarray(depth_m)
    with np.errstate(invalid="ignore"):
        return float((~np.isfinite(z) | (z <= 0)).mean())


def read_depth(path: str | os.PathLike[str], *, scale: float | None = None) -> np.ndarray:
    """Read a metric depth map in metres (float64 ``H x W``), the one depth reader of the CLI and the API.

    Float EXR (channel ``Z``, the standard depth channel, whatever other channels the file holds; without ``Z``
    its only channel, or several only if they are all equal), float TIFF and float ``.npy`` hold metres
    (times ``scale`` if given). Integer maps (16-bit PNG or TIFF from depth cameras and phones, integer NPY) hold
    codes and need ``scale``: metres per code, e.g. 0.001 for millimetres. Missing depth (0, negative, +/-inf) is
    kept (-inf as +inf): ``bokehray.lens.disparity_from_depth`` renders it infinitely far. NaN is refused, naming
    the file. Float64, not float32 like the other readers: ``1200 * 0.001`` m must stay the 1.2 m a user types.
    """
    from .read import load_samples, single_channel  # the codecs: not imported by `bokehray --help`

    check_path(path)
    p = Path(path)
    if scale is not None and (isinstance(scale, bool) or not isinstance(scale, (int, float))
                              or not (math.isfinite(scale) and scale > 0)):
        raise InputError(f"--depth-scale: expected metres per code > 0 (0.001 for millimetres), got {scale!r}")
    p, fmt = format_of(p, ("PNG", "TIFF", "EXR", "NPY"), "depth")
    a = single_channel(p, load_samples(p, fmt, (("Z",),), map_of="depth"), fmt, "depth")
    if a.dtype.kind in "iu":
        if scale is None:
            raise InputError(f"{p}: holds integer codes ({a.dtype}), not metres: give --depth-scale, metres per "
                             "code (0.001 for a millimetre map)")
    elif a.dtype.kind != "f":
        raise InputError(f"{p}: expected float depth in metres or integer codes, got {a.dtype}")
    z = a.astype(np.float64) * (1.0 if scale is None else scale)
    nan = np.isnan(z)
    if nan.any():
        y, x = first_index(nan)
        raise InputError(f"{p}: expected depth in metres or +/-Inf (no depth), got NaN at (y, x) = ({y}, {x})")
    z[z == -np.inf] = np.inf  # no depth either way
    return z
