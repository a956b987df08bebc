"""Clipped highlights: display-referred photos clip bright lights at code 255, and a clipped light blurred
stays a dim disc; the reconstruction gives such lights back their radiance (docs/usage.md)."""

from __future__ import annotations

import itertools
import math
import os
from pathlib import Path

import numpy as np

__all__ = ["CLIP_LEVEL", "HIGHLIGHT_GAIN", "HIGHLIGHT_RAMP_PX", "LIGHT_MAX_PX", "LIGHT_MAX_SHARE", "dilate8",
           "edge_distance", "is_display_referred", "is_light", "label8", "reconstruct_highlights"]

HIGHLIGHT_GAIN = 5.0
"""Radiance given to the clipped channels deep inside a clipped highlight (in units of the clip level)."""

HIGHLIGHT_RAMP_PX = 1.5
"""Distance from a highlight's edge (pixels) over which the gain ramps from 1 to ``HIGHLIGHT_GAIN``."""

CLIP_LEVEL = 0.99
"""A channel at or above this linear value (8-bit code 254 or more) is clipped."""

LIGHT_MAX_PX = 256
"""A clipped region of at most this many pixels is a light (a lamp, the sun, a specular glint) at any frame size."""

LIGHT_MAX_SHARE = 0.0015
"""A clipped region holding at most this share of the frame is a light too (the dev set's lamps hold 0.04-0.10 %);
a larger one is a light only when its surroundings rise towards it (:func:`is_light`)."""

_GLOW_RINGS = (1, 2, 4, 8, 16)  # the rings around a large clipped region: (1..2], (2..4], (4..8], (8..16] px
_GLOW_REACH = 0.25  # a glow's ring at 4..8 px keeps at least this share of its innermost ring's brightness


def is_display_referred(path: str | os.PathLike[str]) -> bool:
    """PNG, JPEG and integer TIFF files hold display-referred codes clipped at 1; EXR and float TIFF are linear."""
    suffix = Path(path).suffix.lower()
    if suffix in (".png", ".jpg", ".jpeg"):
        return True
    if suffix in (".tif", ".tiff"):
        import tifffile

        from .._quiet import library_log

        try:
            with library_log("tifffile"), tifffile.TiffFile(path) as tf:  # damaged tags: its log, not stderr
                return tf.pages[0].dtype.kind in "iu"
        except Exception:  # noqa: BLE001 - the reader has already reported an unreadable file
            return False
    return False


# The three image operations of the highlight reconstruction, in NumPy: scipy.ndimage would do them, but importing
# its import would lengthen every render's start-up (benchmarks/scale/bench_startup.py); highlights are
# small, so these stay cheap. Each is tested against scipy.ndimage (tests/cli_io/test_photo.py).


def label8(mask: np.ndarray) -> tuple[np.ndarray, list[tuple[int, int, int, int]]]:
    """8-connected components of a boolean image: ``(labels, boxes)``, labels 1..n (0: background) numbered in
    the order of their first pixel (row-major), and each one's box ``(y0, y1, x0, x1)``; as
    ``scipy.ndimage.label`` with a 3 x 3 structure and ``find_objects``.

    Runs of True along each row are joined with the runs of the next row that touch them (columns within one),
    by union-find over runs: the work grows with the number of runs, not of pixels.
    """
    h, w = mask.shape
    rows = np.flatnonzero(mask.any(axis=1))  # only the rows that hold a run are scanned (highlights are small)
    edges = np.diff(np.pad(mask[rows], ((0, 0), (1, 1))).astype(np.int8), axis=1)
    ry, rs = np.nonzero(edges == 1)  # run starts (row-major order)
    re = np.nonzero(edges == -1)[1]  # run ends (exclusive), in the same order
    ry = rows[ry]
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


def _ring_medians(mine: np.ndarray, others: np.ndarray, bright: np.ndarray, scale: int) -> list[float]:
    """The median of ``bright`` in each ring of :data:`_GLOW_RINGS` (times ``scale``) around ``mine``, other
    clipped regions left out; NaN for a ring with no pixel (at the frame's edge)."""
    medians = []
    inner = dilate8(mine, _GLOW_RINGS[0] * scale)
    for r in _GLOW_RINGS[1:]:
        outer = dilate8(mine, r * scale)
        ring = outer & ~inner & ~others
        medians.append(float(np.median(bright[ring])) if ring.any() else math.nan)
        inner = outer
    return medians


def is_light(mine: np.ndarray, crop: np.ndarray, others: np.ndarray, frame_pixels: int) -> bool:
    """Whether the clipped region ``mine`` (a boolean crop of the frame, with ``crop`` its linear RGB and ``others``
    the other clipped regions in it) is a light rather than a white surface.

    Small regions are lights: at most :data:`LIGHT_MAX_PX` pixels, or :data:`LIGHT_MAX_SHARE` of the frame. A larger
    one is a light only when its surroundings rise towards it as a glow does: the median brightness (the brightest
    channel) of the rings 1-2, 2-4, 4-8 and 8-16 px out (scaled with the frame: one step per 1000 px of its side)
    falls strictly from ring to ring, and the 4-8 px ring still holds ``_GLOW_REACH`` of the innermost one. A white
    shirt, a wall, snow or a helmet is a flat clipped plateau whose surroundings fall off at its edge: it keeps its
    value.
    """
    area = int(mine.sum())
    if area <= max(LIGHT_MAX_PX, LIGHT_MAX_SHARE * frame_pixels):
        return True
    scale = max(1, round(math.sqrt(frame_pixels) / 1000))
    m = _ring_medians(mine, others, crop.max(axis=2), scale)
    if any(math.isnan(v) for v in m):
        return False
    falls = all(a > b * 1.05 for a, b in itertools.pairwise(m))
    return falls and m[2] >= _GLOW_REACH * m[0]


def reconstruct_highlights(image: np.ndarray, *, overwrite: bool = False) -> tuple[np.ndarray, int]:
    """Re-inflate the clipped highlights of a display-referred photo; returns ``(image, highlights found)``.

    An 8-bit file stores a lamp of radiance 5 as 1.0, so its bokeh ball comes out dim. Here:

    1. a *highlight* is a connected (8-neighbour) region of pixels with a channel >= ``CLIP_LEVEL`` that holds at
       least one pixel with every colour channel clipped (a white-clipped core: lamps, the sun, speculars;
       a saturated but unclipped colour, or one clipped channel alone, is left as it is) and is a light
       (:func:`is_light`: small, or glowing); a large clipped plateau (a white shirt, a wall) keeps its values;
    2. its colour is that of its unclipped rim (the pixels just outside, minus the median of a ring 3-4 px out:
       the rim's partial coverage shows the light's hue before it clipped), normalised to a brightest channel of 1;
    3. each *clipped* channel becomes ``max(1, g * colour)`` with ``g`` ramping from 1 at the edge to
       ``HIGHLIGHT_GAIN`` at ``HIGHLIGHT_RAMP_PX`` inside; unclipped channels keep their (exact) values.

    Alpha, if present, is not touched. The rule and its measured effect are in docs/usage.md and
    benchmarks/renderer/bench_highlights.py.

    ``overwrite=True`` writes the highlights into ``image`` itself when it is float32 (a caller that no longer
    needs the clipped photo, the command line: no frame-sized copy, 144 MB at 12 MP); by default ``image`` is
    never written to.
    """
    img = np.asarray(image, np.float32)
    rgb = img[..., :3]
    # one pass over the frame, a channel at a time (a reduction over a 3-long last axis is 3x slower); the
    # white-core test then looks at the clipped pixels only
    clipped = rgb[..., 0] >= CLIP_LEVEL
    for c in (1, 2):
        clipped |= rgb[..., c] >= CLIP_LEVEL
    ys, xs = np.nonzero(clipped)
    if not (rgb[ys, xs] >= CLIP_LEVEL).all(axis=1).any():  # no white-clipped core anywhere: nothing to do
        return img, 0
    labels, boxes = label8(clipped)
    # overwriting is safe: a highlight writes only its own clipped channels, which every other highlight's rim,
    # ring and core leave out (``others``, ``mine``), so each reads what it would read from the untouched photo
    out = img if overwrite and img.flags.writeable else img.copy()
    found = 0
    h, w = clipped.shape
    scale = max(1, round(math.sqrt(h * w) / 1000))
    pad = _GLOW_RINGS[-1] * scale + 1  # the rim (1 px), the background ring (3-4 px) and the glow's rings
    for i, (by0, by1, bx0, bx1) in enumerate(boxes, start=1):
        y0, y1 = max(0, by0 - pad), min(h, by1 + pad)
        x0, x1 = max(0, bx0 - pad), min(w, bx1 + pad)
        mine = labels[y0:y1, x0:x1] == i
        crop = rgb[y0:y1, x0:x1]
        ch = (crop >= CLIP_LEVEL) & mine[..., None]
        if not ch.all(axis=2).any():
            continue  # no white core: a saturated colour, not a light
        others = clipped[y0:y1, x0:x1] & ~mine  # another highlight's pixels are neither rim nor background
        if not is_light(mine, crop, others, h * w):
            continue  # a white surface: kept as it is
        found += 1
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
