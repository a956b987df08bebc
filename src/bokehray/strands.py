"""Strands broken in the map: a gap between two dashes of a thin strand, where the photo shows the strand going on,
takes the strand's depth (docs/soft-scene.md, "Strands broken in the map").

A strand thinner than about a pixel gets its depth only where it covers half a pixel or more: its map is a row of
dashes. The pixels between two dashes hold a share of the strand's colour but keep the background's depth; when
the strand blurs (in front of the focus) they stay sharp, a column of specks of the strand's colour inside its
blur. :func:`bridge_strands` gives those pixels the strand's depth where the photo shows the strand there; the
matting (``bokehray.matting``) then splits them, and the far pixels they now border, into a near and a far part by
their colour, as it does every pixel of a depth edge. A gap the photo shows as background (a hole in a mesh, the
space between two letters) keeps its depth, and so does every pixel of a map without thin structures.

The rule (``bokehray_kernels.strands``): strand pixels are nearer than a pixel within ``thin_px`` on both sides
along one axis; two strand pixels of the same depth, 2 to ``max_gap`` px apart, whose segment crosses pixels behind
them, bridge those pixels when every one of them is thin across the segment and its colour lies on the line from
the background beside it towards the strand's colour, at least ``min_share`` of the way. A dash end is also walked
out along its strand over the pixels behind it whose colour shows the strand (a tip the map cut short, a strand
entering the frame), and nothing is taken over a light.

:func:`hidden_lights` runs after the matting: a light the photo shows on both sides of an opaque strand is taken as
going on behind it (the hidden pixels split, the light their far part).
"""

from __future__ import annotations

from dataclasses import dataclass

import bokehray_kernels.strands as bk_strands
import numpy as np

from .edge_estimate import in_parts
from .scene import SoftEdges

__all__ = ["TILE_PX", "HiddenLightRule", "StrandRule", "bridge_strands", "gap_offsets", "hidden_lights", "varied_tiles"]


@dataclass(frozen=True, slots=True)
class StrandRule:
    """The constants of :func:`bridge_strands` (docs/design/strand-gaps.md)."""

    jump_px: float = 1.0
    """Nearer or farther: a CoC difference of more than this (px), the matting's depth edge."""
    thin_px: int = 2
    """A strand pixel has a farther pixel within this many px on both sides along one axis (at most 3 px across)."""
    max_gap: int = 6
    """The farthest two dashes of a strand may lie apart (px) and be bridged."""
    min_share: float = 0.25
    """A gap pixel's colour lies at least this far from the background towards the strand's colour."""
    max_off: float = 0.5
    """... and at most this share of the strand's contrast off the line between them."""
    min_contrast: float = 0.05
    """A strand whose colour differs from the background's by less than this share of the brighter is not bridged
    (its colour cannot tell a gap from the strand)."""

    end_px: int = 6
    """A dash end is extended along its strand, over the pixels the photo shows holding it, by at most this many px
    (a tip the map cut short, a strand leaving the frame; 0: no extension)."""

    light_level: float = 1.0
    """No pixel is bridged or extended where the strand's colour (its ends') or the background beside it is brighter
    than this (mean of linear RGB; 1: a white surface): a light's, which the colour test cannot read."""

    def struct(self) -> bk_strands.StrandParams:
        p = bk_strands.StrandParams()
        p.jump_px, p.thin_px, p.min_share = float(self.jump_px), int(self.thin_px), float(self.min_share)
        p.max_off, p.min_contrast, p.end_px = float(self.max_off), float(self.min_contrast), int(self.end_px)
        p.light_level = float(self.light_level)
        return p


def gap_offsets(max_gap: int) -> np.ndarray:
    """The (dy, dx) offsets from one dash's pixel to the next one's: 2 to ``max_gap`` px away (Euclidean), after it
    in row-major order (each pair once), nearest first."""
    r = int(max_gap)
    g = np.arange(-r, r + 1)
    oy, ox = (v.ravel() for v in np.meshgrid(g, g, indexing="ij"))
    dist = np.hypot(oy, ox)
    keep = (dist >= 2.0) & (dist <= r) & ((oy > 0) | ((oy == 0) & (ox > 0)))
    order = np.argsort(dist[keep], kind="stable")
    return np.stack([oy[keep], ox[keep]], 1)[order].astype(np.int32)


TILE_PX = 8
"""(A power of two.) The strand-pixel pass skips the tiles of this size whose neighbourhood's map varies by no more than a jump."""


def varied_tiles(s: np.ndarray, jump_px: float, reach: int) -> np.ndarray:
    """The corners ``(y, x)`` (int32, N x 2) of the :data:`TILE_PX` tiles where a pixel may have a pixel farther by
    more than ``jump_px`` within ``reach`` px: those whose map, with the 8 tiles around them,
    spans more than ``jump_px`` (with the tiles within ``reach`` around them). The tiles on the frame's border and
    the ragged last row and column are always taken."""
    t = TILE_PX
    h, w = s.shape
    hq, wq = h // t, w // t
    nty, ntx = -(-h // t), -(-w // t)
    hi = np.full((nty, ntx), np.inf, np.float32)
    lo = np.full((nty, ntx), -np.inf, np.float32)  # ragged tiles: a range of inf, always varied
    if hq and wq:
        whole = s[: hq * t, : wq * t]
        hi[:hq, :wq], lo[:hq, :wq] = _tile_reduce(whole, t, np.maximum), _tile_reduce(whole, t, np.minimum)
    size = 2 * -(-int(reach) // t) + 1
    hi = _grid_filter(hi, size // 2, np.maximum)
    lo = _grid_filter(lo, size // 2, np.minimum)
    varied = hi - lo > np.float32(jump_px)
    varied[[0, -1]] = True  # outside the frame counts as farther: the frame's corners hold strand pixels
    varied[:, [0, -1]] = True
    ty, tx = np.nonzero(varied)
    return np.stack([ty * t, tx * t], 1).astype(np.int32)


def _grid_filter(a: np.ndarray, k: int, op) -> np.ndarray:
    """``op`` (np.maximum, np.minimum) over the ``(2k+1)^2`` square around each cell of the 2-D grid ``a``, the
    border's cells repeated beyond it: ``scipy.ndimage.maximum_filter(a, 2k+1, mode="nearest")`` (and minimum), the
    same values, without importing ``scipy.ndimage`` (0.3 s of a command's start) for a tile grid."""
    if k <= 0:
        return a.copy()
    h, w = a.shape
    p = np.pad(a, k, mode="edge")
    rows = p[: h, :].copy()
    for dy in range(1, 2 * k + 1):
        op(rows, p[dy : dy + h, :], out=rows)
    out = rows[:, :w].copy()
    for dx in range(1, 2 * k + 1):
        op(out, rows[:, dx : dx + w], out=out)
    return out


def _tile_reduce(a: np.ndarray, t: int, op) -> np.ndarray:
    """``op`` (np.maximum, np.minimum) over the ``t`` x ``t`` tiles of ``a`` (sides multiples of ``t``, a power of
    two), by halving: whole-array passes instead of a reduction a tile (a fifth of the time at 12 MP), the rows'
    halvings first (pairs of whole rows: contiguous, the frame's largest pass), then the columns' (0.022 against
    0.028-0.043 CPU-s for both ops at 12 MP, 8 px tiles)."""
    k = t
    while k > 1:
        a = op(a[0::2], a[1::2])
        k //= 2
    while t > 1:
        a = op(a[:, 0::2], a[:, 1::2])
        t //= 2
    return a


def bridge_strands(image: np.ndarray, signed_coc: np.ndarray, rule: StrandRule | None = None, *,
                   device: str = "cpu", threads: int | None = None, check=None) -> tuple[np.ndarray, int]:
    """The signed CoC map with the gaps of thin strands bridged (each gap pixel given the mean depth of the two
    dashes it joins) and their cut ends extended (each pixel given the end's depth), and how many pixels changed.
    ``image``: ``H x W x 3`` float32 linear RGB; ``signed_coc``: ``H x W`` float32, both finite (checked by the
    caller). The map is returned as given (not copied) when nothing
    changes. ``check()``: called between rounds of the kernel (it raises to stop)."""
    import warp as wp

    rule = rule or StrandRule()
    s = np.ascontiguousarray(signed_coc, np.float32)
    h, w = s.shape
    if h < 5 or w < 5:
        return signed_coc, 0
    dev = wp.get_device(device)
    copy = not dev.is_cpu  # on the CPU the kernels read the (contiguous) arrays in place
    coc = wp.array(s, dtype=float, device=dev, copy=copy)
    params = rule.struct()
    strand = wp.zeros((h, w), dtype=wp.uint8, device=dev)
    tiles = varied_tiles(s, rule.jump_px, rule.thin_px)  # elsewhere no pixel has a farther one within reach
    ty0, tx0 = (wp.array(np.ascontiguousarray(tiles[:, k]), dtype=wp.int32, device=dev) for k in (0, 1))
    slot = wp.zeros((len(tiles), TILE_PX * TILE_PX), dtype=wp.uint8, device=dev)

    def launch_tiles(a: int, b: int) -> None:
        if b > a:
            wp.launch(bk_strands.strand_pixels_kernel, dim=(b - a, TILE_PX),
                      inputs=[coc, params, ty0[a:b], tx0[a:b], TILE_PX], outputs=[strand, slot[a:b]], device=dev)

    in_parts(len(tiles), launch_tiles, threads=threads, cpu=dev.is_cpu, check=check, item_px=TILE_PX * TILE_PX)
    i, j = np.divmod(np.flatnonzero(slot.numpy()), TILE_PX * TILE_PX)  # among the tiles' pixels, not the frame's
    if i.size == 0:
        return signed_coc, 0
    ty = (tiles[i, 0] + j // TILE_PX).astype(np.int32)
    tx = (tiles[i, 1] + j % TILE_PX).astype(np.int32)
    img = wp.array(np.ascontiguousarray(image, np.float32), dtype=wp.vec3, device=dev, copy=copy)
    offs = gap_offsets(rule.max_gap)
    oy = wp.array(offs[:, 0], dtype=wp.int32, device=dev)
    ox = wp.array(offs[:, 1], dtype=wp.int32, device=dev)
    out = wp.array(s, dtype=float, device=dev, copy=True)

    def launch(a: int, b: int) -> wp.array | None:
        if b <= a:
            return None
        changed = wp.zeros(1, dtype=wp.int32, device=dev)  # one counter a part: CPU atomics are plain there
        wp.launch(bk_strands.bridge_strands_kernel, dim=b - a,
                  inputs=[img, coc, strand, wp.array(ty[a:b], dtype=wp.int32, device=dev),
                          wp.array(tx[a:b], dtype=wp.int32, device=dev), oy, ox, params],
                  outputs=[out, changed], device=dev)
        return changed

    counts = in_parts(ty.size, launch, threads=threads, cpu=dev.is_cpu, check=check)
    n = sum(int(c.numpy()[0]) for c in counts if c is not None)  # each pixel once, at its first raise
    if n == 0:
        return signed_coc, 0
    return out.numpy(), n


@dataclass(frozen=True, slots=True)
class HiddenLightRule:
    """The constants of :func:`hidden_lights` (docs/soft-scene.md, "A light behind an opaque strand")."""

    light_level: float = 1.0
    """A far colour whose mean of linear RGB is above this is a light's (1: a white surface)."""
    reach: int = 3
    """A light is looked for at most this many px from the hidden pixel on each side along an axis (strands up to
    5 px across)."""
    jump_px: float = 1.0
    """The light lies behind the strand: its CoC lower than the strand pixel's by more than this."""
    alpha: float = 0.999
    """The strand's coverage given to a hidden pixel (it is opaque; the split needs alpha below 1)."""


_AXES = np.array([(0, 1), (1, 0), (1, 1), (1, -1)], np.int64)


def hidden_lights(image: np.ndarray, signed_coc: np.ndarray, soft: SoftEdges,
                  rule: HiddenLightRule | None = None) -> tuple[SoftEdges, int]:
    """``soft`` with the opaque pixels of thin strands across a light split too, and how many were added.

    A pixel that the split leaves whole and that is not lit itself, with a light behind the strand on both sides of
    it along one of the four axes within ``reach`` px (a split pixel whose far part ``B`` is a light, or a whole
    pixel lit in the photo, farther than the pixel by more than ``jump_px``; only pixels of the strand between; the
    two within ``jump_px`` of each other's CoC: one light), hides that light: the photo shows it on both sides of a
    strand thinner than the light. It becomes a split pixel of coverage ``alpha`` whose far part is the light
    interpolated across it (linear in the distance to the two sides, nearest axis first), so that once the strand
    blurs the light shows whole behind it, as it does through a real lens, instead of the dim tone-mapped fill of a
    hidden region. Nothing is looked at unless a split pixel's ``B`` is a light: the search runs along the axes
    within ``reach`` px of those."""
    rule = rule or HiddenLightRule()
    if len(soft) == 0:
        return soft, 0
    bg = soft.background
    lit_split = (bg[:, 0] + bg[:, 1] + bg[:, 2]) > 3.0 * rule.light_level  # channel columns: no small-axis reduce
    if not lit_split.any():
        return soft, 0
    cand = _near_seeds(soft.index[lit_split], soft.far_coc[lit_split], signed_coc, int(rule.reach), rule.jump_px)
    if cand.size:
        k = np.searchsorted(soft.index, cand).clip(0, len(soft) - 1)
        cand = cand[(soft.index[k] != cand) & (image.reshape(-1, 3)[cand].mean(1) <= rule.light_level)]
    if cand.size == 0:
        return soft, 0
    found = _lights_across(image, signed_coc, soft, cand, rule)
    if found is None:
        return soft, 0
    keep, b, far = found
    return _with_hidden(image, signed_coc, soft, cand[keep], b, far, rule.alpha), int(keep.sum())


def _near_seeds(seeds: np.ndarray, far: np.ndarray, s: np.ndarray, r: int, jump: float) -> np.ndarray:
    """The flat indices, sorted and unique, of the pixels up to ``r`` px from the ``seeds`` along the four axes (the
    only places a seed can be the light beside them) that are nearer than the seed's far part ``far`` by more
    than ``jump`` (a strand in front of the light)."""
    h, w = s.shape
    sy, sx = np.divmod(seeds, w)
    k = np.arange(1, r + 1)
    oy = np.concatenate([np.outer(sg * _AXES[:, 0], k).ravel() for sg in (1, -1)])
    ox = np.concatenate([np.outer(sg * _AXES[:, 1], k).ravel() for sg in (1, -1)])
    y, x = sy[:, None] + oy, sx[:, None] + ox
    ok = (y >= 0) & (y < h) & (x >= 0) & (x < w)
    q = np.where(ok, y * w + x, 0)
    ok &= s.ravel()[q] > (far[:, None] + jump)
    q = np.sort(q[ok])
    return q[np.concatenate([[True], q[1:] != q[:-1]])] if q.size else q


def _lights_across(image, s, soft, cand, rule):
    """Per candidate: whether a light lies behind it on both sides along an axis, the light's colour there
    (interpolated) and CoC; None when no candidate has one."""
    h, w = s.shape
    r = int(rule.reach)
    cy, cx = np.divmod(cand, w)
    own = s.ravel()[cand][:, None, None, None]
    steps = np.arange(1, r + 1)
    sides = np.array([1, -1])
    y = cy[:, None, None, None] + sides[None, None, :, None] * _AXES[None, :, 0, None, None] * steps
    x = cx[:, None, None, None] + sides[None, None, :, None] * _AXES[None, :, 1, None, None] * steps
    inside = (y >= 0) & (y < h) & (x >= 0) & (x < w)
    q = np.where(inside, y.clip(0, h - 1) * w + x.clip(0, w - 1), 0)
    k = np.searchsorted(soft.index, q).clip(0, len(soft) - 1)
    split = inside & (soft.index[k] == q)
    colour = np.where(split[..., None], soft.background[k], image.reshape(-1, 3)[q])
    coc = np.where(split, soft.far_coc[k], s.ravel()[q])
    lit = (colour[..., 0] + colour[..., 1] + colour[..., 2]) > 3.0 * rule.light_level
    light = inside & lit & (coc < own - rule.jump_px)
    strand = inside & ~split & ~light & (s.ravel()[q] >= own - rule.jump_px)  # the strand goes on there
    # the first light along each way, with only the strand's pixels before it
    passable = np.cumprod(np.concatenate([np.ones_like(strand[..., :1]), strand[..., :-1]], -1), -1).astype(bool)
    hit = light & passable
    first = np.where(hit.any(-1), hit.argmax(-1), r)  # (C, 4 axes, 2 sides): step index, r = none
    both = (first < r).all(-1)  # (C, 4)
    fc = np.take_along_axis(coc, first.clip(0, r - 1)[..., None], -1)[..., 0]  # (C, 4, 2): the lights' CoC
    both &= np.abs(fc[..., 0] - fc[..., 1]) <= rule.jump_px  # one light: the same depth on both sides
    if not both.any():
        return None
    dist = np.where(both, first.sum(-1) + 2, 4 * r)
    axis = dist.argmin(1)
    keep = both[np.arange(len(cand)), axis]
    ax = axis[keep]
    f = first[keep][np.arange(keep.sum()), ax]  # (n, 2)
    idx = np.flatnonzero(keep)
    c2 = colour[idx, ax]  # (n, 2 sides, r, 3)
    k2 = coc[idx, ax]
    d1, d2 = (f[:, 0] + 1).astype(np.float32), (f[:, 1] + 1).astype(np.float32)
    b1, b2 = c2[np.arange(idx.size), 0, f[:, 0]], c2[np.arange(idx.size), 1, f[:, 1]]
    wt = (d2 / (d1 + d2))[:, None]  # the nearer side weighs more
    b = (wt * b1 + (1 - wt) * b2).astype(np.float32)
    far = (wt[:, 0] * k2[np.arange(idx.size), 0, f[:, 0]] + (1 - wt[:, 0]) * k2[np.arange(idx.size), 1, f[:, 1]])
    return keep, b, far.astype(np.float32)


def _with_hidden(image, s, soft, add, b, far, alpha):
    """``soft`` with the pixels ``add`` split: coverage ``alpha``, far part ``b`` at CoC ``far``, near part solved
    from the photo's pixel (``alpha F + (1 - alpha) b``, F kept non-negative) at the pixel's own CoC."""
    a = np.float32(alpha)
    photo = image.reshape(-1, 3)[add]
    fg = np.clip((photo - (1 - a) * b) / a, 0, None).astype(np.float32)
    at = np.searchsorted(soft.index, add)  # ``add`` is sorted and holds no split pixel
    cuts = np.concatenate([[0], at, [len(soft)]])

    def put(x, y):  # one copy of each field: its runs between the insertions, interleaved with the new entries
        parts = []
        for j in range(add.size):
            parts += [x[cuts[j]:cuts[j + 1]], y[j:j + 1]]
        return np.concatenate([*parts, x[cuts[-2]:]])

    return SoftEdges(put(soft.index, add), put(soft.alpha, np.full(add.size, a, np.float32)), put(soft.foreground, fg),
                     put(soft.background, b), put(soft.near_coc, s.ravel()[add].astype(np.float32)),
                     put(soft.far_coc, far))
