"""Grain kept: the photo's noise, measured where it is flat and in focus, restored where the blur removed it.

A lens blur averages the sensor's noise away, so a blurred backdrop next to a grainy sharp subject looks plastic, and
an 8-bit output of a smooth blur shows 1-code contour bands once contrast is pushed. This is a *finishing step* for
display-referred photos (8/16-bit sRGB), applied by ``bokehray render`` after the render and before writing (on by
default for them, ``--no-grain`` turns it off; never for linear EXR / float TIFF input): the render itself, which
the accuracy benchmarks score against exact references, stays free of it.

* **Measured** (:func:`measure_grain`): on tiles of :data:`TILE` pixels, the standard deviation of a high-pass of
  the photo's sRGB values (the photo minus a Gaussian of :data:`HIGHPASS_SIGMA` px) per tile; the photo's grain
  is the :data:`FLAT_QUANTILE` quantile over the tiles (the flattest tiles hold noise only; a textured tile is
  louder). The grain is the sensor's, the same on the sharp subject and on the photo's own soft backdrop, so all
  tiles count, not only those the render keeps in focus (in a portrait the in-focus face is a few hundred tiles of
  skin, hair and eyes, none flat: measured there, the grain came out twice the photo's). Luma and each channel are
  measured, so grain that is mostly luma (a phone's JPEG) stays mostly luma.
* **Restored** (:func:`restore_grain`): a disc blur of radius ``r`` keeps ``k = min(1, 1 / (sqrt(pi) r))`` of the
  noise's standard deviation, so a pixel gets seeded Gaussian grain of ``sqrt(1 - k^2)`` times the photo's (sharp
  pixels: none; a blurred backdrop: all of it back), scaled so that its high-pass matches the measured one, added
  in sRGB (through the slope of the sRGB curve in linear light). 8-bit outputs also get a triangular dither of
  one code, in the same proportion. The noise is drawn from ``numpy.random.default_rng(seed)``: the same photo,
  map and options give the same file.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import cache

import numpy as np

from .._memory import row_bands

__all__ = ["FLAT_QUANTILE", "HIGHPASS_SIGMA", "TILE", "Grain", "GrainPlan", "keep_grain", "measure_grain",
           "output_bits", "plan_grain", "removed_share", "restore_grain"]

TILE = 16
"""The side of the tiles the grain is measured on (pixels)."""

HIGHPASS_SIGMA = 2.0
"""The high-pass the grain is measured with: the photo minus a Gaussian blur of this many pixels."""

FLAT_QUANTILE = 0.2
"""The grain is this quantile of the in-focus tiles' high-pass standard deviations (the flat ones)."""

_MIN_TILES = 8  # fewer tiles than this (a frame under about 64 x 80 px): no grain is measured
_LUMA = np.array([0.2126, 0.7152, 0.0722], np.float32)


@dataclass(frozen=True, slots=True)
class Grain:
    """The photo's grain: the high-pass standard deviation (sRGB values, 1 = white) of its luma and of each channel
    in flat in-focus areas, and how many tiles it was measured on."""

    luma: float
    channels: tuple[float, float, float]
    tiles: int

    @property
    def codes(self) -> float:
        """The luma grain in 8-bit codes."""
        return self.luma * 255.0


def _highpass(x: np.ndarray) -> np.ndarray:
    import cv2

    return x - cv2.GaussianBlur(x, (0, 0), HIGHPASS_SIGMA, borderType=cv2.BORDER_REFLECT)


_MARGIN = 8  # the high-pass's reach (OpenCV's kernel for sigma 2: 17 taps) around each measured tile
_MAX_TILES = 1024  # at most this many tiles are measured (a regular subsample of a larger frame's): a 1 MP strip


def _srgb(rgb: np.ndarray) -> np.ndarray:
    """The sRGB curve in float32 (``bokehray.colour.linear_to_srgb`` works in float64, exact to the last bit, 3x
    slower; a grain measurement needs a hundredth of a code)."""
    c = np.clip(np.asarray(rgb, np.float32), np.float32(0.0), np.float32(1.0))
    enc = np.float32(1.055) * np.power(np.maximum(c, np.float32(0.0031308)), np.float32(1 / 2.4)) - np.float32(0.055)
    return np.where(c <= np.float32(0.0031308), c * np.float32(12.92), enc).astype(np.float32)


def _patches(image: np.ndarray) -> np.ndarray:
    """The tiles to measure with their margins, ``n x (TILE + 2 _MARGIN)^2 x 3`` linear RGB: every tile whose margin
    lies inside the frame, or a regular subsample of at most ``_MAX_TILES`` of them."""
    h, w = image.shape[:2]
    t, m = TILE, _MARGIN
    th, tw = max(0, (h - 2 * m) // t), max(0, (w - 2 * m) // t)
    step = max(1, math.ceil(math.sqrt(th * tw / _MAX_TILES))) if th * tw else 1
    ty, tx = np.meshgrid(np.arange(0, th, step), np.arange(0, tw, step), indexing="ij")
    y0, x0 = (ty.ravel() * t), (tx.ravel() * t)  # patch origins (the tile starts _MARGIN further in)
    span = np.arange(t + 2 * m)
    rows = (y0[:, None] + span)[:, :, None]
    cols = (x0[:, None] + span)[:, None, :]
    return image[rows, cols, :3]


def measure_grain(image: np.ndarray) -> Grain:
    """The grain of a photo (linear RGB): the ``FLAT_QUANTILE`` quantile of its tiles' high-pass standard
    deviations, in sRGB values. Fewer than ``_MIN_TILES`` tiles: no grain. The tiles are measured as a strip of
    patches, each with the high-pass's reach around it (so a 12 MP photo costs a 4 MP strip, not the frame)."""
    a = np.asarray(image, np.float32)
    a = a[..., None] if a.ndim == 2 else a
    patches = _patches(a if a.shape[2] >= 3 else np.repeat(a[..., :1], 3, axis=2))  # grey: three equal channels
    n, p = patches.shape[:2]
    if n < _MIN_TILES:
        return Grain(0.0, (0.0, 0.0, 0.0), n)
    srgb = _srgb(patches).reshape(n * p, p, 3)
    t, m = TILE, _MARGIN

    def level(x: np.ndarray) -> float:
        hp = _highpass(np.ascontiguousarray(x)).reshape(n, p, p)[:, m : m + t, m : m + t]
        return float(np.quantile(hp.reshape(n, -1).std(axis=1), FLAT_QUANTILE))

    luma = level(srgb @ _LUMA)
    channels = tuple(level(srgb[..., c]) for c in range(3))
    return Grain(luma, channels, n)


def removed_share(coc: np.ndarray) -> np.ndarray:
    """``sqrt(1 - k^2)`` per pixel, ``k = min(1, 1 / (sqrt(pi) r))`` the share of the noise's standard deviation a
    disc blur of radius ``r`` keeps: the share of the grain to restore (0 where sharp, towards 1 in a wide blur)."""
    r = np.asarray(coc, np.float32)
    kept = np.minimum(1.0, 1.0 / np.maximum(math.sqrt(math.pi) * r, 1e-6))
    return np.sqrt(np.maximum(0.0, 1.0 - kept * kept)).astype(np.float32)


def _in_bands(bands: list[tuple[int, int]], run: Callable[[int, int, int], None]) -> None:
    """``run(i, y0, y1)`` over the row ``bands`` (:func:`~bokehray._memory.row_bands`, band ``i``) on every core:
    NumPy's arithmetic and random fills release the GIL on arrays this large."""
    with ThreadPoolExecutor(max_workers=max(1, min(len(bands), os.cpu_count() or 1))) as pool:
        for f in [pool.submit(run, i, y0, y1) for i, (y0, y1) in enumerate(bands)]:
            f.result()


@cache
def _unit_gain() -> float:
    """The factor that gives white Gaussian noise of standard deviation 1 a high-pass (:func:`_highpass`) of
    standard deviation 1: ``1 / sqrt(sum (delta - G)^2)``, the sum over the high-pass's own response to an impulse
    (exact away from the frame's border)."""
    impulse = np.zeros((8 * _MARGIN + 1,) * 2, np.float32)
    impulse[4 * _MARGIN, 4 * _MARGIN] = 1.0
    return 1.0 / math.sqrt(float(np.square(_highpass(impulse).astype(np.float64)).sum()))


def _split(grain: Grain) -> tuple[float, tuple[float, float, float]]:
    """The standard deviations of the noise shared by the three channels (``a``) and of each one's own (``b_c``), so
    that channel ``c`` gets ``ch_c^2 = a^2 + b_c^2`` and the luma ``luma^2 = a^2 + sum w_c^2 b_c^2`` (``w``: the
    luma weights)."""
    w2 = _LUMA.astype(np.float64) ** 2
    ch2 = np.square(grain.channels)
    a2 = (grain.luma**2 - float((w2 * ch2).sum())) / (1.0 - float(w2.sum()))
    a2 = min(max(a2, 0.0), float(ch2.min()))
    return math.sqrt(a2), tuple(math.sqrt(max(0.0, v - a2)) for v in ch2)


_SLOPE_SHIFT = 15
""":func:`_srgb_slope`'s table is indexed by a float32's top 17 bits: buckets of relative width 1/256 or less, over
which the slope (a power 0.58 of the value) varies by 0.3 % at most (1.7 % in the bucket of the toe's end, where
the curve's own slope jumps by as much)."""


@cache
def _slope_table() -> np.ndarray:
    """d(linear)/d(sRGB) at the middle of each float32 bucket of [0, 1] (:data:`_SLOPE_SHIFT`): ``2.4 / 1.055 *
    lin^(1.4 / 2.4)``, ``1 / 12.92`` on the toe; 0 at 1 (a clipped value gets no grain)."""
    one = int(np.float32(1.0).view(np.uint32)) >> _SLOPE_SHIFT
    starts = (np.arange(one + 2, dtype=np.uint32) << _SLOPE_SHIFT).view(np.float32).astype(np.float64)
    mid = (starts[:-1] + starts[1:]) / 2
    slope = np.where(mid > 0.0031308, 2.4 / 1.055 * np.power(mid, 1.4 / 2.4), 1.0 / 12.92).astype(np.float32)
    slope[one] = 0.0
    slope.flags.writeable = False
    return slope


def _srgb_slope(v: np.ndarray) -> np.ndarray:
    """d(linear)/d(sRGB) at linear values ``v`` (clipped to [0, 1]; 0 at 1 and above), from :func:`_slope_table`."""
    x = np.clip(v, np.float32(0.0), np.float32(1.0))
    x += np.float32(0.0)  # -0.0 -> +0.0 (its bit pattern would index past the table)
    return _slope_table()[x.view(np.uint32) >> _SLOPE_SHIFT]


def restore_grain(rendered: np.ndarray, grain: Grain, removed: np.ndarray, *, seed: int = 0,
                  dither_bits: int | None = None) -> np.ndarray:
    """``rendered`` (linear RGB[A], written in place when float32 and writable) with the photo's ``grain`` added in
    sRGB where the blur ``removed`` it (:func:`removed_share`), and a triangular dither of one code for an output
    of ``dither_bits`` (8: an 8-bit file; None: none). Seeded: the same inputs give the same pixels (each band of
    rows draws from its own generator, spawned from ``seed``, so the bands run on every core in any order). Values
    stay non-negative; alpha is not touched."""
    out = rendered if rendered.dtype == np.float32 and rendered.flags.writeable else rendered.astype(np.float32)
    if grain.luma <= 0.0 and not dither_bits:
        return out
    h, w = out.shape[:2]
    gain = _unit_gain()
    shared_std, own_std = _split(grain)
    planes = out[..., None] if out.ndim == 2 else out
    own = [own_std[c] if planes.shape[2] >= 3 else 0.0 for c in range(min(3, planes.shape[2]))]  # grey: the luma's
    dither_q = None
    if dither_bits and grain.luma * (2**dither_bits - 1) < 0.5:  # grain of half a code or more dithers already
        dither_q = np.float32(1.0 / (2**dither_bits - 1))
    bands = list(row_bands(h, w))
    seeds = np.random.SeedSequence(seed).spawn(len(bands))

    def band(i: int, y0: int, y1: int) -> None:
        share = np.asarray(removed[y0:y1], np.float32)
        if not share.any():  # sharp: nothing removed, nothing to restore
            return
        rng = np.random.default_rng(seeds[i])
        shape = (y1 - y0, w)
        shared = rng.standard_normal(shape, dtype=np.float32)
        shared *= np.float32(gain * shared_std)
        if dither_q is not None:
            shared += (rng.random(shape, dtype=np.float32) - rng.random(shape, dtype=np.float32)) * dither_q
        for c, own_c in enumerate(own):
            noise = shared.copy()
            if own_c > 0.0:
                noise += rng.standard_normal(shape, dtype=np.float32) * np.float32(gain * own_c)
            noise *= share
            v = planes[y0:y1, :, c]
            noise *= _srgb_slope(v)  # through the sRGB curve's slope: the grain is in sRGB codes
            v += noise
            np.maximum(v, 0.0, out=v)

    _in_bands(bands, band)
    return out


def output_bits(path: str, bit_depth: int | None) -> int | None:
    """8 when ``path`` with ``bit_depth`` is written with 8-bit codes (JPEG; PNG by default; TIFF at 8), else None."""
    from pathlib import Path

    from ..formats import FORMATS

    fmt = FORMATS.get(Path(path).suffix.lower())
    eight = fmt == "JPEG" or (fmt == "PNG" and bit_depth in (None, 8)) or (fmt == "TIFF" and bit_depth == 8)
    return 8 if eight else None


@dataclass(frozen=True, slots=True)
class GrainPlan:
    """What the finishing step needs from before the render (the photo and its map are freed during it): the
    photo's :class:`Grain` and the share of it to restore per pixel (float16)."""

    grain: Grain
    removed: np.ndarray

    def describe(self) -> str:
        if self.grain.luma <= 0.0:
            return "none measured (the photo is clean)"
        return f"{self.grain.codes:.2f} codes measured in the photo's flat areas, restored where the blur removed it"


def plan_grain(image: np.ndarray, coc: np.ndarray) -> GrainPlan:
    """The grain of ``image`` and the share to restore for the CoC radii ``coc`` (pixels)."""
    coc = np.asarray(coc, np.float32)
    removed = np.empty(coc.shape, np.float16)

    def band(_i: int, y0: int, y1: int) -> None:
        removed[y0:y1] = removed_share(coc[y0:y1])

    _in_bands(list(row_bands(*coc.shape)), band)
    return GrainPlan(measure_grain(image), removed)


def keep_grain(rendered: np.ndarray, photo: np.ndarray, disparity: np.ndarray, blur, *, seed: int = 0,
               dither_bits: int | None = None) -> np.ndarray:
    """The finishing step of ``bokehray render`` in one call (``bokehray.keep_grain``): ``rendered`` (a render of
    ``photo`` with ``disparity`` and ``blur``, a :class:`~bokehray.lens.BlurParams`) with the photo's grain
    restored where the blur removed it, seeded; ``dither_bits=8`` also dithers for an 8-bit file. ``rendered`` is
    written in place when it is a writable float32 array. For display-referred photos: the render itself
    (``bokehray.render``) never adds grain."""
    plan = plan_grain(np.asarray(photo, np.float32), blur.coc_radius(np.asarray(disparity, np.float32)))
    return restore_grain(rendered, plan.grain, plan.removed, seed=seed, dither_bits=dither_bits)
