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
from dataclasses import dataclass

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


def _unit_noise(rng: np.random.Generator, shape: tuple[int, int]) -> np.ndarray:
    """Gaussian noise whose high-pass has a standard deviation of 1 (white noise, so the factor is exact enough on a
    256 x 256 sample)."""
    n = rng.standard_normal(shape, dtype=np.float32)
    probe = n[: min(256, shape[0]), : min(256, shape[1])]
    s = float(_highpass(np.ascontiguousarray(probe)).std()) if probe.size > 64 else 1.0
    n *= np.float32(1.0 / max(s, 1e-6))
    return n


def _split(grain: Grain) -> tuple[float, tuple[float, float, float]]:
    """The standard deviations of the noise shared by the three channels (``a``) and of each one's own (``b_c``), so
    that channel ``c`` gets ``ch_c^2 = a^2 + b_c^2`` and the luma ``luma^2 = a^2 + sum w_c^2 b_c^2`` (``w``: the
    luma weights)."""
    w2 = _LUMA.astype(np.float64) ** 2
    ch2 = np.square(grain.channels)
    a2 = (grain.luma**2 - float((w2 * ch2).sum())) / (1.0 - float(w2.sum()))
    a2 = min(max(a2, 0.0), float(ch2.min()))
    return math.sqrt(a2), tuple(math.sqrt(max(0.0, v - a2)) for v in ch2)


def restore_grain(rendered: np.ndarray, grain: Grain, removed: np.ndarray, *, seed: int = 0,
                  dither_bits: int | None = None) -> np.ndarray:
    """``rendered`` (linear RGB[A], written in place when float32 and writable) with the photo's ``grain`` added in
    sRGB where the blur ``removed`` it (:func:`removed_share`), and a triangular dither of one code for an output
    of ``dither_bits`` (8: an 8-bit file; None: none). Seeded: the same inputs give the same pixels. Values stay
    non-negative; alpha is not touched."""
    out = rendered if rendered.dtype == np.float32 and rendered.flags.writeable else rendered.astype(np.float32)
    if grain.luma <= 0.0 and not dither_bits:
        return out
    rng = np.random.default_rng(seed)
    shape = out.shape[:2]
    w = np.asarray(removed, np.float32)
    shared_std, own_std = _split(grain)
    shared = _unit_noise(rng, shape) * np.float32(shared_std)
    dither = None
    if dither_bits and grain.luma * (2**dither_bits - 1) < 0.5:  # grain of half a code or more dithers already
        q = 1.0 / (2**dither_bits - 1)
        dither = (rng.random(shape, dtype=np.float32) - rng.random(shape, dtype=np.float32)) * np.float32(q)
    planes = out[..., None] if out.ndim == 2 else out
    for c in range(min(3, planes.shape[2])):  # grey (one plane): the luma's grain
        own = own_std[c] if planes.shape[2] >= 3 else 0.0
        own_noise = _unit_noise(rng, shape) * np.float32(own) if own > 0.0 else None  # drawn whole: seeded alike
        for y0, y1 in row_bands(*shape):  # the arithmetic a band at a time: its temporaries stay small
            noise = shared[y0:y1].copy()
            if own_noise is not None:
                noise += own_noise[y0:y1]
            if dither is not None:
                noise += dither[y0:y1]
            noise *= w[y0:y1]
            v = planes[y0:y1, :, c]
            # d(linear)/d(sRGB) at the pixel's value: 2.4 / 1.055 * lin^(1/2.4 * 1.4); 1/12.92 on the linear toe
            lin = np.clip(v, 0.0, 1.0)
            noise *= np.where(lin > 0.0031308, np.float32(2.4 / 1.055) * np.power(lin, np.float32(1.4 / 2.4)),
                              np.float32(1.0 / 12.92))
            noise[v >= 1.0] = 0.0
            v += noise
            np.maximum(v, 0.0, out=v)
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
    return GrainPlan(measure_grain(image), removed_share(coc).astype(np.float16))


def keep_grain(rendered: np.ndarray, photo: np.ndarray, disparity: np.ndarray, blur, *, seed: int = 0,
               dither_bits: int | None = None) -> np.ndarray:
    """The finishing step of ``bokehray render`` in one call (``bokehray.keep_grain``): ``rendered`` (a render of
    ``photo`` with ``disparity`` and ``blur``, a :class:`~bokehray.lens.BlurParams`) with the photo's grain
    restored where the blur removed it, seeded; ``dither_bits=8`` also dithers for an 8-bit file. ``rendered`` is
    written in place when it is a writable float32 array. For display-referred photos: the render itself
    (``bokehray.render``) never adds grain."""
    plan = plan_grain(np.asarray(photo, np.float32), blur.coc_radius(np.asarray(disparity, np.float32)))
    return restore_grain(rendered, plan.grain, plan.removed, seed=seed, dither_bits=dither_bits)
