"""The edge estimate the matting and the depth fix share: where a depth edge's mixed pixels are and what their
alpha is, by the photo's colour (a local linear colour model per band pixel).

Two consumers, one estimate:

* ``bokehray.matting.split_mixed_pixels`` splits the band pixels whose alpha is mixed into a near and a far part.
* ``bokehray_refiner.depthfix.correct_disparity`` takes its depth edges from here and looks for smeared ramps only
  where this module measures ramps (:func:`ramp_width` > 0, the measure that widens the matting's band).

Steps (docs/soft-scene.md): the depth edges (4-neighbour pairs whose signed CoC differs by more than
``jump_px``); a map whose edges are noise is left alone (:func:`isolated_share`); the unknown band (the
depth-edge pixels, widened with the map's measured ramp width: :func:`edge_band`); per band pixel the kernel
``bokehray_kernels.matting.matting_band_kernel`` (alpha, F, B and the parts' CoC: :meth:`EdgeBand.estimate`).

This module sits beside the depth fix and below the matting in the package's layers (the depth fix cannot import
the matting), so both import it.
"""

from __future__ import annotations

import functools
import itertools
import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import bokehray_kernels.matting as bk_matting
import numpy as np

from ._memory import row_bands

__all__ = [
    "PIXELS_PER_THREAD",
    "EdgeBand",
    "EdgeEstimate",
    "MattingRule",
    "Steps",
    "band_window",
    "depth_edges",
    "dilate",
    "edge_band",
    "edges_of_steps",
    "in_parts",
    "in_row_parts",
    "isolated_share",
    "launch_band_kernel",
    "map_steps",
    "on_threads",
    "ramp_of_steps",
    "ramp_width",
    "row_parts",
    "window_offsets",
]

PIXELS_PER_THREAD = 4096
"""Fewest pixels a CPU thread of a per-pixel kernel gets (fewer are not worth a thread)."""


CHECK_ITEMS = 1 << 17
"""With a ``check``, :func:`in_parts` runs at most this many items a thread between two checks (a fraction of a
second of the matting's kernel on one core)."""


def in_parts(n: int, run, *, threads: int | None = None, cpu: bool = True, check=None, item_px: int = 1) -> list:
    """``run(a, b)`` over ``[0, n)`` cut into parts, their results in order: on the CPU as many parts at a time as
    ``threads`` (default: the cores) with at least ``PIXELS_PER_THREAD`` pixels each (an item is ``item_px`` pixels:
    a tile's), run in a thread pool (Warp CPU launches release the GIL); one part at a time elsewhere. Always at
    least one part (``run(0, 0)`` for nothing). ``check()``: called before each round of parts (at most
    ``CHECK_ITEMS`` items a part), so that a render can be stopped there (it raises); None: one round."""
    workers = 1 if not cpu else max(1, min(int(threads or os.cpu_count() or 1),
                                           -(-n * max(1, int(item_px)) // PIXELS_PER_THREAD)))
    parts = workers if check is None else max(workers, -(-n // CHECK_ITEMS))
    parts = -(-parts // workers) * workers  # whole rounds
    cuts = np.linspace(0, n, parts + 1).astype(np.int64)
    spans = [(int(cuts[j]), int(cuts[j + 1])) for j in range(parts)]
    if workers == 1:
        out = []
        for span in spans:
            if check is not None:
                check()
            out.append(run(*span))
        return out
    out = []
    with ThreadPoolExecutor(max_workers=workers) as pool:
        for r in range(0, parts, workers):
            if check is not None:
                check()
            out.extend(pool.map(lambda span: run(*span), spans[r : r + workers]))
    return out


def row_parts(h: int, w: int, *, align: int = 1, threads: int | None = None) -> list[tuple[int, int]]:
    """The rows ``[0, h)`` of an ``h x w`` frame cut into consecutive parts ``(y0, y1)``, as many as :func:`in_parts`
    runs at once on the CPU (``threads``, default the cores; each part at least ``PIXELS_PER_THREAD`` pixels), every
    cut a multiple of ``align`` rows (a tile grid's). At least one part (``(0, 0)`` for no rows)."""
    workers = max(1, min(int(threads or os.cpu_count() or 1), -(-h * w // PIXELS_PER_THREAD)))
    step = max(1, int(align))
    cuts = sorted({0, h} | {min(h, -(-(h * j // workers) // step) * step) for j in range(1, workers)})
    return list(itertools.pairwise(cuts)) if h > 0 else [(0, 0)]


def on_threads(tasks: list[Callable[[], object]], pool: ThreadPoolExecutor | None = None) -> list:
    """Call each of ``tasks``, the first on this thread and each other on a thread of ``pool`` (None: a thread of its
    own; NumPy's loops and Warp CPU launches release the GIL: the cores share the work), and return their results in
    order once all are done (the others are waited for even when the first raises)."""
    if len(tasks) <= 1:
        return [task() for task in tasks]
    if pool is None:
        with ThreadPoolExecutor(max_workers=len(tasks) - 1) as own:
            return on_threads(tasks, own)
    others = [pool.submit(task) for task in tasks[1:]]
    try:
        first = tasks[0]()
    finally:
        done = [f.result() for f in others]
    return [first] + done


def in_row_parts(h: int, w: int, run: Callable[[int, int], object], *, align: int = 1,
                 threads: int | None = None) -> list:
    """``run(y0, y1)`` over the :func:`row_parts` of an ``h x w`` frame, one part a core (:func:`on_threads`), the
    results in order: for whole-frame NumPy passes whose rows are independent (the values are those of one pass)."""
    return on_threads([functools.partial(run, a, b) for a, b in row_parts(h, w, align=align, threads=threads)])


Steps = tuple[np.ndarray, np.ndarray]
"""A map's steps (:func:`map_steps`): which 4-neighbour differences exceed the jump, down and across."""

def map_steps(coc: np.ndarray, jump_px: float) -> Steps:
    """The map's steps between 4-neighbours: ``(|np.diff(coc, axis=0)| > jump_px, |np.diff(coc, axis=1)| >
    jump_px)``, (H - 1) x W and H x (W - 1) booleans. :func:`depth_edges` and :func:`ramp_width` both start from
    them; the edge estimate computes them once for both (:func:`edges_of_steps`, :func:`ramp_of_steps`). The
    differences are taken a band of rows at a time (``np.diff``'s subtraction, no frame-sized difference or
    absolute value), the frame's rows in parts on the CPU's cores (:func:`in_row_parts`)."""
    h, w = coc.shape
    jy = np.empty((max(h - 1, 0), w), bool)
    jx = np.empty((h, max(w - 1, 0)), bool)

    def part(r0: int, r1: int) -> None:
        for y, y1 in row_bands(r1 - r0, w):
            y, y1 = y + r0, y1 + r0
            for d, out in ((np.subtract(coc[y:y1, 1:], coc[y:y1, :-1]), jx[y:y1]),
                           (np.subtract(coc[y + 1 : y1 + 1], coc[y : min(y1, h - 1)]), jy[y:y1])):
                np.abs(d, out=d)
                np.greater(d, jump_px, out=out)

    in_row_parts(h, w, part)
    return jy, jx


def ramp_width(signed_coc: np.ndarray, jump_px: float, cap: int) -> int:
    """How many pixels a depth edge's CoC ramp spans (0 for a hard edge): the 90th percentile, over the map's
    depth-edge pairs, of the length of the run of consecutive same-sign steps above ``jump_px`` a pair belongs
    to (along its axis), minus one; at most ``cap``."""
    return ramp_of_steps(signed_coc, map_steps(signed_coc, jump_px), cap)


def ramp_of_steps(coc: np.ndarray, steps: Steps, cap: int) -> int:
    """:func:`ramp_width` of the map ``coc`` whose :func:`map_steps` are ``steps`` (the sign of each step is
    taken from the map, at the steps only)."""
    lengths = []
    for ax, jump in enumerate(steps):
        if jump.size == 0:
            continue
        pos = np.flatnonzero(jump)  # row-major positions of the steps (the edge pairs only)
        if pos.size == 0:
            continue
        rows, cols = np.divmod(pos, jump.shape[1])
        sign = np.sign(coc[rows + 1, cols] - coc[rows, cols] if ax == 0 else
                       coc[rows, cols + 1] - coc[rows, cols]).astype(np.int8)  # np.diff's value at the step
        if ax == 0:  # runs go down the columns: order the steps column by column
            order = np.lexsort((rows, cols))
            line, along, sign = cols[order], rows[order], sign[order]
        else:
            line, along = rows, cols
        # a run continues where the next step is the next pixel of the same line with the same sign
        cont = (line[1:] == line[:-1]) & (along[1:] == along[:-1] + 1) & (sign[1:] == sign[:-1])
        starts = np.flatnonzero(np.concatenate([[True], ~cont]))
        run = np.diff(np.concatenate([starts, [pos.size]]))
        lengths.append(np.repeat(run, run))
    if not lengths:
        return 0
    return int(min(cap, max(0, int(np.percentile(np.concatenate(lengths), 90)) - 1)))


def isolated_share(signed_coc: np.ndarray, jump_px: float) -> float:
    """The share of pixels whose CoC differs by more than ``jump_px`` from each of their neighbours in the image
    (eight, fewer at the border); 0 for a single pixel."""
    h, w = signed_coc.shape
    if h * w < 2:
        return 0.0
    p = np.pad(signed_coc.astype(np.float64), 1, mode="constant", constant_values=np.nan)
    iso = np.ones((h, w), bool)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            if dy or dx:
                nb = p[1 + dy:1 + dy + h, 1 + dx:1 + dx + w]
                iso &= ~(np.abs(nb - signed_coc) <= jump_px)  # NaN (outside) counts as different
    return float(iso.mean())


def window_offsets(radius: int) -> tuple[np.ndarray, np.ndarray]:
    """(dy, dx) offsets of the search window and their distances, nearest first: every pixel within 4 px, and a
    grid of pitch 2 from there to ``radius`` (the far rings of a wide window hold the same colours at a quarter
    of the cost)."""
    r = int(radius)
    g = np.arange(-r, r + 1)
    oy, ox = np.meshgrid(g, g, indexing="ij")
    dist = np.hypot(oy, ox)
    keep = (dist <= r + 0.5) & ((dist <= 4.0) | ((oy % 2 == 0) & (ox % 2 == 0)))
    order = np.argsort(dist[keep], kind="stable")
    offs = np.stack([oy[keep], ox[keep]], 1)[order]
    return offs.astype(np.int64), dist[keep][order].astype(np.float32)


def dilate(mask: np.ndarray, k: int) -> np.ndarray:
    """Binary dilation of a 2-D mask (a tile grid, a small image) by a (2k+1)^2 square, via 2-D prefix sums."""
    if k <= 0 or not mask.any():
        return mask.copy()
    h, w = mask.shape
    c = np.zeros((h + 1, w + 1), np.int32)
    c[1:, 1:] = np.cumsum(np.cumsum(mask.astype(np.int32), 0), 1)
    y0 = np.clip(np.arange(h) - k, 0, h)
    y1 = np.clip(np.arange(h) + k + 1, 0, h)
    x0 = np.clip(np.arange(w) - k, 0, w)
    x1 = np.clip(np.arange(w) + k + 1, 0, w)
    s = c[y1][:, x1] - c[y0][:, x1] - c[y1][:, x0] + c[y0][:, x0]
    return s > 0


def depth_edges(coc: np.ndarray, jump_px: float) -> np.ndarray:
    """Boolean map: both pixels of every 4-neighbour pair whose CoC differs by more than ``jump_px``."""
    return edges_of_steps(map_steps(coc, jump_px))


def edges_of_steps(steps: Steps) -> np.ndarray:
    """:func:`depth_edges` of the map whose :func:`map_steps` are ``steps``."""
    jy, jx = steps
    h, w = jx.shape[0], jy.shape[1]
    e = np.zeros((h, w), bool)  # (H, W): jx is H x (W - 1), jy (H - 1) x W

    def part(a: int, b: int) -> None:  # the rows [a, b) of the map, the steps either side of them
        e[a : min(b, h - 1)] |= jy[a : min(b, h - 1)]
        e[max(a, 1) : b] |= jy[max(a, 1) - 1 : b - 1]
        e[a:b, :-1] |= jx[a:b]
        e[a:b, 1:] |= jx[a:b]

    in_row_parts(h, w, part)
    return e


def _largest_magnitude(image: np.ndarray) -> float:
    """``max(image.max(), -image.min())`` of a non-empty image, its rows' parts on the CPU's cores."""
    h, w = image.shape[:2]

    def part(a: int, b: int) -> tuple[float, float] | None:
        return (float(image[a:b].max()), float(image[a:b].min())) if b > a else None

    found = [v for v in in_row_parts(h, w, part) if v is not None]
    return max(max(v[0] for v in found), -min(v[1] for v in found))


@dataclass(frozen=True, slots=True)
class MattingRule:
    """The constants of the edge estimate and the split (``bokehray.matting.split_mixed_pixels`` says what each
    does); the defaults are the measured ones (docs/soft-scene.md)."""

    jump_px: float = 1.0
    band_px: int = 0
    max_ramp_px: int = 6
    unknown_weight: float = 0.3
    ridge: float = 0.03
    purity: float = 12.0
    min_contrast: float = 0.02
    min_alpha: float = 0.02
    max_alpha: float = 0.9
    model_sd: float | None = 0.1
    max_isolated_share: float = 0.25
    light_level: float = 1.0
    light_ratio: float = 1.2
    light_reach: int = 16
    light_thin: float = 0.35
    light_share: float = 0.25

    def band_params(self, scale: float = 1.0) -> bk_matting.BandParams:
        """The kernel's constants for an image divided by ``scale`` (``light_level`` is in the photo's units)."""
        p = bk_matting.BandParams()
        p.jump_px, p.unknown_weight, p.ridge, p.purity = (float(self.jump_px), float(self.unknown_weight),
                                                          float(self.ridge), float(self.purity))
        whole = float(self.purity).is_integer() and 0 <= self.purity <= 64
        p.purity_n = int(self.purity) if whole else -1
        p.light_level = float(self.light_level) / float(scale)
        p.light_ratio, p.light_reach = float(self.light_ratio), int(self.light_reach)
        p.light_thin, p.light_share = float(self.light_thin), float(self.light_share)
        return p


def band_window(radius: int, device) -> bk_matting.BandWindow:
    """The window of radius ``radius`` as the kernel takes it (:func:`window_offsets`, Gaussian weights of sigma
    ``radius / 2``)."""
    import warp as wp

    offs, dist = window_offsets(radius)
    sigma = 0.5 * radius
    window = bk_matting.BandWindow()
    window.offset_y = wp.array(offs[:, 0].astype(np.int32), dtype=wp.int32, device=device)
    window.offset_x = wp.array(offs[:, 1].astype(np.int32), dtype=wp.int32, device=device)
    window.offset_g = wp.array(np.exp(-(dist.astype(np.float64) ** 2) / (2.0 * sigma * sigma)).astype(np.float32),
                               dtype=float, device=device)
    return window


def launch_band_kernel(img, s, band, by, bx, radius: int, rule: MattingRule, device, threads, check=None,
                       scale: float = 1.0):
    """Launch ``bokehray_kernels.matting.matting_band_kernel`` over the band pixels ``(by, bx)`` of the box ``img``
    (scaled), ``s`` (its CoC) and ``band`` (its band mask), in rounds of parts on CPU threads (:func:`in_parts`: Warp
    CPU launches release the GIL). Returns NumPy arrays: alpha, F, B, their variances, the near and far CoC and the
    flags."""
    import warp as wp

    dev = wp.get_device(device)
    copy = not dev.is_cpu  # on the CPU the kernel reads the (contiguous) arrays in place: no copy of the box
    image = wp.array(np.ascontiguousarray(img, np.float32), dtype=wp.vec3, device=dev, copy=copy)
    coc = wp.array(np.ascontiguousarray(s, np.float32), dtype=float, device=dev, copy=copy)
    unknown = wp.array(np.ascontiguousarray(band, bool).view(np.uint8), dtype=wp.uint8, device=dev, copy=copy)
    window, params = band_window(radius, dev), rule.band_params(scale)
    names = ("alpha", "fg", "bg", "fg_var", "bg_var", "near_coc", "far_coc", "flags")
    types = (float, wp.vec3, wp.vec3, wp.vec3, wp.vec3, float, float, wp.int32)

    def launch(a: int, b: int) -> list[np.ndarray]:
        out = bk_matting.BandEstimate()
        for name, dtype in zip(names, types):
            setattr(out, name, wp.empty(b - a, dtype=dtype, device=dev))
        if b > a:
            wp.launch(bk_matting.matting_band_kernel, dim=b - a,
                      inputs=[image, coc, unknown, wp.array(by[a:b].astype(np.int32), dtype=wp.int32, device=dev),
                              wp.array(bx[a:b].astype(np.int32), dtype=wp.int32, device=dev), window, params, out],
                      device=dev)
        return [getattr(out, name).numpy() for name in names]

    outs = in_parts(by.size, launch, threads=threads, cpu=dev.is_cpu, check=check)
    return tuple(np.concatenate([o[k] for o in outs]) for k in range(8))


@dataclass(frozen=True, eq=False)
class EdgeBand:
    """The unknown band around a map's depth edges, before its matting: band pixel ``k`` lies at
    ``(y0 + by[k], x0 + bx[k])`` of the box ``(y0, y1, x0, x1)`` (the edges padded by what a band pixel's window
    reaches); ``image`` is the box of the image divided by ``scale`` (its largest value), ``coc`` the box of the map,
    ``band`` the box's band mask, ``radius`` the window's, ``ramp`` the map's measured ramp width.
    :meth:`estimate` runs the matting kernel on a slice of the band pixels."""

    shape: tuple[int, int]
    box: tuple[int, int, int, int]
    by: np.ndarray
    bx: np.ndarray
    ramp: int
    scale: float
    image: np.ndarray
    coc: np.ndarray
    band: np.ndarray
    radius: int

    @property
    def size(self) -> int:
        return int(self.by.size)

    def estimate(self, a: int, b: int, rule: MattingRule, *, device: str = "cpu", threads: int | None = None,
                 check=None) -> EdgeEstimate:
        """The edge estimate of band pixels ``a`` to ``b`` (its arrays that long; ``box``, ``image`` the band's)."""
        by, bx = self.by[a:b], self.bx[a:b]
        out = launch_band_kernel(self.image, self.coc, self.band, by, bx, self.radius, rule, device, threads, check,
                                 self.scale)
        return EdgeEstimate(self, by, bx, *out)


@dataclass(frozen=True, eq=False)
class EdgeEstimate:
    """The matting of band pixels ``by``, ``bx`` (a slice of ``band``'s: :meth:`EdgeBand.estimate`).

    ``alpha`` is the local linear colour model's coverage of the near part, ``fg`` / ``bg`` the near and far
    colours and ``fg_var`` / ``bg_var`` their spreads (all in units of ``band.scale``: the image was divided by its
    largest value), ``near`` / ``far`` the parts' CoC (the window's largest and smallest), ``flags`` the
    kernel's ``BAND_OK`` / ``BAND_OWN_NEAR`` bits.
    """

    band: EdgeBand
    by: np.ndarray
    bx: np.ndarray
    alpha: np.ndarray
    fg: np.ndarray
    bg: np.ndarray
    fg_var: np.ndarray
    bg_var: np.ndarray
    near: np.ndarray
    far: np.ndarray
    flags: np.ndarray

    @property
    def ok(self) -> np.ndarray:
        """The band pixels whose window holds a depth edge and samples of both sides."""
        return (self.flags & bk_matting.BAND_OK) != 0

    @property
    def own_near(self) -> np.ndarray:
        """The band pixels the map puts on the near side of their window's CoC range."""
        return (self.flags & bk_matting.BAND_OWN_NEAR) != 0

    def contrast(self, min_contrast: float) -> np.ndarray:
        """The band pixels whose F and B differ by more than ``min_contrast`` of the brighter of the two
        (Euclidean, linear RGB): elsewhere the colour says nothing about alpha."""
        d = self.fg - self.bg
        den = (d * d).sum(1)
        bright = np.maximum((self.fg * self.fg).sum(1), (self.bg * self.bg).sum(1))
        return (den > np.float32(min_contrast) ** 2 * bright) & (den > 1e-20)


def edge_band(image: np.ndarray, signed_coc: np.ndarray, rule: MattingRule | None = None,
              check=None) -> EdgeBand | None:
    """The band around the depth edges of a checked ``H x W x 3`` float32 linear image's ``H x W`` float32 signed
    CoC (``rule``: :class:`MattingRule`). None where the map has no depth edge or its edges are noise. ``check()``:
    called between the steps (a render stops there: it raises)."""
    rule = rule or MattingRule()
    jump_px, band_px, max_ramp_px, max_isolated_share = (rule.jump_px, rule.band_px, rule.max_ramp_px,
                                                         rule.max_isolated_share)
    check = check or (lambda: None)
    s = signed_coc
    h, w = s.shape
    if h < 2 and w < 2:
        return None
    steps = map_steps(s, float(jump_px))  # the depth edges and the ramp width both read them
    edges = edges_of_steps(steps)
    check()
    if not edges.any():
        return None
    # isolated pixels are edge pixels: only a map with more edge pixels than the share allows can be noise
    if edges.mean() > max_isolated_share and isolated_share(s, float(jump_px)) > max_isolated_share:
        return None  # noise in the map, not edges
    # max |v| as max(max v, -min v): the same value, without a frame-sized |image|
    scale = _largest_magnitude(image) or 1.0
    ramp = ramp_of_steps(s, steps, int(max_ramp_px)) if max_ramp_px > 0 else 0  # capped at 0: not measured
    del steps
    check()
    b = int(band_px) + (ramp + 1) // 2
    radius = ramp + 2 * b + 2
    # work on the box of the edges, padded by everything a band pixel's window reaches
    ey, ex = np.flatnonzero(edges.any(axis=1)), np.flatnonzero(edges.any(axis=0))
    pad = b + radius
    y0, y1 = max(0, int(ey.min()) - pad), min(h, int(ey.max()) + pad + 1)
    x0, x1 = max(0, int(ex.min()) - pad), min(w, int(ex.max()) + pad + 1)
    band = dilate(edges[y0:y1, x0:x1], b)
    # the band's pixels, row-major, and the box of the image divided by its scale (every threshold is relative: the
    # result does not depend on the exposure; the box only: nothing reads more), its rows' parts on the CPU's cores
    box_img = np.empty((y1 - y0, x1 - x0, *image.shape[2:]), (image[:0, :0] / np.float32(scale)).dtype)

    def part(a: int, b: int) -> tuple[np.ndarray, np.ndarray]:
        np.divide(image[y0 + a : y0 + b, x0:x1], np.float32(scale), out=box_img[a:b])
        py, px = np.nonzero(band[a:b])
        return (py + a).astype(np.int32), px.astype(np.int32)

    found = in_row_parts(y1 - y0, x1 - x0, part)
    by, bx = (np.concatenate([f[k] for f in found]) for k in (0, 1))
    check()
    return EdgeBand((h, w), (y0, y1, x0, x1), by, bx, ramp, scale, box_img, s[y0:y1, x0:x1], band, radius)
