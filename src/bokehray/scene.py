"""The layered scene built from a photo: the step every quality level stands on.

From one image and its signed CoC map ``s = K (d - d_f)`` (px, > 0 in front of the focus):

1. CoC radii beyond twice the image diagonal are compressed (:func:`cap_coc`);
2. tiles that nothing blurred can reach are marked to copy (:func:`copy_tiles`, preview only);
3. the remaining pixels are cut into depth layers by ``s`` (:func:`layer_edges`): a :class:`LayeredScene`
   holds the per-pixel layer ids, the edges, the largest CoC and one :class:`LayerRecord` per layer (its CoC
   range, bounding box, radius bound and fill reach); with soft edges (:class:`SoftEdges`, from matting) the
   mixed pixels at depth edges are split first (:func:`split_scene`): the far part is the pixel, the near part
   a source of the layer its CoC falls in (:class:`NearParts`);
4. each layer's sources, its own pixels, its near parts, plus the pull-push fill of the region nearer layers hide
   (:func:`build_layer_sources`);
5. how far a layer's light and fill reach (:func:`scatter_halo`, :func:`fill_halo`), so tiles can be cut
   with exact halos (``bokehray.tiling``).

The preview scatters each layer's sources (``bokehray.levels.preview``); the ray tracer turns them into
textures and traces rays through them (``bokehray.levels.raytrace``). Nothing else recomputes a footprint.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import math
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass

import bokehray_kernels as bk
import numpy as np
import warp as wp

from . import _memory
from .edge_estimate import dilate, in_row_parts, on_threads, row_parts
from .options import LayerOptions

__all__ = [
    "FILL_MIN_REACH_PX", "LayerRecord", "LayerSources", "LayeredScene", "NearParts", "SoftEdges", "build_layer_sources",
    "build_scene", "cap_coc", "check_soft_edges", "copy_tiles", "copy_tiles_of", "fill_halo", "layer_edges", "pad_soft_edges",
    "pyramid_levels", "radius_tile_max", "rim_radii", "row_span", "scatter_halo", "soft_radius", "soft_replicas", "split_scene", "tile_max",
    "tile_reduce", "tile_reduce_in_parts",
]  # fmt: skip

def row_span(device, width: int) -> tuple[int, int]:
    """``(threads a row, pixels a thread)`` for the per-pixel kernels that take a ``span`` (a launch of ``(rows,
    threads a row)``): a row a thread on a CPU, where Warp calls a kernel once a thread (a thread a pixel cost
    1.5-2x the time), a pixel a thread on a GPU."""
    span = max(1, int(width)) if wp.get_device(device).is_cpu else 1
    return -(-int(width) // span), span


FILL_MIN_REACH_PX = 0.5
"""A layer is filled only when nearer layers blur by at least this much (below it nothing behind them shows)."""

FILL_GATE_SLOPE = bk.FILL_GATE_SLOPE
"""The fill reaches ``FILL_GATE_SLOPE * r + 1`` px (L1) behind a hider of CoC radius ``r``: sqrt(2), an L1
distance bound of the Euclidean disc (defined once, in the kernels)."""

MAX_PULL_LEVELS = 16

COARSE_SCATTER_CELLS = 2
"""A level-l scatter spreads up to this many cells of ``2^l`` px beyond the radius (coarse pixels, bilinear
upsampling): a layer's box holds them."""

CUT_CELLS = 2
"""A tile's window cuts the coarse cells at its border (they sum fewer pixels than in the untiled render); its
halo keeps this many further cells of the coarsest level between them and the tile's core."""

_HISTOGRAM_BIN_PX = 0.25


@dataclass(frozen=True, slots=True, eq=False)
class SoftEdges:
    """Mixed pixels at depth edges split into a near part (foreground colour F with coverage alpha, at near_coc)
    and a far part (background colour B, coverage 1, at far_coc). Sparse: only the split pixels (flat indices).

    The far part replaces the pixel in the scene (colour B, coverage 1, CoC ``far_coc``); the near part is an
    extra source (premultiplied ``alpha F``, coverage ``alpha``, CoC ``near_coc``). In focus,
    ``alpha F + (1 - alpha) B`` is the photo's pixel.
    """

    index: np.ndarray  # (n,) int64 flat pixel indices (row-major, y * W + x), sorted, unique
    alpha: np.ndarray  # (n,) float32 in (0, 1): foreground coverage
    foreground: np.ndarray  # (n, 3) float32 linear RGB, F (decontaminated)
    background: np.ndarray  # (n, 3) float32 linear RGB, B
    near_coc: np.ndarray  # (n,) float32 signed CoC (px) of the near part (> far_coc)
    far_coc: np.ndarray  # (n,) float32 signed CoC of the far part

    @classmethod
    def empty(cls) -> SoftEdges:
        """No split pixel: the scene is the photo's, one depth a pixel."""
        f = np.zeros(0, np.float32)
        return cls(np.zeros(0, np.int64), f, np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32), f.copy(),
                   f.copy())

    def __len__(self) -> int:
        return int(self.index.shape[0])


@dataclass(frozen=True, slots=True, eq=False)
class NearParts:
    """The near parts of the split pixels as a scene holds them: position (y, x) in the scene's frame (or a
    window's, :meth:`window`), the premultiplied source ``(alpha F, alpha)``, its signed CoC and its layer."""

    y: np.ndarray  # (n,) int32
    x: np.ndarray  # (n,) int32
    value: np.ndarray  # (n, 4) float32
    coc: np.ndarray  # (n,) float32
    layer: np.ndarray  # (n,) int32

    @classmethod
    def empty(cls) -> NearParts:
        i = np.zeros(0, np.int32)
        return cls(i, i.copy(), np.zeros((0, 4), np.float32), np.zeros(0, np.float32), i.copy())

    def __len__(self) -> int:
        return int(self.y.shape[0])

    def window(self, box: tuple[int, int, int, int]) -> NearParts:
        """The parts inside ``box`` (y0, y1, x0, x1), in the box's coordinates."""
        y0, y1, x0, x1 = box
        k = (self.y >= y0) & (self.y < y1) & (self.x >= x0) & (self.x < x1)
        return NearParts((self.y[k] - y0).astype(np.int32), (self.x[k] - x0).astype(np.int32), self.value[k],
                         self.coc[k], self.layer[k])


def _border_replicas(soft: SoftEdges, shape: tuple[int, int], pads: tuple[int, int, int, int]):
    """Per split pixel on the frame's border: its index among the split pixels, and how many rows and columns of
    the padded frame it stands in (itself and its replicas)."""
    h0, w0 = shape
    pt, pb, pl, pr = pads
    y, x = soft.index // w0, soft.index % w0
    on = np.flatnonzero((y == 0) | (y == h0 - 1) | (x == 0) | (x == w0 - 1))
    yb, xb = y[on], x[on]
    top, bottom = np.where(yb == 0, pt, 0), np.where(yb == h0 - 1, pb, 0)
    left, right = np.where(xb == 0, pl, 0), np.where(xb == w0 - 1, pr, 0)
    return on, yb, xb, top, 1 + top + bottom, left, 1 + left + right


def soft_replicas(soft: SoftEdges, shape: tuple[int, int], pads: tuple[int, int, int, int]) -> int:
    """How many replicas :func:`pad_soft_edges` adds (counted before anything is allocated)."""
    if len(soft) == 0 or not any(pads):
        return 0
    _, _, _, _, nr, _, nc = _border_replicas(soft, shape, pads)
    return int((nr.astype(np.int64) * nc - 1).sum())


def pad_soft_edges(soft: SoftEdges, shape: tuple[int, int], pads: tuple[int, int, int, int]) -> SoftEdges:
    """``soft`` on the frame of ``shape`` edge-replicated by ``pads`` (top, bottom, left, right), as
    ``np.pad(mode="edge")`` replicates the image: a split pixel on the border is split alike in its replicas."""
    h0, w0 = shape
    pt, _, pl, pr = pads
    w = w0 + pl + pr
    if len(soft) == 0:
        return soft
    on, yb, xb, top, nr, left, nc = _border_replicas(soft, shape, pads)
    count = nr.astype(np.int64) * nc - 1  # every (row, column) of the pixel's but its own
    g = np.repeat(np.arange(on.size), count)
    j = np.arange(g.size) - np.repeat(np.cumsum(count) - count, count) + 1  # 1 .. nr * nc - 1 within a pixel
    k, m = j // nc[g], j % nc[g]  # the k-th of its rows, the m-th of its columns (0: its own)

    def place(own, n_before, k, start_after):  # own, then the pads before, then those after
        return np.where(k == 0, own, np.where(k <= n_before, k - 1, start_after + (k - 1 - n_before)))

    rows = place(yb[g] + pt, top[g], k, h0 + pt)
    cols = place(xb[g] + pl, left[g], m, w0 + pl)
    y, x = soft.index // w0, soft.index % w0
    index = np.concatenate([(y + pt) * w + (x + pl), rows.astype(np.int64) * w + cols])
    src = np.concatenate([np.arange(len(soft)), on[g]])
    order = np.argsort(index, kind="stable")
    k = src[order]
    return SoftEdges(index[order], soft.alpha[k], soft.foreground[k], soft.background[k], soft.near_coc[k],
                     soft.far_coc[k])


def soft_radius(signed_coc: np.ndarray, soft: SoftEdges | None) -> np.ndarray:
    """The CoC radius a pixel's light can have: ``|s|``, and at split pixels the larger of its two parts' (what
    :func:`copy_tiles` must see)."""
    r = np.abs(signed_coc)
    if soft is not None and len(soft):
        flat = r.reshape(-1)
        flat[soft.index] = np.maximum(np.abs(soft.near_coc), np.abs(soft.far_coc))
    return r


def rim_radii(signed_coc: np.ndarray, soft: SoftEdges | None) -> tuple[np.ndarray, ...]:
    """The frame's first and last row and first and last column of :func:`soft_radius` (top, bottom, left,
    right), from the rims alone."""
    h, w = signed_coc.shape
    rims = tuple(np.abs(v) for v in (signed_coc[0, :], signed_coc[-1, :], signed_coc[:, 0], signed_coc[:, -1]))
    if soft is not None and len(soft):
        y, x = np.divmod(soft.index, w)
        r = np.maximum(np.abs(soft.near_coc), np.abs(soft.far_coc))
        for rim, on, at in zip(rims, (y == 0, y == h - 1, x == 0, x == w - 1), (x, x, y, y)):
            rim[at[on]] = r[on]
    return rims


def check_soft_edges(soft: SoftEdges, shape: tuple[int, int]) -> None:
    """Refuse split pixels that are not what :class:`SoftEdges` promises (one clear line)."""
    from .errors import InputError

    n = len(soft)
    idx = np.asarray(soft.index)
    if idx.ndim != 1 or any(np.shape(a)[:1] != (n,) for a in (soft.alpha, soft.foreground, soft.background,
                                                                   soft.near_coc, soft.far_coc)):
        raise InputError(f"soft edges: expected n entries in every field, got index {idx.shape}, alpha "
                         f"{np.shape(soft.alpha)}, foreground {np.shape(soft.foreground)}")
    if n == 0:
        return
    if idx.min() < 0 or idx.max() >= shape[0] * shape[1] or (np.diff(idx) <= 0).any():
        raise InputError(f"soft edges: expected sorted unique pixel indices in [0, {shape[0] * shape[1]}), got "
                         f"{int(idx.min())} .. {int(idx.max())}")
    fields = (soft.alpha, soft.foreground, soft.background, soft.near_coc, soft.far_coc)
    if not all(np.isfinite(a).all() for a in fields):
        raise InputError("soft edges: expected finite alpha, colours and CoCs")
    if (soft.alpha <= 0).any() or (soft.alpha >= 1).any():
        raise InputError("soft edges: expected alpha in (0, 1) at every split pixel")


def within_range(alpha: np.ndarray, fg: np.ndarray, bg: np.ndarray, photo: np.ndarray, lo: np.ndarray,
                  hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """F and B of split pixels kept inside the photo's per-channel range ``[lo, hi]`` (every render is a
    convex combination of the photo's radiances): where either lies outside it, F is clamped into it and B
    solved from the photo's pixel ``alpha F + (1 - alpha) B``; if that B lies outside, B is clamped and F solved
    (then inside, as the pixel is). Pixels whose F and B are inside are untouched."""
    out = ((fg < lo) | (fg > hi) | (bg < lo) | (bg > hi)).any(axis=1)
    if not out.any():
        return fg, bg
    fg, bg = fg.astype(np.float32), bg.astype(np.float32)
    a, p = alpha[out, None].astype(np.float64), photo[out].astype(np.float64)
    f = np.clip(fg[out].astype(np.float64), lo, hi)
    b = (p - a * f) / (1.0 - a)
    bad = (b < lo) | (b > hi)
    b = np.clip(b, lo, hi)
    f = np.where(bad, (p - (1.0 - a) * b) / a, f)
    fg[out], bg[out] = np.clip(f, lo, hi), b
    return fg, bg


def split_scene(image: np.ndarray, signed_coc: np.ndarray, soft: SoftEdges | None, active: np.ndarray,
                options: LayerOptions, level_radius_px: float | None = None, *, overwrite: bool = False,
                photo_range: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray, LayeredScene]:
    """The layered scene with the mixed pixels of ``soft`` split: (colour, signed CoC, scene) to build sources on.

    A split pixel's far part replaces it (colour B, signed CoC ``far_coc``: it is a pixel of the far part's
    layer); its near part (``alpha F``, ``alpha``) is a source of the layer ``near_coc`` falls in
    (``LayeredScene.near``). The layer edges see both parts' CoCs. A split whose parts fall in one layer stays
    the photo's pixel (inside a layer nothing is occluded: the split would change nothing but the ray tracer's
    one depth a pixel), and so does one on a pixel that is not ``active`` (a copied tile: its parts are both
    in focus, the photo's pixel is their sum). F and B are kept inside the photo's colour range
    (:func:`within_range`). Without split pixels this is ``build_scene`` on the inputs.

    ``overwrite=True``: ``image`` and ``signed_coc`` are the caller's to change (copies it made, such as a padded
    frame, that it reads no more as they were): the split pixels' far colour and CoC are written into them
    (when float32, C-contiguous and writeable; ``image`` of three channels) instead of into copies (226 MB at
    12 MP), and they are returned. The same values either way. ``photo_range``: the image's per-channel smallest
    and largest value (float32, of its first three channels) when the caller has them (None: found here).
    """
    if soft is None or len(soft) == 0:
        return image, signed_coc, build_scene(signed_coc, active, options, level_radius_px)
    w = signed_coc.shape[1]
    keep = active.reshape(-1)[soft.index]
    idx = soft.index[keep]
    far = soft.far_coc[keep].astype(np.float32)
    near = soft.near_coc[keep].astype(np.float32)
    s = signed_coc if overwrite and _writable(signed_coc, np.float32, 2) else signed_coc.copy()
    photo_coc = s.reshape(-1)[idx]  # the photo's CoC of the split pixels (a copy), before the far parts replace it
    s.reshape(-1)[idx] = far
    # the layer edges see the active pixels' CoC and the near parts' (read in place, band by band)
    values, lo, hi, lo32, hi32 = _active_values(s, active, near)
    edges = _layer_edges_of(values, lo32, hi32, options)
    del values
    e32 = float32_edges(edges)
    far_id = np.clip(np.searchsorted(e32, far, side="right") - 1, 0, len(edges) - 2)
    near_id = np.clip(np.searchsorted(e32, near, side="right") - 1, 0, len(edges) - 2)
    split = near_id > far_id
    back = idx[~split]  # one layer (or near behind far): the photo's pixel
    orig = photo_coc[~split]
    s.reshape(-1)[back] = orig
    if len(back):  # keep the photo's CoC of those pixels inside the layers' range
        edges[0] = min(edges[0], float(orig.min()) - 0.5)
        edges[-1] = max(edges[-1], float(orig.max()) + 0.5)
        lo, hi = min(lo, float(orig.min())), max(hi, float(orig.max()))
    idx, keep_i = idx[split], np.flatnonzero(keep)[split]
    a = soft.alpha[keep_i].astype(np.float32)
    img = image if overwrite and _writable(image, np.float32, 3) and image.shape[2] == 3 else \
        np.array(image[..., :3], np.float32)
    lo_c, hi_c = photo_range or (img.min(axis=0).min(axis=0), img.max(axis=0).max(axis=0))  # per axis: far faster than axis=(0, 1)
    fg, bg = within_range(a, soft.foreground[keep_i], soft.background[keep_i], img.reshape(-1, 3)[idx], lo_c, hi_c)
    value = np.concatenate([fg * a[:, None], a[:, None]], axis=1).astype(np.float32)
    parts = NearParts((idx // w).astype(np.int32), (idx % w).astype(np.int32), value, near[split],
                      near_id[split].astype(np.int32))
    img.reshape(-1, 3)[idx] = bg
    scene = build_scene(s, active, options, level_radius_px, edges=edges, near=parts,
                        max_coc=max(hi, -lo))
    return img, s, scene


def _writable(a: np.ndarray, dtype: type, ndim: int) -> bool:
    """Whether ``a`` can be written in place as a ``dtype`` array of ``ndim`` dimensions whose ``reshape(-1)``
    is a view (C-contiguous)."""
    return a.dtype == dtype and a.ndim == ndim and a.flags.c_contiguous and a.flags.writeable


def cap_coc(signed_coc: np.ndarray, largest: float | None = None) -> np.ndarray:
    """Compress CoC radii beyond twice the image diagonal (order kept): their light covers the frame uniformly.

    Every aperture (a triangle at worst) contains the disc of half its circumradius, so a
    source whose radius exceeds twice the diagonal lights every pixel of the frame equally:
    a larger radius only spreads less of its light inside the frame. Without the cap a CoC
    far beyond the image (K = 1e5 on a small image) leaves each pixel a coverage below the
    float32 noise floor of the compositing (1e-4), and the render would fall back to the
    unblurred input; the ray tracer's march would take O(K) steps per ray. Beyond the cap
    ``c`` a radius ``r`` becomes ``c + log1p(r - c)`` (still ordered, so layers keep their
    depth order; not idempotent, so the entry points apply it once). Renders whose CoC stays
    within the cap are unchanged. ``largest``: ``max(signed_coc.max(), -signed_coc.min())`` when the caller has it
    (None: found here).
    """
    h, w = signed_coc.shape
    cap = np.float32(2.0 * math.hypot(h, w) + 2.0)
    if signed_coc.size == 0:
        return signed_coc
    if largest is None:
        largest = max(float(signed_coc.max()), -float(signed_coc.min()))
    if largest <= cap:
        return signed_coc  # the normal case: no copy
    r = np.abs(signed_coc)
    big = r > cap
    out = signed_coc.copy()
    out[big] = np.sign(signed_coc[big]) * (cap + np.log1p(r[big] - cap))
    return out.astype(np.float32)


def tile_max(values: np.ndarray, tile: int) -> np.ndarray:
    """Maximum of ``values`` over each ``tile`` x ``tile`` cell of the grid (partial cells at the far edges, as if
    padded with zeros)."""
    return tile_reduce(values, tile, 0, np.maximum)


def tile_reduce(values: np.ndarray, tile: int, fill: object, op: np.ufunc) -> np.ndarray:
    """``op`` (``np.maximum``, ``np.minimum``) of ``values`` over each ``tile`` x ``tile`` cell of the grid, the
    partial cells at the far edges padded with ``fill``: the values of padding the map and reducing axes (1, 3)
    of its ``(th, tile, tw, tile)`` view, without the padded copy of the map. The rows of each cell are reduced
    first (a reduction over the middle axis of ``(th, tile, W)``, 4x faster than over two strided axes), then
    the columns of that ``th x W`` array."""
    h, w = values.shape
    th, tw = -(-h // tile), -(-w // tile)
    full = h // tile
    rows = np.full((th, tw * tile), fill, values.dtype)
    op.reduce(values[: full * tile].reshape(full, tile, w), axis=1, out=rows[:full, :w])
    if full < th:  # the partial cells of the last row of the grid
        last = np.full((tile, w), fill, values.dtype)
        last[: h - full * tile] = values[full * tile :]
        op.reduce(last, axis=0, out=rows[full, :w])
    return op.reduce(rows.reshape(th, tw, tile), axis=2)


def tile_reduce_in_parts(values: np.ndarray, tile: int, fill: object, op: np.ufunc) -> np.ndarray:
    """:func:`tile_reduce`, whole tile rows a part, the parts on the CPU's cores (``edge_estimate.in_row_parts``):
    the same values."""
    h, w = values.shape
    out = np.empty((-(-h // tile), -(-w // tile)), values.dtype)

    def part(a: int, b: int) -> None:
        if b > a:
            out[a // tile : -(-b // tile)] = tile_reduce(values[a:b], tile, fill, op)

    in_row_parts(h, w, part, align=tile)
    return out


def grid_to_pixels(grid: np.ndarray, tile: int, shape: tuple[int, int]) -> np.ndarray:
    """Expand a per-tile grid to pixels (cropped to ``shape``)."""
    return np.repeat(np.repeat(grid, tile, 0), tile, 1)[: shape[0], : shape[1]]


def copy_tiles(radius: np.ndarray, tile: int) -> np.ndarray:
    """Boolean tile grid: True where the tile can be copied from the input.

    A tile is copied when no pixel whose CoC reaches into it has a radius of
    half a pixel or more (its own pixels included).
    """
    return copy_tiles_of(tile_max(radius, tile), tile)


def radius_tile_max(signed_coc: np.ndarray, soft: SoftEdges | None, tile: int) -> np.ndarray:
    """``tile_max(soft_radius(signed_coc, soft), tile)``, a band of whole tile rows at a time, the rows' parts on
    the CPU's cores (``edge_estimate.in_row_parts``): no frame-sized radius map. The same values."""
    h, w = signed_coc.shape
    out = np.empty((-(-h // tile), -(-w // tile)), np.abs(signed_coc[:0, :0]).dtype)
    index, radius = None, None
    if soft is not None and len(soft):
        index, radius = soft.index, np.maximum(np.abs(soft.near_coc), np.abs(soft.far_coc))
    rows = max(1, _memory.BAND_PX // max(1, w) // tile) * tile

    def part(r0: int, r1: int) -> None:
        for y0 in range(r0, r1, rows):
            y1 = min(r1, y0 + rows)
            r = np.abs(signed_coc[y0:y1])
            if index is not None:  # the split pixels of these rows (their indices are sorted)
                a, b = np.searchsorted(index, (y0 * w, y1 * w))
                r.reshape(-1)[index[a:b] - y0 * w] = radius[a:b]
            out[y0 // tile : -(-y1 // tile)] = tile_max(r, tile)

    in_row_parts(h, w, part, align=tile)
    return out


def copy_tiles_of(tmax: np.ndarray, tile: int) -> np.ndarray:
    """:func:`copy_tiles` of the radius map whose :func:`tile_max` is ``tmax``."""
    blurred = tmax >= 0.5
    needed = np.zeros_like(blurred)
    if blurred.any():
        reach = np.ceil((tmax + 1.0) / tile).astype(np.int64)
        for k in np.unique(reach[blurred]):
            needed |= dilate(blurred & (reach == k), int(k))
    return ~needed


def layer_edges(signed_coc: np.ndarray, options: LayerOptions) -> np.ndarray:
    """Edges (ascending, in CoC px) of the depth layers for the given signed CoC values.

    Layers exist to resolve occlusion; on a continuous surface every layer edge
    is a seam (two one-sided blurs composited instead of one). So edges go
    (1) around the focus, ``s = -0.5`` and ``s = +0.5``: the in-focus layer is
    its own, so nothing blurred behind it can halo over it;
    (2) into the gaps of the CoC histogram, where the depth jumps; and
    (3) where a gap-free run is still wider than ``max_layer_px``, at even
    spacing, so an in-focus subject and a far background on one continuous
    range still get separate layers (no halo). At most ``max_layers`` layers:
    the narrowest gaps are dropped first, and what the budget leaves for (3) is
    shared between the wide runs in proportion to their width.
    """
    signed_coc = np.asarray(signed_coc, np.float32).ravel()
    lo, hi = float(signed_coc.min()), float(signed_coc.max())
    return _layer_edges_of([lambda: (signed_coc,)], lo, hi, options)


Groups = list[Callable[[], Iterable[np.ndarray]]]
"""Values in groups of pieces: each group a callable yielding its float32 pieces (again at each call); the groups
are read on the CPU's cores, one a thread (:func:`_active_values`)."""


def _layer_edges_of(groups: Groups, lo: float, hi: float, options: LayerOptions) -> np.ndarray:
    """:func:`layer_edges` of the float32 values the ``groups`` yield (:data:`Groups`), whose smallest and largest
    are ``lo`` and ``hi``: the values need not be gathered into one array."""
    if hi - lo < options.min_layer_px:
        return np.array([lo - 0.5, hi + 0.5])
    bin_px = _HISTOGRAM_BIN_PX
    n_bins = int(math.ceil((hi - lo) / bin_px)) + 1
    hists = on_threads([functools.partial(lambda g: _histogram(g(), lo, bin_px, n_bins), g) for g in groups])
    hist = np.zeros(max(h.size for h in hists), np.int64)  # a group's may be longer (float32 rounding of the top)
    for h in hists:
        hist[: h.size] += h
    empty = hist == 0
    # runs of empty bins: candidate cuts at their centres, ranked by width
    change = np.flatnonzero(np.diff(np.concatenate([[0], empty.astype(np.int8), [0]])))
    runs = change.reshape(-1, 2)
    gaps = [(lo + bin_px * (a + b) / 2.0, (b - a) * bin_px) for a, b in runs]
    gaps.sort(key=lambda g: -g[1])
    ranked = [c for c in (-0.5, 0.5) if lo < c < hi] + [pos for pos, _ in gaps]  # focus cuts first
    cuts = set(ranked[: max(0, options.max_layers - 1)])
    edges = np.array(sorted({lo - 0.5, hi + 0.5} | cuts))
    # split the runs that are still too wide, sharing what is left of the layer budget
    # between them in proportion to their width (the focus and gap cuts always stay)
    widths = np.diff(edges)
    want = np.maximum(1, np.ceil(widths / options.max_layer_px)).astype(int)
    spare = options.max_layers - len(widths)
    if want.sum() - len(widths) > spare:
        extra = want - 1
        share = np.floor(extra * max(spare, 0) / max(extra.sum(), 1)).astype(int)
        want = 1 + share
    out = [edges[0]]
    for a, b, n in zip(edges[:-1], edges[1:], want):
        out.extend(a + (b - a) * np.arange(1, n + 1) / n)
    return np.array(out)


def _histogram(parts: Iterable[np.ndarray], lo: float, bin_px: float, n_bins: int) -> np.ndarray:
    """``np.bincount(((values - lo) / bin_px).astype(np.int64), minlength=n_bins)`` of the float32 ``values``
    that are the 1-D ``parts`` one after the other, a band at a time into one float32 buffer: the same float32
    arithmetic, the same counts."""
    hist = np.zeros(n_bins, np.int64)
    band = _memory.BAND_PX
    buf = np.empty(band, np.float32)
    for values in parts:
        for i in range(0, values.size, band):
            part = values[i : i + band]
            b = buf[: part.size]
            np.subtract(part, lo, out=b)
            np.divide(b, bin_px, out=b)
            c = np.bincount(b.astype(np.int64), minlength=n_bins)
            if c.size > hist.size:  # a bin past n_bins (float32 rounding of the top value): bincount grows, so do we
                hist = np.concatenate([hist, np.zeros(c.size - hist.size, np.int64)])
            hist[: c.size] += c
    return hist


def _active_values(s: np.ndarray, active: np.ndarray, extra: np.ndarray | None = None
                   ) -> tuple[Groups, float, float, float, float]:
    """The values ``np.concatenate([s[active], extra])`` in pieces, without gathering them (two frame-sized
    copies at 12 MP): ``(groups, lo, hi, lo32, hi32)``. The :data:`Groups` yield them as float32, the rows' parts
    (:func:`~bokehray.edge_estimate.row_parts`) one a group, a band of rows of ``s[active]`` at a time, then
    ``extra`` (in the last group); ``lo`` and ``hi`` are the smallest and largest value as the concatenation holds
    them, ``lo32`` and ``hi32`` as float32 holds them (:func:`layer_edges` casts to float32; rounding is monotonic,
    so the float32 extremes are the extremes rounded). The extremes are found on the CPU's cores."""
    extra = np.zeros(0, np.float32) if extra is None else extra
    h, w = s.shape
    cuts = row_parts(h, w)

    def native(r0: int, r1: int, last: bool) -> Iterator[np.ndarray]:
        for y0, y1 in _memory.row_bands(r1 - r0, w):
            yield s[r0 + y0 : r0 + y1][active[r0 + y0 : r0 + y1]]
        if last:
            yield extra

    def group(r0: int, r1: int, last: bool) -> Callable[[], Iterator[np.ndarray]]:
        return lambda: (np.asarray(v, np.float32) for v in native(r0, r1, last))

    def extremes(r0: int, r1: int, last: bool) -> list[tuple[float, float]]:
        return [(float(v.min()), float(v.max())) for v in native(r0, r1, last) if v.size]

    parts = [(r0, r1, k == len(cuts) - 1) for k, (r0, r1) in enumerate(cuts)]
    found = [e for es in on_threads([functools.partial(extremes, *p) for p in parts]) for e in es]
    lows, highs = zip(*found)  # empty: as min() of none
    lo, hi = min(lows), max(highs)
    return [group(*p) for p in parts], lo, hi, float(np.float32(lo)), float(np.float32(hi))


def pyramid_levels(max_radius: float, level_radius_px: float) -> int:
    """Levels of the radius pyramid a layer of CoC radius up to ``max_radius`` needs (``bk.MAX_LEVELS`` at most)."""
    n = 1
    while max_radius > level_radius_px * (1 << (n - 1)) and n < bk.MAX_LEVELS:
        n += 1
    return n


def lowest_level(layer: LayerRecord, level_radius_px: float) -> int:
    """The lowest pyramid level above 0 any source of ``layer`` is scattered on (0: level 1 may hold some).

    Every source's signed CoC lies in the layer's range ``[s_lo, s_hi]`` (its own pixels, and the fill clamped
    to it), so its radius is at least the range's end nearer to 0; taken a hair smaller, so that a float32
    radius rounded onto a level's boundary stays above it."""
    if layer.s_lo <= 0.0 <= layer.s_hi:
        return 0
    r_min = min(abs(layer.s_lo), abs(layer.s_hi)) * (1.0 - 1e-6)
    return pyramid_levels(r_min, level_radius_px) - 1


def pull_levels(fill_reach: float) -> int:
    """Levels of the pull-push pyramid that fills a layer hidden up to ``fill_reach`` px deep."""
    return max(1, min(MAX_PULL_LEVELS, int(math.ceil(math.log2(FILL_GATE_SLOPE * fill_reach + 2.0))) + 1))


@dataclass(frozen=True, slots=True)
class LayerRecord:
    """One depth layer of a :class:`LayeredScene`.

    ``bbox`` (y0, y1, x0, x1) holds its tiles, padded by its largest CoC, its pyramid's spread and, when
    filled, the fill's reach (:func:`light_pad`): every source of the layer and all of its light lie inside.
    ``fill_reach``: the largest CoC of everything nearer (how far behind it a nearer blur can reveal); 0 when
    not filled. ``support``: the tiles (of ``tile_px``, on the scene's grid) within that pad of the layer's
    own tiles, the only ones its sources and light reach (a layer cut at a depth jump is often a thin
    population spread over a frame-sized box); None: everywhere (also when ``tile_px`` is not a power of two,
    as the kernels find tiles by shifts, or below ``SUPPORT_MIN_TILE_PX``, where a mask per layer costs more
    than it saves). ``origin``: the scene position of the frame ``bbox`` is given in (a tile's window; (0, 0)
    for the whole scene). ``pixels``: how many of the scene's pixels are the layer's own.
    """

    index: int
    s_lo: float
    s_hi: float
    bbox: tuple[int, int, int, int]
    max_radius: float
    fill_reach: float
    support: np.ndarray | None = dataclasses.field(default=None, compare=False, repr=False)
    tile_px: int = 1
    origin: tuple[int, int] = (0, 0)
    pixels: int = 0  # its own pixels in the whole scene

    @property
    def filled(self) -> bool:
        return self.fill_reach >= FILL_MIN_REACH_PX

    def moved(self, bbox: tuple[int, int, int, int], origin: tuple[int, int] | None = None) -> LayerRecord:
        """The same layer on another box (a tile's window at ``origin`` in the scene, or the whole image)."""
        return dataclasses.replace(self, bbox=bbox, origin=self.origin if origin is None else origin)


@dataclass(frozen=True, slots=True)
class LayerSupport:
    """A layer's support on the device, as the kernels read it (``bokehray_kernels.support``): the tile mask, the
    tile side, and the scene position of the layer box's origin."""

    mask: wp.array
    shift: int  # tiles of 2^shift px
    oy: int
    ox: int

    @classmethod
    def everywhere(cls, device: str) -> LayerSupport:
        return cls(wp.ones((1, 1), dtype=wp.uint8, device=device), 30, 0, 0)  # one tile larger than any image

    @classmethod
    def of(cls, layer: LayerRecord, device: str) -> LayerSupport:
        if layer.support is None:
            return cls.everywhere(device)
        y0, _, x0, _ = layer.bbox
        return cls(wp.array(layer.support.astype(np.uint8), dtype=wp.uint8, device=device),
                   layer.tile_px.bit_length() - 1, layer.origin[0] + y0, layer.origin[1] + x0)

    @classmethod
    def within(cls, layer: LayerRecord, box: tuple[int, int, int, int], device: str) -> LayerSupport:
        """The layer's support cut to the tiles that meet ``box`` (y0, y1, x0, x1 in the coordinates of the layer's
        ``bbox``): where the preview keeps its light (the frame without its clamped border, a tile's core); the
        support "everywhere" where the layer has none."""
        if layer.support is None:
            return cls.everywhere(device)
        t, (oy, ox) = layer.tile_px, layer.origin
        y0, y1, x0, x1 = box
        mask = np.zeros(layer.support.shape, np.uint8)
        rows = slice((y0 + oy) // t, -(-(y1 + oy) // t))
        cols = slice((x0 + ox) // t, -(-(x1 + ox) // t))
        mask[rows, cols] = layer.support[rows, cols]
        by0, _, bx0, _ = layer.bbox
        return cls(wp.array(mask, dtype=wp.uint8, device=device), t.bit_length() - 1, oy + by0, ox + bx0)

    def down(self, rows: int) -> LayerSupport:
        """The same support for the box's rows from ``rows`` on (a view of the box starting there)."""
        return dataclasses.replace(self, oy=self.oy + rows)

    def struct(self) -> bk.Support:
        """The support as the kernels take it."""
        s = bk.Support()
        s.mask, s.shift, s.oy, s.ox = self.mask, self.shift, self.oy, self.ox
        return s


@dataclass(frozen=True, slots=True, eq=False)
class LayeredScene:
    """The photo cut into depth layers: per-pixel layer ids (-1 = copied, in no layer), the layer edges in CoC
    px, the largest CoC radius of the layered pixels, and the present layers far to near (ids grow towards the
    camera). ``level_radius_px`` is the radius-pyramid step the boxes were padded for (None: no pyramid). ``near``:
the near parts of split pixels (:func:`split_scene`), sources of the layers they fall in."""

    ids: np.ndarray
    edges: np.ndarray
    max_coc: float
    layers: tuple[LayerRecord, ...]
    level_radius_px: float | None
    near: NearParts = dataclasses.field(default_factory=NearParts.empty)

    @property
    def n_slots(self) -> int:
        """One past the largest layer index (the size of per-layer counters)."""
        return max(lyr.index for lyr in self.layers) + 1


def build_scene(signed_coc: np.ndarray, active: np.ndarray, options: LayerOptions,
                level_radius_px: float | None = None, *, edges: np.ndarray | None = None,
                near: NearParts | None = None, max_coc: float | None = None) -> LayeredScene:
    """Cut the active pixels into depth layers.

    Each record holds the layer's CoC range, its bounding box (its tiles, padded by its largest CoC, by the
    pyramid's spread when scattered with ``level_radius_px``, and by the fill's reach when filled) and the reach
    of everything nearer. ``edges``, ``near`` and ``max_coc`` come from :func:`split_scene` (the near parts of
    split pixels: they count among their layers' pixels and tiles); by default the active pixels' own.
    """
    h, w = signed_coc.shape
    if edges is None:  # the active pixels' own, read in place band by band (layer_edges of signed_coc[active])
        values, lo, hi, lo32, hi32 = _active_values(signed_coc, active)
        max_coc = max(hi, -lo)
        edges = _layer_edges_of(values, lo32, hi32, options)
    n_slices = len(edges) - 1
    sid, counts = _layer_ids(signed_coc, active, float32_edges(edges), n_slices)

    # Per-layer extents on the tile grid (host side, on small arrays): a layer's
    # bounding box is the union of the tiles holding any of its pixels.
    t = options.tile_px
    tile_lo = np.minimum(tile_reduce_in_parts(sid.view(np.uint32), t, np.uint32(0xFFFFFFFF), np.minimum),
                         n_slices)  # -1 (no layer, also the padding) as the largest
    tile_hi = tile_reduce_in_parts(sid, t, -1, np.maximum)
    near_tiles = None
    if near is not None and len(near):
        counts = counts + np.bincount(near.layer, minlength=n_slices)
        near_tiles = (near.layer, near.y // t, near.x // t)
    present = counts > 0
    # CoC reach of everything nearer than each layer: suffix maximum of the layers' radius bounds
    max_r_slice = np.minimum(np.maximum(np.abs(edges[:-1]), np.abs(edges[1:])), max_coc)
    nearer_reach = np.zeros(n_slices)
    run = 0.0
    for i in range(n_slices - 1, -1, -1):
        nearer_reach[i] = run
        if present[i]:
            run = max(run, max_r_slice[i])
    layers = []
    for i in np.flatnonzero(present):
        own = (tile_lo <= i) & (tile_hi >= i)  # the tiles that may hold its pixels (a superset of those that do)
        if near_tiles is not None:
            mine = near_tiles[0] == i
            own[near_tiles[1][mine], near_tiles[2][mine]] = True  # and its near parts of split pixels
        ty, tx = np.nonzero(own)
        reach = float(nearer_reach[i]) if options.fill else 0.0
        pad = light_pad(float(max_r_slice[i]), reach, level_radius_px)
        bbox = (max(0, ty.min() * t - pad), min(h, (ty.max() + 1) * t + pad),
                max(0, tx.min() * t - pad), min(w, (tx.max() + 1) * t + pad))
        support = dilate(own, -(-pad // t)) if t >= SUPPORT_MIN_TILE_PX and t & (t - 1) == 0 else None
        layers.append(LayerRecord(int(i), float(edges[i]), float(edges[i + 1]), bbox, float(max_r_slice[i]), reach,
                                  support, t, pixels=int(counts[i])))
    return LayeredScene(sid, edges, max_coc, tuple(layers), level_radius_px,
                        near if near is not None else NearParts.empty())


def _layer_ids(signed_coc: np.ndarray, active: np.ndarray, e32: np.ndarray, n_slices: int
               ) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel layer ids (int32; -1 where not ``active``) and the active pixels' count per layer, in one pass
    over the map a band of rows at a time: the layer of ``s`` is ``searchsorted(e32, s, "right") - 1`` clipped to
    ``[0, n_slices - 1]``. Each band's search result (int64: the id plus one, 0 for an inactive pixel) is counted
    as it is (``bincount`` takes int64 without a conversion) and cast into the ids; no frame-sized int64 or mask
    temporary. The rows' parts run on the CPU's cores (``edge_estimate.in_row_parts``)."""
    h, w = signed_coc.shape
    sid = np.empty((h, w), np.int32)

    def part(r0: int, r1: int) -> np.ndarray:  # the rows [r0, r1): their ids, and their counts
        counts = np.zeros(n_slices + 1, np.int64)
        for y0, y1 in _memory.row_bands(r1 - r0, w):
            y0, y1 = y0 + r0, y1 + r0
            k = np.searchsorted(e32, signed_coc[y0:y1], side="right")
            np.clip(k, 1, n_slices, out=k)
            np.multiply(k, active[y0:y1], out=k)
            counts += np.bincount(k.reshape(-1), minlength=n_slices + 1)
            np.subtract(k, 1, out=sid[y0:y1], casting="unsafe")
        return counts

    return sid, sum(in_row_parts(h, w, part))[1:]


def float32_edges(edges: np.ndarray) -> np.ndarray:
    """``edges`` (float64) as the smallest float32 values at or above them: a float32 CoC is at or above an edge
    exactly when it is at or above its float32 version, so searching those needs no float64 copy of the map."""
    e32 = edges.astype(np.float32)
    low = e32.astype(np.float64) < edges
    e32[low] = np.nextafter(e32[low], np.float32(np.inf))
    return e32


SUPPORT_MIN_TILE_PX = 8
"""The finest tile grid layers get a support on: on a grid of 1 px a layer's mask is as large as the frame (5x
the planning time, 1 B/px a layer)."""


def light_pad(max_radius: float, fill_reach: float, level_radius_px: float | None) -> int:
    """How far [px] a layer's sources and light reach beyond its own pixels: the fill's reach (when filled),
    its largest CoC plus two pixels, and the radius pyramid's spread (``level_radius_px``; None: no pyramid)."""
    coarse = 0
    if level_radius_px is not None:
        coarse = COARSE_SCATTER_CELLS << (pyramid_levels(max_radius, level_radius_px) - 1)
    return _fill_pad(fill_reach) + int(math.ceil(max_radius)) + 2 + coarse


def _fill_pad(reach: float) -> int:
    """How far the fill extends a layer beyond its own pixels (the gate ``sqrt(2) r + 1`` rounded up, plus one)."""
    return int(math.ceil(FILL_GATE_SLOPE * reach)) + 2 if reach >= FILL_MIN_REACH_PX else 0


# --------------------------------------------------------------------------- halos


def fill_halo(layer: LayerRecord) -> tuple[int, int]:
    """(halo, alignment) of a layer's fill: a filled value depends on pull-push cells up to ``3 * 2^n`` px away
    (``n`` pull levels; each push reads the coarser level's neighbours) and a window's cut cells reach ``2^n`` px
    in; the pyramid's cells are ``2^n`` px. (0, 1) for an unfilled layer."""
    if not layer.filled:
        return 0, 1
    n_pp = pull_levels(layer.fill_reach)
    return 4 * (1 << n_pp) + 4, 1 << n_pp


def scatter_halo(layer: LayerRecord, level_radius_px: float) -> tuple[int, int]:
    """(halo, alignment) of a scattered layer: how far a pixel depends on the layer's sources (its largest radius
    plus the coarsest pyramid level's spread and its cut cells), the fill's halo on top, and the cell every
    pyramid of the layer is anchored to."""
    n_lv = pyramid_levels(layer.max_radius, level_radius_px)
    cell = 1 << (n_lv - 1)
    halo = int(math.ceil(layer.max_radius)) + 2 + (COARSE_SCATTER_CELLS + CUT_CELLS) * cell
    f_halo, f_align = fill_halo(layer)
    return halo + f_halo, max(cell, f_align)


# --------------------------------------------------------------------------- sources


@dataclass(slots=True)
class LayerSources:
    """The scene's arrays on the device for one window (the whole image or a tile's): what every layer's sources
    are built from, plus the counter of filled sources per layer (read once per render)."""

    image: wp.array
    signed_coc: wp.array
    ids: wp.array
    filled: wp.array
    device: str
    near: tuple[wp.array, ...] | None = None  # the near parts in the window (y, x, value, CoC, layer); None: none

    @classmethod
    def upload(cls, image: np.ndarray, signed_coc: np.ndarray, ids: np.ndarray, n_slots: int,
               device: str, near: NearParts | None = None) -> LayerSources:
        """``near``: the near parts of split pixels in the window's coordinates (:meth:`NearParts.window`)."""
        parts = None
        if near is not None and len(near):
            parts = (wp.array(near.y, dtype=wp.int32, device=device), wp.array(near.x, dtype=wp.int32, device=device),
                     wp.array(np.ascontiguousarray(near.value, np.float32), dtype=wp.vec4, device=device),
                     wp.array(np.ascontiguousarray(near.coc, np.float32), dtype=float, device=device),
                     wp.array(near.layer, dtype=wp.int32, device=device))
        copy = not wp.get_device(device).is_cpu  # on the CPU the kernels read the (contiguous) arrays in place
        return cls(
            wp.array(np.ascontiguousarray(image[..., :3], np.float32), dtype=wp.vec3, device=device, copy=copy),
            wp.array(np.ascontiguousarray(signed_coc, np.float32), dtype=float, device=device, copy=copy),
            wp.array(np.ascontiguousarray(ids, np.int32), dtype=wp.int32, device=device, copy=copy),
            wp.zeros(n_slots, dtype=wp.int32, device=device),
            device,
            parts,
        )

    def filled_count(self) -> int:
        return int(self.filled.numpy().sum())


def build_layer_sources(layer: LayerRecord, arrays: LayerSources, zeros=wp.zeros,
                        fill_gate=None) -> tuple[wp.array, wp.array]:
    """One layer's sources on its bounding box: (premultiplied RGB, coverage) and signed CoC.

    The layer's own pixels, the near parts of split pixels that fall in it (``arrays.near``), plus (when the
    layer is filled) the pull-push fill of the region nearer layers hide, at the layer's density; the number of
    filled sources is added to ``arrays.filled[layer.index]``. ``zeros(shape, dtype, device)`` allocates the two
    (zeroed) arrays: the kernels write the sources only, so a lazily zeroed array (``bokehray.levels.buffers.
    lazy_zeros``) takes pages only where sources lie. The fill runs inside ``fill_gate`` (a context manager, None:
    none; the preview's lock, one fill at a time over its workers); the layer's own sources are written before it.
    """
    device = arrays.device
    y0, y1, x0, x1 = layer.bbox
    h, w = y1 - y0, x1 - x0
    src = zeros((h, w), wp.vec4, device)  # zeroed: the kernels write the layer's sources only
    coc = zeros((h, w), float, device)
    none = wp.zeros((1, 1), dtype=float, device=device)  # no level 0: the pyramid starts at level 1 (below)
    level0 = bk.PullPushLevel()
    level0.total, level0.weight, level0.known = wp.zeros((1, 1), dtype=wp.vec4, device=device), none, none
    n, span = row_span(device, w)
    wp.launch(
        bk.layer_sources_kernel,
        dim=(h, n),
        inputs=[span, arrays.image, arrays.signed_coc, arrays.ids, layer.index, x0, y0, 0],
        outputs=[src, coc, level0],
        device=device,
    )
    if arrays.near is not None:  # the near parts of split pixels that fall in this layer
        wp.launch(bk.near_sources_kernel, dim=arrays.near[0].shape[0], inputs=[*arrays.near, layer.index, x0, y0],
                  outputs=[src, coc], device=device)
    if layer.filled:
        with fill_gate or contextlib.nullcontext():
            _fill(layer, arrays, src, coc)
    return src, coc


def _fill(layer: LayerRecord, arrays: LayerSources, src: wp.array, coc: wp.array) -> None:
    """Add the pull-push fill of the region nearer layers hide to a layer's sources (``src``, ``coc``, in place).

    Level 0 of the pyramid is never stored (a third of the fill's bytes): level 1 is pulled straight from the
    photo (``layer_pull_kernel``) and a hidden pixel's level-0 sums are zero (``fill_sources_kernel``). Each
    level is freed once the push no longer reads it: pushing level ``lv`` reads level ``lv + 1`` only, and the
    fill reads level 1 only. The values are those of the whole pyramid, bit for bit.
    """
    device = arrays.device
    y0, y1, x0, x1 = layer.bbox
    h, w = y1 - y0, x1 - x0
    rows = wp.get_device(device).is_cpu  # a row a thread on a CPU (its per-thread call), a texel on a GPU
    totals, weights, knowns = [], [], []
    for lv in range(1, pull_levels(layer.fill_reach) + 1):
        ch, cw = (h + (1 << lv) - 1) >> lv, (w + (1 << lv) - 1) >> lv
        totals.append(wp.empty((ch, cw), dtype=wp.vec4, device=device))
        weights.append(wp.empty((ch, cw), dtype=float, device=device))
        knowns.append(wp.empty((ch, cw), dtype=float, device=device))
        if lv == 1:
            n, span = row_span(device, cw)
            wp.launch(bk.layer_pull_kernel, dim=(ch, n),
                      inputs=[span, arrays.image, arrays.signed_coc, arrays.ids, layer.index, x0, y0, h, w],
                      outputs=[_pull_push(totals, weights, knowns, -1)], device=device)
        else:
            wp.launch(bk.pull_kernel, dim=(ch, cw), inputs=[_pull_push(totals, weights, knowns, -2)],
                      outputs=[_pull_push(totals, weights, knowns, -1)], device=device)
    top = len(totals) - 1  # list index i holds level i + 1
    for i in range(top, -1, -1):  # down to level 1: the fill pushes the level-0 texels it needs
        c = min(i + 1, top)  # the top level has no coarser level (flag 1): it passes itself
        n, span = row_span(device, totals[i].shape[1])
        wp.launch(bk.push_kernel, dim=(totals[i].shape[0], n),
                  inputs=[span, _pull_push(totals, weights, knowns, c), int(i == top)],
                  outputs=[_pull_push(totals, weights, knowns, i)], device=device)
        if i < top:  # nothing reads the coarser level any more
            totals[i + 1] = weights[i + 1] = knowns[i + 1] = None
    level1 = _pull_push(totals, weights, knowns, 0)
    del totals, weights, knowns
    dist = wp.empty((h, w), dtype=float, device=device)
    wp.launch(bk.row_distance_kernel, dim=h, inputs=[arrays.ids, layer.index, x0, y0, w], outputs=[dist],
              device=device)
    band = 64 if rows else 1  # a band of columns a thread on a CPU
    wp.launch(bk.column_distance_kernel, dim=(w + band - 1) // band, inputs=[dist, h, band], device=device)
    n, span = row_span(device, w)
    wp.launch(
        bk.fill_sources_kernel,
        dim=(h, n),
        inputs=[span, arrays.ids, layer.index, x0, y0, level1, dist, arrays.signed_coc, layer.s_lo, layer.s_hi],
        outputs=[src, coc, arrays.filled],
        device=device,
    )


def _pull_push(totals: list, weights: list, knowns: list, level: int) -> bk.PullPushLevel:
    """Level ``level`` of a pull-push pyramid as the kernels take it."""
    lv = bk.PullPushLevel()
    lv.total, lv.weight, lv.known = totals[level], weights[level], knowns[level]
    return lv
