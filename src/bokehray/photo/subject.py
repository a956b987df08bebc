"""The default blur and focus of a photo: ``--amount`` and the subject.

* **Blur amount** (:func:`k_from_amount`): ``--amount A`` in 0..100 sets ``K = A / 100 * 6 %`` of the image
  diagonal, so the same amount looks the same at 1 MP and at 24 MP. ``A = 50`` (the default) gives a CoC
  radius of 3 % of the diagonal for a point one full disparity unit from the focus.
* **Default focus** (:func:`subject_focus`): the nearest region that holds at least ``SUBJECT_MASS`` (3 %) of the
  centre-weighted frame (a Gaussian of 0.3 x the frame's width and height around its centre), focused at the
  weighted median disparity of that region.

docs/usage.md says it for photographers.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from .depth import subsample

__all__ = ["AMOUNT_DEFAULT", "AMOUNT_K_FRACTION", "SUBJECT_MASS", "Subject", "amount_from_k", "k_from_amount",
           "subject_focus"]

AMOUNT_DEFAULT = 50.0
"""``--amount`` when neither it nor ``--blur`` is given."""

AMOUNT_K_FRACTION = 0.06
"""``K`` at ``--amount 100``, as a fraction of the image diagonal."""

SUBJECT_MASS = 0.03
"""Least share of the centre-weighted frame the default focus's region must hold (thinner things are skipped)."""

CENTRE_SIGMA = 0.3
"""The centre weighting of the default focus: a Gaussian of this many frame widths (heights) across."""
_HIST_BINS = 256
_GAP_MASS = 2e-4  # a histogram bin with less weighted mass than this separates two regions


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
    its disparity range and its share of the centre-weighted frame."""

    d_f: float
    x: int
    y: int
    d_range: tuple[float, float]
    share: float



def subject_focus(disparity: np.ndarray) -> Subject:
    """The default focus: the nearest region holding >= ``SUBJECT_MASS`` of the centre-weighted frame.

    The weighted histogram of the disparity (256 bins; weights a Gaussian of ``CENTRE_SIGMA`` frame sizes around
    the centre) is walked from the nearest bin; the first bin where the mass seen so far reaches ``SUBJECT_MASS``
    lies in the subject. The subject's region is that bin's run of bins bounded by near-empty bins (less than
    0.02 % of the mass: a gap in depth), and the focus is the weighted median disparity of the pixels in it. Thin
    near things (grass, wires in front) hold too little of the frame to be chosen unless nothing else is near.
    """
    d = np.asarray(disparity, np.float32)
    if d.ndim != 2 or d.size == 0:
        raise InputError(f"disparity: expected a non-empty H x W map, got shape {d.shape}")
    s, step = subsample(d)
    h, w = s.shape
    yy = (np.arange(h) + 0.5) / h - 0.5
    xx = (np.arange(w) + 0.5) / w - 0.5
    weight = np.exp(-0.5 * (yy[:, None] ** 2 + xx[None, :] ** 2) / CENTRE_SIGMA**2)
    weight /= weight.sum()
    bins = np.clip((s * _HIST_BINS).astype(np.int64), 0, _HIST_BINS - 1)
    hist = np.bincount(bins.ravel(), weights=weight.ravel(), minlength=_HIST_BINS)
    near_first = np.cumsum(hist[::-1])
    seed = _HIST_BINS - 1 - int(np.searchsorted(near_first, SUBJECT_MASS))
    seed = min(max(seed, 0), _HIST_BINS - 1)
    lo = hi = seed
    while lo > 0 and hist[lo - 1] >= _GAP_MASS:
        lo -= 1
    while hi < _HIST_BINS - 1 and hist[hi + 1] >= _GAP_MASS:
        hi += 1
    inside = (bins >= lo) & (bins <= hi)
    vals, wts = s[inside], weight[inside]
    order = np.argsort(vals, kind="stable")
    cum = np.cumsum(wts[order])
    d_f = float(vals[order][int(np.searchsorted(cum, 0.5 * cum[-1]))])
    iy, ix = np.nonzero(inside)
    cy = float(np.average(iy, weights=wts)) * step
    cx = float(np.average(ix, weights=wts)) * step
    return Subject(d_f, int(round(cx)), int(round(cy)), (float(vals.min()), float(vals.max())), float(cum[-1]))

