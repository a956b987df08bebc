"""The default blur and focus of a photo: ``--amount`` and the subject.

* **Blur amount** (:func:`k_from_amount`): ``--amount A`` in 0..100 sets ``K = A / 100 * 6 %`` of the image
  diagonal, so the same amount looks the same at 1 MP and at 24 MP. ``A = 50`` (the default) gives a CoC
  radius of 3 % of the diagonal for a point one full disparity unit from the focus.
* **Default focus** (:func:`default_focus`): the eyes of the nearest sizeable face when the photo shows faces
  (:mod:`bokehray.photo.faces`), else the subject (:func:`subject_focus`): the centre-weighted histogram of the map (a Gaussian of 0.3 x the
  frame's width and height around its centre), over the map's own range, smoothed and split into depth regions
  at its troughs (:func:`depth_regions`); the nearest region that holds at least ``SUBJECT_MASS`` (3 %) of the
  weight is the subject, focused at its weighted median disparity. It needs no empty histogram bin, so soft,
  dithered, float, 8/16-bit and normalised maps of one scene find the same subject.

docs/usage.md says it for photographers.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from .depth import subsample

__all__ = ["AMOUNT_DEFAULT", "AMOUNT_K_FRACTION", "SUBJECT_MASS", "Subject", "amount_from_k", "default_focus",
           "depth_regions", "k_from_amount", "subject_focus"]

AMOUNT_DEFAULT = 50.0
"""``--amount`` when neither it nor ``--blur`` is given."""

AMOUNT_K_FRACTION = 0.06
"""``K`` at ``--amount 100``, as a fraction of the image diagonal."""

SUBJECT_MASS = 0.03
"""Least share of the centre-weighted frame the default focus's region must hold (thinner things are skipped)."""

CENTRE_SIGMA = 0.3
"""The centre weighting of the default focus: a Gaussian of this many frame widths (heights) across."""
_HIST_BINS = 256
_RANGE_PERCENTILES = (0.1, 99.9)  # the histogram spans the map's own range between these percentiles
_SMOOTH_BINS = 2.0  # the histogram is smoothed by a Gaussian of this many bins (0.8 % of the range)
_VALLEY = 0.5  # a trough higher than this share of the lower neighbouring peak does not separate two regions


def k_from_amount(amount: float, height: int, width: int) -> float:
    """``K`` in pixels for a blur ``amount`` in [0, 100]: ``amount / 100 * AMOUNT_K_FRACTION * diagonal``."""
    if isinstance(amount, bool) or not isinstance(amount, (int, float)) or not math.isfinite(amount):
        raise InputError(f"amount: expected a number in [0, 100], got {amount!r}")
    if not 0.0 <= amount <= 100.0:
        raise InputError(f"--amount: expected a number in [0, 100], got {amount:g}")
    return float(amount) / 100.0 * AMOUNT_K_FRACTION * math.hypot(height, width)


def amount_from_k(k_px: float, height: int, width: int) -> float:
    """The inverse of :func:`k_from_amount` (may exceed 100 for a large ``--blur``)."""
    return float(k_px) / (AMOUNT_K_FRACTION * math.hypot(height, width)) * 100.0


@dataclass(frozen=True, slots=True)
class Subject:
    """The default focus: disparity ``d_f``, where the region lies (``x``, ``y``: its weighted centroid in pixels),
    its disparity range, its share of the centre-weighted frame, how many depth regions the map has and what share
    of the frame the nearer regions skipped as too small held."""

    d_f: float
    x: int
    y: int
    d_range: tuple[float, float]
    share: float
    regions: int = 1
    skipped: float = 0.0

    def words(self) -> str:
        """The choice said shortest, for the page."""
        return "the subject"

    def describe(self) -> str:
        """What was chosen and why, in one line (``bokehray render`` prints it)."""
        nearer = (f"; nearer regions holding {self.skipped:.0%} skipped as too small" if self.skipped >= 0.005 else
                  "")
        return (f"on the subject around pixel ({self.x}, {self.y}), d_f = {self.d_f:.3f}: the nearest depth region "
                f"holding {SUBJECT_MASS:.0%} or more of the centre-weighted frame (d {self.d_range[0]:.3f}.."
                f"{self.d_range[1]:.3f}, {self.share:.0%} of it; {self.regions} region{'s' * (self.regions > 1)} "
                f"found{nearer})")


def _smooth(hist: np.ndarray, sigma: float) -> np.ndarray:
    r = int(math.ceil(3 * sigma))
    k = np.exp(-0.5 * (np.arange(-r, r + 1) / sigma) ** 2)
    return np.convolve(np.pad(hist, r, mode="reflect"), k / k.sum(), mode="valid")


def depth_regions(hist: np.ndarray) -> list[tuple[int, int]]:
    """The modes of a histogram, as inclusive bin ranges ``(lo, hi)`` from the first bin to the last.

    The histogram is smoothed (a Gaussian of ``_SMOOTH_BINS`` bins) and cut at its local minima; then, as long as
    some valley between two neighbouring regions is higher than ``_VALLEY`` times the lower of their two peaks, the
    shallowest such valley is removed (the two merge). What remains are the regions a real gap in depth separates,
    whether the gap is empty (a hard-edged map) or only a trough (a soft, dithered or estimated map: brush edges
    and blur fill every bin between two surfaces with a thin ramp, far below either surface's peak). A region that
    holds no weight of ``hist`` joins its neighbour, so every region returned holds some (all of ``hist`` is one
    region when it is all zero).
    """
    s = _smooth(np.asarray(hist, np.float64), _SMOOTH_BINS)
    n = s.size
    cuts = [i for i in range(1, n - 1) if s[i] < s[i - 1] and s[i] <= s[i + 1]]
    edges = [0, *cuts, n]  # region j is bins edges[j] .. edges[j+1] - 1; the valley between j and j+1 is edges[j+1]
    peaks = [float(s[a:b].max()) for a, b in itertools.pairwise(edges)]
    while len(peaks) > 1:
        ratios = [s[edges[j + 1]] / max(min(peaks[j], peaks[j + 1]), 1e-300) for j in range(len(peaks) - 1)]
        j = int(np.argmax(ratios))
        if ratios[j] <= _VALLEY:
            break
        peaks[j : j + 2] = [max(peaks[j], peaks[j + 1])]
        del edges[j + 1]
    # A stretch of empty bins the cuts set apart (a flat map's 249 bins beyond its one value: the smoothed
    # histogram falls to 0 and the first 0 is a cut) holds no weight: it joins the region before it (the first
    # region, the one after it) instead of counting as a region of its own.
    raw = np.asarray(hist, np.float64)
    starts = [a for a, b in itertools.pairwise(edges) if raw[a:b].sum() > 0.0][1:]
    return [(a, b - 1) for a, b in itertools.pairwise([0, *starts, n])]


def subject_focus(disparity: np.ndarray) -> Subject:
    """The default focus: the nearest depth region holding >= ``SUBJECT_MASS`` of the centre-weighted frame.

    On a grid of at most 512 samples a side (one pixel of each block, at offsets that vary: :func:`subsample`), the
    centre-weighted histogram (256 bins over the map's own 0.1st..99.9th
    percentile range, so the encoding's range and bit depth do not matter; weights a Gaussian of ``CENTRE_SIGMA``
    frame sizes around the centre) is split into depth regions at its troughs (:func:`depth_regions`). Walking from
    the nearest region, the first that holds at least ``SUBJECT_MASS`` of the weight is the subject; the focus is the
    weighted median disparity of its pixels. Thin near things (grass, wires in front) hold too little of the frame to
    be chosen unless nothing else is near; no step depends on a histogram bin being empty, so a soft map (brush
    edges, a model's output, dithered or float) finds the same subject as a hard-edged one.
    """
    d = np.asarray(disparity, np.float32)
    if d.ndim != 2 or d.size == 0:
        raise InputError(f"disparity: expected a non-empty H x W map, got shape {d.shape}")
    s, rows, cols = subsample(d)
    h, w = s.shape
    yy = (np.arange(h) + 0.5) / h - 0.5
    xx = (np.arange(w) + 0.5) / w - 0.5
    weight = np.exp(-0.5 * (yy[:, None] ** 2 + xx[None, :] ** 2) / CENTRE_SIGMA**2)
    weight /= weight.sum()
    lo, hi = (float(v) for v in np.percentile(s, _RANGE_PERCENTILES))
    if not hi - lo > 1e-6:  # (nearly) flat between the percentiles: the whole range, outliers included
        lo, hi = float(s.min()), float(s.max())
    if hi - lo > 1e-6:
        scaled = (s.astype(np.float64) - lo) * (_HIST_BINS / (hi - lo))
        bins = np.clip(scaled, 0, _HIST_BINS - 1).astype(np.int64)
    else:  # flat: one region
        bins = np.zeros(s.shape, np.int64)
    hist = np.bincount(bins.ravel(), weights=weight.ravel(), minlength=_HIST_BINS)
    regions = depth_regions(hist)
    skipped = 0.0
    for r_lo, r_hi in reversed(regions):  # nearest first
        mass = float(hist[r_lo : r_hi + 1].sum())
        if mass >= SUBJECT_MASS:
            break
        skipped += mass
    else:  # nothing holds enough (cannot happen with SUBJECT_MASS <= 1 / regions): the largest region
        r_lo, r_hi = max(regions, key=lambda r: hist[r[0] : r[1] + 1].sum())
        skipped = float(hist[r_hi + 1 :].sum())
    inside = (bins >= r_lo) & (bins <= r_hi)
    vals, wts = s[inside], weight[inside]
    order = np.argsort(vals, kind="stable")
    cum = np.cumsum(wts[order])
    d_f = float(vals[order][int(np.searchsorted(cum, 0.5 * cum[-1]))])
    iy, ix = np.nonzero(inside)
    cy = float(np.average(rows[iy], weights=wts))
    cx = float(np.average(cols[ix], weights=wts))
    return Subject(d_f, int(round(cx)), int(round(cy)), (float(vals.min()), float(vals.max())), float(cum[-1]),
                   len(regions), skipped)


def default_focus(image: np.ndarray | None, disparity: np.ndarray):
    """The default focus of a photo: the eyes of its nearest sizeable face (an :class:`~bokehray.photo.faces.EyesFocus`)
    when it shows faces, else :func:`subject_focus` (a :class:`Subject`). Both carry ``d_f``, ``x``, ``y``,
    ``describe()`` and ``words()``. ``image=None`` (no photo at hand) is the subject search alone."""
    if image is not None:
        from .faces import eyes_focus

        eyes = eyes_focus(image, np.asarray(disparity, np.float32))
        if eyes is not None:
            return eyes
    return subject_focus(disparity)
