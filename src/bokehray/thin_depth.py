"""Soft depth maps: thin structures a blurred map lost, given back their depth from the photo (docs/soft-scene.md,
"Soft maps").

A soft map is close to the true map blurred, ``D = G_s * D_true``, and the true map is locally two depths whose
boundary is the photo's colour boundary: ``D_true = a . I + b`` over a small window (the matting's local linear
colour model). Blurring both sides, ``D = a . (G_s * I) + b``: a ridge regression of the map on the photo blurred by
``s`` over each window gives ``(a, b)``, and ``a . I + b`` is the map before the blur, with the 1-3 px wires and
twigs a blur of 2-8 px flattened into a faint bump.

Both sides of that model are blurred by ``s``: they hold little finer than ``s`` px, so the regression is fitted on
a grid of ``f ~ s`` px (each sample the mean of its ``f x f`` block of map and photo; block means keep the linear
model exact), a ``f^2``-th of the work of a per-pixel fit (a blur of 2 px is fitted per pixel). Only the output, ``a . I + b`` on the sharp photo,
is per pixel. :func:`restore_thin` tries the blurs ``ThinRule.sigmas`` and
keeps, for the whole image, the one whose colour model explains its usable windows best (the median residual):
one map, one blur. A window is usable where its colour model explains it clearly better than a plane does (tilted
planes and smooth slopes stay exactly as they are) and it holds no hard step (a hard map's step is no blur: hard
maps stay exactly as they are). The restored value is made hard, each pixel at its window's far plateau (its
smallest map value) or at its near value, and used only where that is a structure. The near value follows the
blur model: a thin structure's blurred peak no longer tells its depth, so its near value is the largest restored
value around; a wide object (the map holds its nearest value over a square of 1.5 blurs' radius: an object 4.5
blurs wide or more, whose blurred peak is within 2.5 % of its depth) keeps the map's own plateau, which the
restoration over a texture overshoots. The far value is a plateau of the map, and so is a wide object's near
value (a ramp that does not reach one is the ramp snap's, ``bokehray.ramps``, which runs next); the restoration
does not undershoot the far plateau as a texture's amplified noise would; enough of the window lies on the near
side; and the step is worth a pixel of blur. The matting then splits the mixed pixels of the step this leaves, as
on a hard map.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import bokehray_kernels.thin as bk_thin
import cv2
import numpy as np

from .edge_estimate import in_parts, in_row_parts

__all__ = ["ThinRule", "restore_thin"]


@dataclass(frozen=True, slots=True)
class ThinRule:
    """The constants of :func:`restore_thin` (chosen on the dev set's soft maps: docs/design/thin-depth.md)."""

    sigmas: tuple[float, ...] = (2.0, 4.0, 8.0)
    """The map blurs tried (Gaussian sigma, px); the image keeps the one whose colour model fits its windows best
    (1 px was almost never usable: such a map keeps steps of half its range, which the hard-step test refuses)."""
    sample: float = 1.0
    """A blur ``s`` is fitted on a grid of ``f`` px, the power of two nearest ``sample * s`` (a sample is the mean
    of its ``f x f`` block): the blurred photo aliases by less than 1 % (``exp(-2 pi^2 s^2 / (2 f)^2)``). Half
    that spacing lost 4.4 dB on the two-plane scene at focus 0.5 (its wider windows of 18 - 28 px overshoot)."""
    fine: float = 2.0
    """... except blurs of at most this many px, fitted per pixel (``f = 1``) once the image's blur is chosen
    among the grids' fits: on a grid of 2 px the dev set's Gaussian 2 px maps lost 0.47 dB (whole)."""
    window: float = 1.5
    """A blur ``s`` is fitted over windows of radius ``ceil(window * s) + 1`` px, rounded to whole samples (at
    least 2): 9, 20 and 40 px across for 2, 4 and 8 px."""
    share: float = 0.25
    """The image's blur is chosen among those whose usable windows cover at least this share of the pixels the
    most usable blur's cover (a blur that explains a few windows best is not the map's: the demo at 12 MP, its
    map blurred by 11 px, chose 2 px from 0.2 % of its pixels)."""
    profile: float = 4.0
    """A blur ``s`` is fitted only where the window's map spans between ``s / profile`` and ``profile * s`` of its
    steepest 4-neighbour step (a step blurred by ``s`` spans about ``2.5 s`` of its steepest step): a window
    blurred far more or far less is no fit of it (2 lost 0.03 - 0.08 in the dev set's map error, 4 nothing)."""
    ridge: float = 1e-6
    """Ridge on the colour slopes, in squared tone-mapped colour units (the window's colour covariance is about
    1e-3 to 1e-2: the ridge only keeps flat windows solvable; 1e-4 halved what the fit gives back on the wires)."""
    ratio: float = 0.5
    """The colour model must leave less than this share of a plane's residual over the window."""
    jump: float = 0.5
    """A window with a 4-neighbour step of this share of its range or more holds a hard edge: left alone."""
    undershoot: float = 0.5
    """The restored values may fall below the window's far value by at most this share of the restored step."""
    keep: float = 0.1
    """A pixel in the top (bottom) share of its window's map range is not moved to the far (near) value, whatever
    its colour says (a blob of texture in a plateau is no structure)."""
    flat_reach: float = 1.5
    """A wide object or a thin structure, from the map's blur model: the map's nearest value within twice the window
    is a plateau where the map holds it (within ``flat_tol`` of the step) over a whole square of radius
    ``flat_reach * s`` px (a box of ``2 * flat_reach * s``, to the grid's samples)."""
    flat_tol: float = 0.2
    """A bar of width ``w`` blurred by ``s`` holds its peak within 0.2 of the step over +-1.5 s only where ``w`` is
    4.5 s or more, and its blurred peak is then within 2.5 % of its depth: such an object's near value is the map's
    own plateau, its largest value within twice the window (the restored values overshoot over a texture: the demo
    at 12 MP, its cat's rim 10 - 16 CoC px nearer than the cat; the window's own largest value can lie on the
    ramp's tail, a step of 0.01 CoC px from the plateau: the two-plane scene lost 0.44 dB at focus 0.85); a
    narrower one's blurred peak no longer tells its depth, which the colour does (the largest restored value of the
    window). Wire crossings are peaks, no plateaus: thin. 0.1 / 0.3 moved the dev set's map errors by up to 0.001 /
    0.003."""
    plateau_tol: float = 0.3
    """The window's far value must be a plateau: twice as wide, the map's smallest value is lower by at most this
    share of its range; and so must its near value, where the object is wide (``flat_tol``)."""
    min_sd: float = 0.05
    """A window whose map varies by less than this (CoC px, rms) is flat: left alone."""
    min_step: float = 1.0
    """A window whose map, or restored step, spans less than this (CoC px) is left alone: the two sides' blurs
    differ by less than a pixel (the matting's own depth edge, ``MattingRule.jump_px``)."""
    grad_min: float = 0.2
    """Only maps with a ramp somewhere are looked at: two steps in a row of the same sign, each above this (CoC px
    per px; ``ramps.RampRule.grad_min``)."""

    def factor(self, sigma: float, choosing: bool = False) -> int:
        """The fit's grid spacing (px) for a blur ``sigma`` (``choosing``: the grid the image's blur is chosen on,
        where the fine blurs are fitted on the grid of their size too)."""
        if sigma <= self.fine and not choosing:
            return 1
        return 1 << max(0, round(math.log2(max(1.0, self.sample * sigma))))

    def samples(self, sigma: float, f: int) -> int:
        """The fit's window radius (samples) for a blur ``sigma`` on a grid of ``f`` px."""
        return max(2, round((math.ceil(self.window * sigma) + 1) / f))


def restore_thin(image: np.ndarray, signed_coc: np.ndarray, rule: ThinRule | None = None, *,
                 bounds: tuple[float, float] | None = None, check=None) -> tuple[np.ndarray, int]:
    """The signed CoC map with the depth of structures its blur flattened given back from the photo, and how many
    pixels changed. ``image``: ``H x W x 3`` float32 linear RGB; ``signed_coc``: ``H x W`` float32, both finite.
    ``bounds``: the CoC of the farthest and the nearest disparity (0 and 1): restored values stay within them.
    The map is returned as given (not copied) when nothing changes. ``check()``: called between the blurs tried."""
    rule = rule or ThinRule()
    s = np.ascontiguousarray(signed_coc, np.float32)
    h, w = s.shape
    if h < 3 or w < 3:
        return signed_coc, 0
    photo = np.ascontiguousarray(image[..., :3], np.float32)
    grids = _Grids.of(photo, s, rule.grad_min)
    if grids is None:
        return signed_coc, 0
    best = _best_fit(grids, rule, check)
    lo, hi = -np.inf, np.inf
    if bounds is not None:
        lo, hi = min(grids.low_high[0], min(bounds)), max(grids.low_high[1], max(bounds))
    done = None if best is None else _harden(best, grids, rule, (lo, hi))
    return (signed_coc, 0) if done is None else done


def _full_steps(d: np.ndarray) -> np.ndarray:
    """Each pixel's larger step to its right and lower neighbour."""
    step = np.zeros_like(d)
    np.abs(np.diff(d, axis=0), out=step[:-1])
    np.maximum(step[:, :-1], np.abs(np.diff(d, axis=1)), out=step[:, :-1])
    return step


@dataclass(slots=True)
class _Level:
    """The map and the photo on a grid of ``f`` px: block means (the fit's samples), the map's block minimum and
    maximum and its largest 4-neighbour step within the block (the hard-step test's, exact at any ``f``)."""

    f: int
    photo: np.ndarray
    mean: np.ndarray
    low: np.ndarray
    high: np.ndarray
    step: np.ndarray

    def halved(self) -> _Level:
        return _Level(2 * self.f, _mean2(self.photo), _mean2(self.mean), _pool2(self.low, np.minimum),
                      _pool2(self.high, np.maximum), _pool2(self.step, np.maximum))


@dataclass(slots=True)
class _Fit:
    """One blur's fit on its level's grid: the model ``a . photo + b``, where it may be used, its windows' relative
    residual, the map's smallest and largest value over each window and (once chosen: :func:`_plateaus`) over
    twice it, and the largest value the map holds over a whole square of ``ThinRule.flat_reach`` blurs within twice
    the window."""

    sigma: float
    f: int
    k: int
    a: np.ndarray
    b: np.ndarray
    ok: np.ndarray
    rel: np.ndarray
    far: np.ndarray
    near: np.ndarray
    part: float = 1.0
    far_wide: np.ndarray | None = None
    near_wide: np.ndarray | None = None
    flat: np.ndarray | None = None


class _Grids:
    """The map normalised (``(s - centre) / scale``: mean about 0, range 1) and the photo on the grids of the fits,
    each made when first asked for: the half-resolution grid from the frame in one pass (a Warp kernel, once
    another has found that the map ramps somewhere), the coarser ones each halved from the last, the frame itself (``f = 1``:
    a fine blur's per-pixel fit) only where a fit needs it."""

    def __init__(self, photo: np.ndarray, s: np.ndarray, centre: float, half: _Level, low_high: tuple[float, float]):
        self.photo, self.s, self.centre, self.low_high = photo, s, centre, low_high
        self.by_f = {2: half}

    @property
    def scale(self) -> float:
        """The map's range (its smallest and largest 2 x 2 block values): the normalised map spans 1."""
        return self.low_high[1] - self.low_high[0]

    @classmethod
    def of(cls, photo: np.ndarray, s: np.ndarray, grad_min: float) -> _Grids | None:
        """The grids, or None where no two steps of the same sign above ``grad_min`` follow each other along a
        row or a column (a hard map's steps stand alone: it is not fitted) or the map is flat."""
        if not _ramps(s, grad_min):
            return None
        colour, mean, low, high, step = _half_level(photo, s)
        lo, hi = float(low.min()), float(high.max())
        scale = hi - lo
        if scale <= 0:
            return None
        centre = float(mean.mean())
        c, inv = np.float32(centre), np.float32(1 / scale)
        for x in (mean, low, high):  # in place: no new frame-sized arrays
            np.subtract(x, c, out=x)
            np.multiply(x, inv, out=x)
        np.multiply(step, inv, out=step)
        return cls(photo, s, centre, _Level(2, colour, mean, low, high, step), (lo, hi))

    def __getitem__(self, f: int) -> _Level:
        if f not in self.by_f:
            if f == 1:
                d = self.normalised(self.s)
                self.by_f[1] = _Level(1, self.photo, d, d, d, _full_steps(d))
            else:
                self.by_f[f] = _pad_even(self[f // 2]).halved()
        return self.by_f[f]

    def normalised(self, s: np.ndarray) -> np.ndarray:
        return (s - np.float32(self.centre)) / np.float32(self.scale)


def _ramps(s: np.ndarray, grad_min: float) -> bool:
    """Whether two steps of the same sign above ``grad_min`` follow each other somewhere along a row or a column
    (``bokehray_kernels.thin.thin_ramp_kernel``: bands of rows on the CPU's cores, each row's thread done once one
    is found)."""
    import warp as wp

    h, w = s.shape
    coc = wp.array(s, dtype=float, device="cpu", copy=False)
    found = np.zeros(1, np.int32)
    flag = wp.array(found, dtype=wp.int32, device="cpu", copy=False)

    def band(y0: int, y1: int) -> None:
        if y1 > y0:
            wp.launch(bk_thin.thin_ramp_kernel, dim=y1 - y0, inputs=[coc, y0, float(grad_min)], outputs=[flag],
                      device="cpu")

    in_row_parts(h, w, band)
    return bool(found[0])


def _half_level(photo: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, ...]:
    """The frame's 2 x 2 blocks (the last row / column repeated at an odd side): their mean colour and map value,
    the map's smallest and largest value and largest step to a right or lower neighbour
    (``bokehray_kernels.thin.thin_level_kernel``; bands of block rows on the CPU's cores)."""
    import warp as wp

    h, w = s.shape
    gh, gw = (h + 1) // 2, (w + 1) // 2
    dev = wp.get_device("cpu")
    coc = wp.array(s, dtype=float, device=dev, copy=False)
    img = wp.array(photo, dtype=wp.vec3, device=dev, copy=False)
    colour = np.empty((gh, gw, 3), np.float32)
    mean, low, high, step = (np.empty((gh, gw), np.float32) for _ in range(4))
    outs = [wp.array(colour, dtype=wp.vec3, device=dev, copy=False)]
    outs += [wp.array(x, dtype=float, device=dev, copy=False) for x in (mean, low, high, step)]

    def band(y0: int, y1: int) -> None:
        if y1 > y0:
            wp.launch(bk_thin.thin_level_kernel, dim=y1 - y0, inputs=[coc, img, y0], outputs=outs,
                      device=dev)

    in_row_parts(gh, 4 * gw, band)
    return colour, mean, low, high, step


def _best_fit(levels: _Grids, rule: ThinRule, check) -> _Fit | None:
    """The fit of the blur whose usable windows' median relative residual is lowest (one map, one blur), among
    those whose usable windows cover ``rule.share`` of the most any blur's do, each blur fitted on its own grid; a
    fine blur, chosen on its coarse grid, is applied from its per-pixel fit."""
    fits = []
    for sigma in rule.sigmas:
        if check is not None:
            check()
        fit = _fit(levels[rule.factor(sigma, choosing=True)], sigma, rule, levels.scale, every=2)
        if fit is not None:
            fits.append(fit)
    if not fits:
        return None
    area = [int(x.ok.sum()) * x.f * x.f / x.part for x in fits]  # px whose windows each blur explains
    fits = [x for x, n in zip(fits, area) if n >= rule.share * max(area)]
    best = min(fits, key=lambda x: float(np.median(x.rel[x.ok])))
    if rule.factor(best.sigma) != best.f or best.part < 1:
        best = _fit(levels[rule.factor(best.sigma)], best.sigma, rule, levels.scale)
    return None if best is None else _plateaus(best, levels[best.f], rule)


def _pad_even(level: _Level) -> _Level:
    """The level with a replicated last row / column where a side is odd (a block at the edge is the mean of the
    pixels it holds, weighted towards the last)."""
    h, w = level.mean.shape
    if h % 2 == 0 and w % 2 == 0:
        return level

    def pad(x):
        return cv2.copyMakeBorder(x, 0, h % 2, 0, w % 2, cv2.BORDER_REPLICATE)

    return _Level(level.f, pad(level.photo), pad(level.mean), pad(level.low), pad(level.high), pad(level.step))


def _mean2(x: np.ndarray) -> np.ndarray:
    return cv2.resize(x, (x.shape[1] // 2, x.shape[0] // 2), interpolation=cv2.INTER_AREA)


def _pool2(x: np.ndarray, op) -> np.ndarray:
    rows = op(x[0::2], x[1::2])  # whole rows first: contiguous, half the strided work
    return op(rows[:, 0::2], rows[:, 1::2])


def _box_sum(x: np.ndarray, r: int) -> np.ndarray:
    """The sum over each (2r+1)^2 window, nothing beyond the grid's borders (a mirrored slope is no plane)."""
    return cv2.boxFilter(x, -1, (2 * r + 1, 2 * r + 1), normalize=False, borderType=cv2.BORDER_CONSTANT)


def _box(x: np.ndarray, r: int) -> np.ndarray:
    """The mean over each (2r+1)^2 window, cut at the grid's borders."""
    h, w = x.shape[:2]
    count = np.outer(_extent(h, r)[2], _extent(w, r)[2]).astype(x.dtype)
    return _box_sum(x, r) / (count if x.ndim == 2 else count[..., None])


def _extent(n: int, r: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per index along an axis of ``n``: the first and last index of its window of radius ``r``, and the count."""
    i = np.arange(n)
    lo, hi = np.maximum(i - r, 0), np.minimum(i + r, n - 1)
    return lo, hi, hi - lo + 1


def _erode(x: np.ndarray, k: int) -> np.ndarray:
    return cv2.erode(x, np.ones((2 * k + 1, 2 * k + 1), np.uint8), borderType=cv2.BORDER_REPLICATE)


def _dilate(x: np.ndarray, k: int) -> np.ndarray:
    return cv2.dilate(x, np.ones((2 * k + 1, 2 * k + 1), np.uint8), borderType=cv2.BORDER_REPLICATE)


def tone(photo: np.ndarray) -> np.ndarray:
    """The regression's colour: ``c / (1 + c)`` (a lamp's value does not swamp the fit)."""
    return photo / (1 + np.maximum(photo, 0))


def _fit(level: _Level, sigma: float, rule: ThinRule, scale: float, every: int = 1) -> _Fit | None:
    """The colour model of one blur on its level's grid, where its windows may be used; None where none may (no
    window varies by a pixel of blur, or every one that does holds a hard step: nothing is fitted). The grid goes
    tile by tile: a tile with no window that may be used costs nothing. ``every = 2``: where there are ``_SPARE``
    tiles or more to fit, only a lattice of them is, one of every ``m``, ``m`` at least 2 and enough to leave about
    ``_CHOOSE`` (enough to choose the image's blur from; :class:`_Fit`'s ``part`` is the share fitted). The lattice,
    ``7 ty + 3 tx = 0 (mod m)`` over the tiles' rows and columns, is a checkerboard at ``m = 2`` and spreads over
    both rows and columns at any ``m``."""
    f, k = level.f, rule.samples(sigma, level.f)
    far, near = _erode(level.low, k), _dilate(level.high, k)
    span = near - far
    steepest = _dilate(level.step, k)
    maybe = (steepest < rule.jump * span) & (span >= rule.min_step / scale)
    # the blur the window's profile shows: a step blurred by s spans about 2.5 s of its steepest steps
    maybe &= (span >= sigma / rule.profile * steepest) & (span <= rule.profile * sigma * steepest)
    if not maybe.any():
        return None
    h, w = maybe.shape
    a, b = np.zeros((h, w, 3), np.float32), np.zeros((h, w), np.float32)
    ok, rel = np.zeros((h, w), bool), np.full((h, w), np.inf, np.float32)
    # the block means are a box of f px (variance (f^2 - 1) / 12): the rest of the blur on the grid
    rest = math.sqrt(max(sigma * sigma - (f * f - 1) / 12, 0.0)) / f
    margin = k + math.ceil(4 * rest) + 1  # the windows and the blur's kernel reach this far
    floor = (rule.min_sd / scale) ** 2
    # the colours are centred for the float64 sums (any one centre keeps the fit exact: a coarse mean of the grid)
    centre = tone(level.photo[::8, ::8]).reshape(-1, 3).mean(0).astype(np.float64)

    def tile(y0: int, x0: int) -> None:
        core = (slice(y0, y0 + _TILE), slice(x0, x0 + _TILE))
        ya, xa, yb, xb = max(0, y0 - margin), max(0, x0 - margin), min(h, y0 + _TILE + margin), min(w, x0 + _TILE + margin)
        part = (slice(ya, yb), slice(xa, xb))
        inner = np.zeros((yb - ya, xb - xa), bool)
        inner[y0 - ya : y0 - ya + _TILE, x0 - xa : x0 - xa + _TILE] = maybe[core]
        iy, ix = np.nonzero(inner)
        fa, fb, fok, frel = _fit_part(level.photo[part], level.mean[part], inner, rest, k, rule, floor, centre)
        a[iy + ya, ix + xa], b[iy + ya, ix + xa], ok[iy + ya, ix + xa], rel[iy + ya, ix + xa] = fa, fb, fok, frel

    tiles = [(y0, x0) for y0 in range(0, h, _TILE) for x0 in range(0, w, _TILE)
             if maybe[y0 : y0 + _TILE, x0 : x0 + _TILE].any()]  # a tile with no window that may be used: skipped
    part = 1.0
    if every > 1 and len(tiles) >= _SPARE:
        m = max(every, -(-len(tiles) // _CHOOSE))
        kept = [(y0, x0) for y0, x0 in tiles if (7 * (y0 // _TILE) + 3 * (x0 // _TILE)) % m == 0]
        part, tiles = len(kept) / len(tiles), kept
    for y0, x0 in tiles:
        tile(y0, x0)
    if not ok.any():
        return None
    return _Fit(sigma, f, k, a, b, ok, rel, far, near, part)


def _plateaus(fit: _Fit, level: _Level, rule: ThinRule) -> _Fit:
    """The chosen fit with the map's smallest and largest value over twice each window, and the largest value the
    map holds over a whole square of ``rule.flat_reach`` blurs within it."""
    e = max(1, int(rule.flat_reach * fit.sigma / fit.f))  # the square's radius in samples
    fit.far_wide, fit.near_wide = _erode(level.low, 2 * fit.k), _dilate(level.high, 2 * fit.k)
    fit.flat = _dilate(_erode(level.low, e), 2 * fit.k)
    return fit


_TILE = 128
"""The fit goes over its grid in tiles of this many samples (and the margin its windows and blur reach)."""
_SPARE = 8
"""The image's blur is chosen from a part of a grid's tiles where it has this many to fit ..."""
_CHOOSE = 16
"""... about this many, or half of them where that is more (the same choice as from all on the demo at 1.5, 3.5
and 12 MP, every soft kind)."""


def _fit_part(photo: np.ndarray, d: np.ndarray, where: np.ndarray, rest: float, k: int, rule: ThinRule,
              floor: float, centre: np.ndarray):
    """The regression at the samples ``where`` of a part of the grid: (a, b, usable, relative residual), 1-D."""
    guide = tone(photo).astype(np.float64)  # float64: the 3 x 3 solve is ill-conditioned where colours align
    guide -= centre
    gb = cv2.GaussianBlur(guide, (0, 0), rest, borderType=cv2.BORDER_REFLECT) if rest > 0 else guide
    a, b, res, var, plane = _window_fit(gb, d.astype(np.float64), np.nonzero(where), k, rule.ridge)
    ok = (res < rule.ratio * plane) & (var > floor)
    return a, b - a @ centre, ok, res / np.maximum(var, 1e-12)  # b: the model on the photo as it is, not centred


def _in_parts(n: int, run, item_px: int) -> list:
    """``edge_estimate.in_parts`` over ``n`` items of ``item_px`` pixels' work each, on one thread where that is
    under ``_PARALLEL_PX`` (a thread costs more than it saves there)."""
    return in_parts(n, run, item_px=item_px, threads=None if n * item_px >= _PARALLEL_PX else 1)


_PARALLEL_PX = 1 << 17


def _window_fit(gb: np.ndarray, d: np.ndarray, at: tuple[np.ndarray, np.ndarray], k: int, ridge: float):
    """Per window of radius ``k`` around the samples ``at`` (cut at the grid's borders): ``d ~ a . gb + b`` by
    ridge regression, its residual variance, the variance of ``d`` and the best plane's residual variance
    (``bokehray_kernels.thin.thin_fit_kernel``, float64; the samples in parts on the CPU's cores)."""
    import warp as wp

    n = at[0].size
    guide = wp.array(np.ascontiguousarray(gb), dtype=wp.vec3d, device="cpu", copy=False)
    dm = wp.array(np.ascontiguousarray(d), dtype=wp.float64, device="cpu", copy=False)
    ys, xs = at[0].astype(np.int32), at[1].astype(np.int32)
    a = np.empty((n, 3), np.float64)
    b, res, var, plane = (np.empty(n, np.float64) for _ in range(4))

    # runs of consecutive samples along a row: a thread a run, its windows' sums sliding along it
    cut = np.flatnonzero((np.diff(ys) != 0) | (np.diff(xs) != 1)) + 1
    first = np.concatenate([[0], cut]).astype(np.int32) if n else np.zeros(0, np.int32)
    runs = np.diff(np.append(first, n)).astype(np.int32)
    wys, wxs = (wp.array(v, dtype=wp.int32, device="cpu", copy=False) for v in (ys, xs))
    outs = [wp.array(a, dtype=wp.vec3d, device="cpu", copy=False)]
    outs += [wp.array(x, dtype=wp.float64, device="cpu", copy=False) for x in (b, res, var, plane)]

    def part(i: int, j: int) -> None:
        if j > i:
            wp.launch(bk_thin.thin_fit_kernel, dim=j - i,
                      inputs=[guide, dm, wys, wxs, wp.array(runs[i:j], dtype=wp.int32, device="cpu", copy=False),
                              wp.array(first[i:j], dtype=wp.int32, device="cpu", copy=False), k, ridge], outputs=outs,
                      device="cpu")

    _in_parts(first.size, part, (2 * k + 1) * max(1, n // max(1, first.size)) * 4)
    return a, b, res, var, plane


def _harden(fit: _Fit, grids: _Grids, rule: ThinRule, bounds: tuple[float, float]):
    """Each pixel of a usable block at its window's far value (the map's smallest) or near value (a thin
    structure's: the largest restored value; a wide object's, whose map holds its peak as a plateau: that plateau,
    if lower), where that is a structure: the far value is a plateau of the map, and so is a wide object's near
    value; the restoration does not undershoot the far value; enough of the window is on the near side; the step
    is worth a pixel of blur. Only the usable blocks' pixels are computed (the rest of the image costs nothing;
    ``bokehray_kernels.thin``): the map with those pixels moved (values clamped to ``bounds``, in CoC px) and how
    many moved, or None."""
    iy, ix = np.nonzero(fit.ok)
    k = fit.k
    blocks = _BlockArgs(grids, fit, iy, ix)
    est, top, low = blocks.extremes()
    top = _dilate(_scatter(fit.ok.shape, iy, ix, top, -np.inf), k)
    low = _erode(_scatter(fit.ok.shape, iy, ix, low, np.inf), k)
    far = fit.far
    wide = fit.near_wide - fit.flat <= rule.flat_tol * (fit.near_wide - far)  # the map's peak is a plateau
    nearv = np.where(wide, np.minimum(top, fit.near_wide), top)  # the near value: a wide object's, its plateau
    above = (est > (0.5 * (far + nearv))[iy, ix][:, None, None]).sum((1, 2))
    n_high = _box(_scatter(fit.ok.shape, iy, ix, above, 0.0), k)
    tol = rule.plateau_tol * (fit.near_wide - fit.far_wide)
    use = fit.ok & (far - fit.far_wide <= tol) & (~wide | (fit.near_wide - fit.near <= tol))
    use &= far - low <= rule.undershoot * (top - far)
    use &= nearv - far >= rule.min_step / grids.scale
    r = (2 * k + 1) * fit.f // 2  # the window's radius in px: a structure holds half a line across it
    use &= n_high * ((2 * k + 1) ** 2) >= r + 1
    pick = use[iy, ix]
    if not pick.any():
        return None
    return blocks.harden(pick, far, nearv, fit.near, rule, bounds)


def _scatter(shape: tuple[int, int], iy: np.ndarray, ix: np.ndarray, per_block: np.ndarray, fill: float) -> np.ndarray:
    out = np.full(shape, fill, np.float32)
    out[iy, ix] = per_block
    return out


class _BlockArgs:
    """The usable blocks of a fit as the hardening kernels' arguments (the blocks cut into parts on the CPU's
    cores)."""

    def __init__(self, grids: _Grids, fit: _Fit, iy: np.ndarray, ix: np.ndarray):
        import warp as wp

        self.wp, self.grids, self.f = wp, grids, fit.f
        self.iy, self.ix = iy.astype(np.int32), ix.astype(np.int32)
        self.a = np.ascontiguousarray(fit.a[iy, ix], np.float32)
        self.b = np.ascontiguousarray(fit.b[iy, ix], np.float32)
        self.photo = wp.array(grids.photo, dtype=wp.vec3, device="cpu", copy=False)
        self.coc = wp.array(grids.s, dtype=float, device="cpu", copy=False)

    def _arrays(self, a: int, b: int, *extra: np.ndarray) -> list:
        wp = self.wp
        out = [wp.array(self.iy[a:b], dtype=wp.int32, device="cpu", copy=False),
               wp.array(self.ix[a:b], dtype=wp.int32, device="cpu", copy=False),
               wp.array(self.a[a:b], dtype=wp.vec3, device="cpu", copy=False),
               wp.array(self.b[a:b], dtype=float, device="cpu", copy=False)]
        return out + [wp.array(np.ascontiguousarray(x[a:b], np.float32), dtype=float, device="cpu", copy=False)
                      for x in extra]

    def extremes(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The sharp model at each block's pixels (N x f x f), and each block's largest and smallest value."""
        wp, n = self.wp, self.iy.size
        est = np.empty((n, self.f, self.f), np.float32)
        top, low = np.empty(n, np.float32), np.empty(n, np.float32)

        def part(a: int, b: int) -> None:
            if b > a:
                outs = [wp.array(est[a:b], dtype=float, device="cpu", copy=False)]
                outs += [wp.array(x[a:b], dtype=float, device="cpu", copy=False) for x in (top, low)]
                wp.launch(bk_thin.thin_extremes_kernel, dim=b - a, inputs=[self.photo, *self._arrays(a, b), self.f],
                          outputs=outs, device="cpu")

        _in_parts(n, part, self.f * self.f)
        return est, top, low

    def harden(self, pick: np.ndarray, far: np.ndarray, nearv: np.ndarray, top: np.ndarray, rule: ThinRule,
               bounds: tuple[float, float]):
        """The map with the picked blocks' pixels at their far or near value, and how many moved; None if none."""
        wp, g = self.wp, self.grids
        idx = np.flatnonzero(pick)
        self.iy, self.ix, self.a, self.b = self.iy[idx], self.ix[idx], self.a[idx], self.b[idx]
        per = [x[self.iy, self.ix] for x in (far, nearv, top)]
        out = g.s.copy()
        wout = wp.array(out, dtype=float, device="cpu", copy=False)
        params = bk_thin.HardenParams()
        params.f, params.centre, params.scale = self.f, g.centre, g.scale
        params.keep, params.keep_top = rule.keep, 1 - rule.keep
        params.lo, params.hi = bounds

        def part(a: int, b: int) -> int:
            moved = wp.zeros(1, dtype=wp.int32, device="cpu")
            if b > a:
                wp.launch(bk_thin.thin_harden_kernel, dim=b - a,
                          inputs=[self.photo, self.coc, *self._arrays(a, b, *per), params], outputs=[wout, moved],
                          device="cpu")
            return int(moved.numpy()[0])

        n = sum(_in_parts(idx.size, part, self.f * self.f))
        return (out, n) if n else None
