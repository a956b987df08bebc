"""Photos and depth maps as people have them: depth conventions, the default blur and focus.

Everything here is documented in docs/usage.md (for photographers) and docs/conventions.md:

* **Blur amount** (:func:`k_from_amount`): ``--amount A`` in 0..100 sets ``K = A / 100 * 6 %`` of the image
  diagonal, so the same amount looks the same at 1 MP and at 24 MP. ``A = 50`` (the default) gives a CoC
  radius of 3 % of the diagonal for a point one full disparity unit from the focus.
* **Default focus** (:func:`subject_focus`): the nearest region that holds at least ``SUBJECT_MASS`` (3 %) of the
  centre-weighted frame (a Gaussian of 0.3 x the frame's width and height around its centre), focused at the
  weighted median disparity of that region.
* **Relative maps** (:func:`normalize_relative`): min-max between the 0.5th and 99.5th percentiles, clipped to
  [0, 1]; ``invert`` flips a near-is-dark map.
* **Reversed maps** (:func:`looks_reversed`): a map whose frame border (5 % bands) is nearer than its centre
  (the middle ninth) by more than ``REVERSED_MARGIN`` is probably near-is-dark.
* **Missing depth** (:func:`depth_to_disparity`): metric depth <= 0 (no measurement: depth cameras write 0),
  and +/-inf are infinitely far (disparity 0, sky); NaN is refused, naming the file.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .embedded import (  # noqa: F401 - re-exported: the file-level conventions live in .embedded (io uses them)
    SRGB_CHROMATICITIES,
    Embedded,
    apply_orientation,
    embedded,
    exif_for_output,
    orientation_words,
    srgb_icc,
    to_srgb_codes,
)
from .errors import InputError

__all__ = [
    "AMOUNT_DEFAULT", "AMOUNT_K_FRACTION", "REVERSED_MARGIN", "SUBJECT_MASS", "Subject", "amount_from_k",
    "depth_to_disparity", "k_from_amount", "looks_reversed", "normalize_relative", "read_depth_map",
    "subject_focus", "SRGB_CHROMATICITIES", "Embedded", "apply_orientation", "embedded", "exif_for_output",
    "orientation_words", "srgb_icc", "to_srgb_codes", "is_display_referred", "reconstruct_highlights",
]  # fmt: skip

AMOUNT_DEFAULT = 50.0
"""``--amount`` when neither it nor ``--blur`` is given."""

AMOUNT_K_FRACTION = 0.06
"""``K`` at ``--amount 100``, as a fraction of the image diagonal."""

SUBJECT_MASS = 0.03
"""Least share of the centre-weighted frame the default focus's region must hold (thinner things are skipped)."""

CENTRE_SIGMA = 0.3
"""The centre weighting of the default focus: a Gaussian of this many frame widths (heights) across."""

NORMALIZE_PERCENTILES = (0.5, 99.5)
"""The robust min and max of ``--normalize``, in percent."""

REVERSED_MARGIN = 0.2
"""How much nearer (in normalised disparity) the frame border must be than the centre to call a map reversed."""

BORDER_NEAR = 0.85
"""A frame border whose median disparity is at least this sits on the nearest values."""

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


def _sample(d: np.ndarray, most: int = 512) -> tuple[np.ndarray, int]:
    step = max(1, int(math.ceil(max(d.shape) / most)))
    return d[::step, ::step], step


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
    s, step = _sample(d)
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
    s, _ = _sample(d)
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


def normalize_relative(values: np.ndarray, *, invert: bool = False, source: str = "disparity") -> np.ndarray:
    """A relative map of any range (e.g. a monocular model's inverse depth) to disparity in [0, 1].

    Min-max between the 0.5th and 99.5th percentiles of the finite values, clipped to [0, 1], so a few outliers
    do not squash the rest; ``invert`` flips it for near-is-dark maps. Non-finite values are refused.
    """
    v = np.asarray(values, np.float64)
    if not np.isfinite(v).all():
        raise InputError(f"{source}: --normalize needs finite values; NaN or Inf found")
    lo, hi = np.percentile(v, NORMALIZE_PERCENTILES)
    if not hi > lo:
        lo, hi = float(v.min()), float(v.max())
    if not hi > lo:
        raise InputError(f"{source}: the map is constant ({lo:g}): nothing to normalise, every pixel is at one depth")
    d = np.clip((v - lo) / (hi - lo), 0.0, 1.0)
    return (1.0 - d if invert else d).astype(np.float32)


def depth_to_disparity(depth_m: np.ndarray, norm=None, *, source: str = "depth"):  # noqa: ANN001 - lens types
    """Metric depth to disparity with the stated rule for missing depth; returns ``(d, norm, missing share)``.

    Depth <= 0 (no measurement) and +/-inf are infinitely far: disparity 0. NaN is refused, naming ``source``.
    """
    from .lens import DepthNormalization, disparity_from_depth

    z = np.asarray(depth_m, np.float64)
    if np.isnan(z).any():
        y, x = (int(i) for i in np.unravel_index(int(np.argmax(np.isnan(z))), z.shape))
        raise InputError(f"{source}: expected depth in metres, got NaN at (y, x) = ({y}, {x})")
    missing = ~np.isfinite(z) | (z <= 0)
    if missing.all():
        raise InputError(f"{source}: no pixel has a depth (every value is 0, negative or infinite)")
    z = np.where(missing, np.inf, z)
    if norm is not None and not isinstance(norm, DepthNormalization):
        raise InputError("depth normalisation: expected a bokehray.DepthNormalization")
    try:
        d, norm = disparity_from_depth(z, norm)
    except InputError as e:
        raise InputError(f"{source}: {e}") from None
    return d, norm, float(missing.mean())


def read_depth_map(path: str | os.PathLike[str], *, scale: float | None = None) -> np.ndarray:
    """A metric depth map in metres (float64 ``H x W``; missing depth kept as written, see
    :func:`depth_to_disparity`).

    Float EXR/TIFF/NPY hold metres (times ``scale`` if given). Integer maps (16-bit PNG or TIFF from depth cameras
    and phones, integer NPY) hold codes and need ``scale``: metres per code, e.g. 0.001 for millimetres.
    """
    from . import io

    p = Path(path)
    if scale is not None and not (math.isfinite(scale) and scale > 0):
        raise InputError(f"--depth-scale: expected metres per code > 0 (0.001 for millimetres), got {scale:g}")
    p, fmt = io._format(p, ("PNG", "TIFF", "EXR", "NPY"), "depth")
    a = io._single_channel(p, io._load(p, fmt, (("Z",), ("Y",), ("R",))), fmt, "depth")
    if a.dtype.kind in "iu":
        if scale is None:
            raise InputError(f"{p}: holds integer codes ({a.dtype}), not metres: give --depth-scale, metres per "
                             "code (0.001 for a millimetre map)")
        return a.astype(np.float64) * scale
    if a.dtype.kind != "f":
        raise InputError(f"{p}: expected float depth in metres or integer codes, got {a.dtype}")
    out = a.astype(np.float64)
    return out * scale if scale is not None else out


# --------------------------------------------------------------------------- clipped highlights

HIGHLIGHT_GAIN = 5.0
"""Radiance given to the clipped channels deep inside a clipped highlight (in units of the clip level)."""

HIGHLIGHT_RAMP_PX = 1.5
"""Distance from a highlight's edge (pixels) over which the gain ramps from 1 to ``HIGHLIGHT_GAIN``."""

CLIP_LEVEL = 0.99
"""A channel at or above this linear value (8-bit code 254 or more) is clipped."""


def is_display_referred(path: str | os.PathLike[str]) -> bool:
    """PNG, JPEG and integer TIFF files hold display-referred codes clipped at 1; EXR and float TIFF are linear."""
    suffix = Path(path).suffix.lower()
    if suffix in (".png", ".jpg", ".jpeg"):
        return True
    if suffix in (".tif", ".tiff"):
        import tifffile

        try:
            with tifffile.TiffFile(path) as tf:
                return tf.pages[0].dtype.kind in "iu"
        except Exception:  # noqa: BLE001 - the reader has already reported an unreadable file
            return False
    return False


# The three image operations of the highlight reconstruction, in NumPy: scipy.ndimage would do them, but importing
# it costs about 0.2 s of every render's start-up (docs/usage.md, benchmarks/bench_startup.py); highlights are
# small, so these stay cheap. Each is tested against scipy.ndimage (tests/cli_io/test_photo.py).


def label8(mask: np.ndarray) -> tuple[np.ndarray, list[tuple[int, int, int, int]]]:
    """8-connected components of a boolean image: ``(labels, boxes)``, labels 1..n (0: background) numbered in
    the order of their first pixel (row-major), and each one's box ``(y0, y1, x0, x1)``; as
    ``scipy.ndimage.label`` with a 3 x 3 structure and ``find_objects``.

    Runs of True along each row are joined with the runs of the next row that touch them (columns within one),
    by union-find over runs: the work grows with the number of runs, not of pixels.
    """
    h, w = mask.shape
    edges = np.diff(np.pad(mask, ((0, 0), (1, 1))).astype(np.int8), axis=1)
    ry, rs = np.nonzero(edges == 1)  # run starts (row-major order)
    re = np.nonzero(edges == -1)[1]  # run ends (exclusive), in the same order
    n = len(ry)
    parent = list(range(n))

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    first = np.searchsorted(ry, np.arange(h + 1))
    rs_l, re_l = rs.tolist(), re.tolist()
    for y in range(h - 1):
        i, i1, j, j1 = first[y], first[y + 1], first[y + 1], first[y + 2]
        while i < i1 and j < j1:
            if rs_l[i] <= re_l[j] and rs_l[j] <= re_l[i]:  # within one column of each other: 8-connected
                a, b = root(i), root(j)
                if a != b:
                    parent[max(a, b)] = min(a, b)  # the earlier run stays the root
            if re_l[i] < re_l[j]:
                i += 1
            else:
                j += 1
    roots = np.array([root(i) for i in range(n)], np.int64)
    uniq, run_label = np.unique(roots, return_inverse=True)  # roots are each component's first run
    run_label = run_label + 1
    labels = np.zeros((h, w), np.int32)
    lengths = re - rs
    flat = np.repeat(ry * w + rs - np.cumsum(np.r_[0, lengths[:-1]]), lengths) + np.arange(lengths.sum())
    labels.ravel()[flat] = np.repeat(run_label, lengths)
    k = len(uniq)
    y0 = np.full(k, h)
    y1 = np.zeros(k, np.int64)
    x0 = np.full(k, w)
    x1 = np.zeros(k, np.int64)
    np.minimum.at(y0, run_label - 1, ry)
    np.maximum.at(y1, run_label - 1, ry + 1)
    np.minimum.at(x0, run_label - 1, rs)
    np.maximum.at(x1, run_label - 1, re)
    return labels, list(zip(y0.tolist(), y1.tolist(), x0.tolist(), x1.tolist()))


def dilate8(mask: np.ndarray, steps: int) -> np.ndarray:
    """``steps`` 8-neighbour dilations (a (2 steps + 1)^2 square), nothing beyond the array: as
    ``scipy.ndimage.binary_dilation(mask, np.ones((3, 3)), steps)``."""
    out = mask.copy()
    for axis in (0, 1):
        src = out.copy()
        n = src.shape[axis]
        for k in range(1, min(steps, n - 1) + 1):
            lo = [slice(None)] * 2
            hi = [slice(None)] * 2
            lo[axis], hi[axis] = slice(0, n - k), slice(k, n)
            out[tuple(lo)] |= src[tuple(hi)]
            out[tuple(hi)] |= src[tuple(lo)]
    return out


def edge_distance(mask: np.ndarray, cap: float) -> np.ndarray:
    """Euclidean distance of each True pixel to the nearest False one (outside the array counts as False), where
    below ``cap``; ``cap`` elsewhere: ``min(scipy.ndimage.distance_transform_edt(np.pad(mask, 1))[1:-1, 1:-1],
    cap)``. Only the offsets nearer than ``cap`` are looked at."""
    h, w = mask.shape
    reach = max(1, int(math.ceil(cap)))
    padded = np.pad(mask, reach)
    dist = np.where(mask, cap, 0.0)
    for dy in range(-reach, reach + 1):
        for dx in range(-reach, reach + 1):
            d = math.hypot(dy, dx)
            if 0 < d < cap:
                outside = ~padded[reach + dy : reach + dy + h, reach + dx : reach + dx + w]
                np.minimum(dist, np.where(mask & outside, d, cap), out=dist)
    return dist


def reconstruct_highlights(image: np.ndarray) -> tuple[np.ndarray, int]:
    """Re-inflate the clipped highlights of a display-referred photo; returns ``(image, highlights found)``.

    An 8-bit file stores a lamp of radiance 5 as 1.0, so its bokeh ball comes out dim. Here:

    1. a *highlight* is a connected (8-neighbour) region of pixels with a channel >= ``CLIP_LEVEL`` that holds at
       least one pixel with every colour channel clipped (a white-clipped core: lamps, the sun, speculars;
       a saturated but unclipped colour, or one clipped channel alone, is left as it is);
    2. its colour is that of its unclipped rim (the pixels just outside, minus the median of a ring 3-4 px out:
       the rim's partial coverage shows the light's hue before it clipped), normalised to a brightest channel of 1;
    3. each *clipped* channel becomes ``max(1, g * colour)`` with ``g`` ramping from 1 at the edge to
       ``HIGHLIGHT_GAIN`` at ``HIGHLIGHT_RAMP_PX`` inside; unclipped channels keep their (exact) values.

    Alpha, if present, is not touched. The rule and its measured effect are in docs/usage.md and
    benchmarks/bench_highlights.py.
    """
    img = np.asarray(image, np.float32)
    rgb = img[..., :3]
    clipped_ch = rgb >= CLIP_LEVEL
    if not clipped_ch.all(axis=2).any():  # no white-clipped core anywhere: nothing to do
        return img, 0
    clipped = clipped_ch.any(axis=2)
    labels, boxes = label8(clipped)
    out = img.copy()
    found = 0
    h, w = clipped.shape
    pad = 5  # the rim (1 px) and the background ring (3-4 px) around each highlight
    for i, (by0, by1, bx0, bx1) in enumerate(boxes, start=1):
        y0, y1 = max(0, by0 - pad), min(h, by1 + pad)
        x0, x1 = max(0, bx0 - pad), min(w, bx1 + pad)
        mine = labels[y0:y1, x0:x1] == i
        ch = clipped_ch[y0:y1, x0:x1] & mine[..., None]
        if not ch.all(axis=2).any():
            continue  # no white core: a saturated colour, not a light
        found += 1
        crop = rgb[y0:y1, x0:x1]
        others = clipped[y0:y1, x0:x1] & ~mine  # another highlight's pixels are neither rim nor background
        rim = dilate8(mine, 1) & ~mine & ~others
        ring = dilate8(mine, 4) & ~dilate8(mine, 2) & ~others
        colour = np.ones(3)
        if rim.any() and ring.any():
            diff = np.clip(crop[rim].mean(axis=0) - np.median(crop[ring], axis=0), 0.0, None)
            if diff.max() > 0.02:  # a usable rim; else white
                colour = diff / diff.max()
        dist = edge_distance(mine, HIGHLIGHT_RAMP_PX)
        gain = 1.0 + (HIGHLIGHT_GAIN - 1.0) * np.clip(dist / HIGHLIGHT_RAMP_PX, 0.0, 1.0)
        target = np.maximum(gain[..., None] * colour, 1.0).astype(np.float32)
        view = out[y0:y1, x0:x1, :3]
        view[ch] = target[ch]
    return out, found
