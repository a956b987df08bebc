"""``render --refine``: the shipped refiner applied where depth errors show, blended into the classical render.

First (with a ``rerender`` callback, which the pipeline always passes) the colour-guided depth correction
(``bokehray_refiner.depthfix``) moves depth edges that sit off the photo's colour edges back onto them, and the classical
level renders again on the corrected map; the steps below then work on that render and that map.

Depth errors only change the image where a depth discontinuity meets a
non-trivial blur; elsewhere the classical render is already right. So the
image is cut into tiles, and a tile is refined only if a discontinuity whose
CoC jump exceeds ``min_jump_px`` lies within reach (the larger CoC radius at
that edge) of it. Each refined tile runs with a halo of context; its
correction (refined minus classical, in sRGB) is feathered to 0 across the
halo, so refined and untouched tiles meet without a seam. The correction is
also kept only within (the edge's CoC + a margin) of a depth edge, and only as
far as the confidence gate (``gate.py``) lets it through: where the depth edge
sits on a colour edge of the photo, or over a clipped light, the classical render
is kept. Every other pixel is bit-identical to the classical render; tiles the
gate closes entirely are not run through the network.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

from bokehray.colour import linear_to_srgb, srgb_to_linear
from bokehray.errors import InputError
from bokehray.lens import BlurParams
from bokehray_refiner.depthfix import DepthFixOptions, correction_steps
from bokehray_refiner.pisa import PisaMaskOptions

from .edges import EdgeNet, Placement, load_edge_net, place_edges
from .gate import GateOptions, channel_max, edge_gate, refine_gate
from .masks import PisaMaskProvider
from .model import BokehRefiner, RefinerConfig
from .saved import load_saved
from .tiles import raised_cosine_ramp, refine_boxes

__all__ = ["DEFAULT_WEIGHTS", "RefineOptions", "RefineStats", "blend_weight", "correct_and_render",
           "corrected_disparity", "disagreement", "edge_band", "edge_reach", "fixed_share", "load_refiner",
           "map_found_wrong", "refine", "refine_boxes", "tiles_near", "tiles_to_refine"]

DEFAULT_WEIGHTS = Path(__file__).parent / "weights" / "refiner.safetensors"


@dataclass(frozen=True)
class RefineOptions:
    """Where and how to refine.

    Args:
        tile: tile side in pixels (a multiple of 8).
        halo: context around a tile in pixels (a multiple of 8); the correction fades out across it.
        min_jump_px: a depth edge matters if the CoC radius jumps by more than this across it.
        batch: tiles per forward pass.
        full_frame_px: when the tiles with their halos would cover more than the frame, and the frame has at
            most this many pixels, one pass over the whole frame replaces them (same blend weights).
        band_margin_px, band_feather_px: the correction is kept only within (the edge's CoC + margin) of a
            depth edge, fading out over the feather: farther away a depth error cannot change the image.
        gate: the confidence gate (``GateOptions(enabled=False)`` lets the whole band through).
        depthfix: the colour-guided depth correction run first (``bokehray_refiner.depthfix``); it needs a ``rerender``
            callback in :func:`refine` (the classical level again, on the corrected disparity).
        neural: False stops after the depth correction (the neural residual is not run).
        merge_tiles: neighbouring tiles to refine run as one box with one halo (:func:`refine_boxes`), blended
            with the same per-tile weights, instead of one pass per tile, each with its own halo.
        edges: after the depth correction, the learned edge placement (:mod:`.edges`, the shipped weights unless
            :func:`refine` is given ``edge_model``) moves the map's edges in the band, before the level renders
            again; only where the correction left the map disagreeing with the photo (``edge_min_disagreement``).
        edge_min_disagreement: the edge network runs only where, on the corrected map, the confidence gate's
            colour/depth agreement (:func:`.gate.refine_gate`, no highlight guard) is open over at least this mean share
            of the edge band: where the correction put nearly every depth edge on a colour edge (a map grown by
            1 px, say) little is left for it, and its moves there cost more than they gain (docs/design/edge-gate.md). 0: whenever the map was found wrong.
        edge_threshold: the edge network moves a pixel across an edge only where it gives the other side at least
            this probability.
        edge_passes: the edge network runs again on the map it made, up to this many passes in all (fewer where a
            pass moves nothing): a misplaced strip contaminates the sides' colour means it reads until it is moved
            (:func:`.edges.place_edges`; measured: research/refiner_edges/README.md).
        edge_colour_margin: and only where the pixel's colour is nearer the local mean colour of the side it joins,
            by this much (sRGB; :func:`.edges.colour_allows`); None: no colour veto.
        min_fixed_share: refine changes only a map the depth correction found wrong: where its local passes moved at
            least this share of the edge band's pixels. On any other map their few moves are dropped and neither
            network runs: the render is the classical level's on the given map, bit for bit (on the map shifted
            back, where the correction found the whole map misregistered: a shift moves every pixel and is not
            counted). A map whose edges sit on
            the photo's has nothing to repair, and there the correction's and the networks' few confident wrong
            moves cost more than they gain (docs/design/edge-gate.md). 0: every map. Where the correction does
            not run (off, or :func:`refine` without ``rerender``) there is no evidence either way: the residual
            network runs on every map, and the edge network only with this at 0 (and a ``rerender``).
        model: a local folder holding a one-step diffusion checkpoint in the diffusers layout (docs/refiner.md, "A
            one-step diffusion checkpoint"): it renders the whole frame with PISA attention instead of this pass
            (``bokehray_refiner.onestep.refine_one_step``), on the render's device; its weights must fit its
            config. None: the shipped CPU networks above.
    """

    tile: int = 64
    halo: int = 32
    min_jump_px: float = 1.0
    batch: int = 8
    full_frame_px: int = 4_000_000
    band_margin_px: float = 6.0
    band_feather_px: float = 4.0
    gate: GateOptions = GateOptions()
    depthfix: DepthFixOptions = DepthFixOptions()
    neural: bool = True
    merge_tiles: bool = True
    edges: bool = True
    edge_threshold: float = 0.7
    edge_passes: int = 1
    edge_colour_margin: float | None = None
    min_fixed_share: float = 0.01
    edge_min_disagreement: float = 0.04
    model: str | os.PathLike | None = None

    def __post_init__(self) -> None:
        if self.tile < 8 or self.tile % 8 or self.halo < 0 or self.halo % 8:
            raise InputError(f"refine tiles: tile and halo must be multiples of 8 (tile >= 8), got {self.tile}, "
                             f"{self.halo}")
        if not (np.isfinite(self.min_jump_px) and self.min_jump_px > 0) or self.batch < 1:
            raise InputError("refine: min_jump_px must be > 0 and batch >= 1")
        if not 0.5 <= self.edge_threshold <= 1.0:  # below 0.5 a pixel would be sure of both sides
            raise InputError(f"refine: edge_threshold must be in [0.5, 1], got {self.edge_threshold}")
        if isinstance(self.edge_passes, bool) or not isinstance(self.edge_passes, int | np.integer) \
                or not 1 <= self.edge_passes <= 16:
            raise InputError(f"refine: edge_passes must be an integer in [1, 16], got {self.edge_passes!r}")
        if self.edge_colour_margin is not None and not 0.0 <= self.edge_colour_margin < 2.0:
            raise InputError(f"refine: edge_colour_margin must be None or in [0, 2), got {self.edge_colour_margin}")
        if not 0.0 <= self.edge_min_disagreement <= 1.0:
            raise InputError(f"refine: edge_min_disagreement must be in [0, 1], got {self.edge_min_disagreement}")
        if not 0.0 <= self.min_fixed_share <= 1.0:
            raise InputError(f"refine: min_fixed_share must be in [0, 1], got {self.min_fixed_share}")


@dataclass
class RefineStats:
    """What ``--refine`` did."""

    tiles_total: int = 0
    tiles_refined: int = 0
    seconds: float = 0.0
    tiles_near_edges: int = 0  #: tiles within reach of a depth edge, before the gate
    band_pixels: int = 0  #: pixels of the edge band (where a depth error can change the image)
    gate_open: float = 0.0  #: mean gate over the band: the share of the correction let through
    depth_fixed_px: int = 0  #: pixels whose disparity the depth correction changed (then the level ran again)
    fixed_share: float | None = None  #: the share of the edge band the depth correction's local passes moved (a
    #: global shift not counted; None: the correction did not run)
    found_wrong: bool = True  #: at least ``min_fixed_share`` of it: else no network ran, only a shift was kept, and the
    #: tile, band and gate counts above stay 0
    edge_disagreement: float | None = None  #: the gate's mean over the band of the corrected map (None: not measured)
    edges_ran: bool = False  #: the edge network ran (``edge_min_disagreement``)
    depthfix_seconds: float = 0.0  #: the correction itself (with ``options.edges``, the edge network's too)
    rerender_seconds: float = 0.0  #: the classical level again, on the corrected disparity (its only render, when
    #: refine() was given no classical render: then not part of ``seconds``)
    gate_seconds: float = 0.0  #: the edge band and the confidence gate
    neural_seconds: float = 0.0  #: the network on the refined tiles and the blend
    disparity: np.ndarray | None = field(default=None, repr=False)  #: the corrected disparity (None: unchanged)

    @property
    def share_refined(self) -> float:
        return self.tiles_refined / self.tiles_total if self.tiles_total else 0.0

    def as_dict(self) -> dict:
        return {"tiles_total": self.tiles_total, "tiles_refined": self.tiles_refined,
                "share_refined": self.share_refined, "seconds": self.seconds,
                "tiles_near_edges": self.tiles_near_edges, "band_pixels": self.band_pixels,
                "gate_open": self.gate_open, "depth_fixed_px": self.depth_fixed_px,
                "fixed_share": self.fixed_share, "found_wrong": self.found_wrong,
                "edge_disagreement": self.edge_disagreement, "edges_ran": self.edges_ran,
                "depthfix_seconds": self.depthfix_seconds, "rerender_seconds": self.rerender_seconds,
                "gate_seconds": self.gate_seconds, "neural_seconds": self.neural_seconds}


def load_refiner(path: str | os.PathLike | None = None, device: str = "cpu") -> BokehRefiner:
    """Load refiner weights (default: the ones shipped in the package) written by ``bokehray train-refiner``.

    Loaded models are cached per file, modification time and device (inference only: do not train them).
    """
    return load_saved(path, DEFAULT_WEIGHTS, device, _build_refiner, what="refiner weights",
                      made_by="bokehray train-refiner", how_to_make="train them with `bokehray train-refiner`")


def _build_refiner(config: dict) -> BokehRefiner:
    return BokehRefiner(RefinerConfig(**config))


def edge_reach(coc: np.ndarray, min_jump_px: float) -> np.ndarray:
    """At each pixel on a depth edge that matters (CoC jump > ``min_jump_px``), the larger CoC radius; 0 elsewhere."""
    h, w = coc.shape
    reach = np.zeros((h, w), np.float32)
    for ax in (0, 1):
        a = np.take(coc, range(coc.shape[ax] - 1), axis=ax)
        b = np.take(coc, range(1, coc.shape[ax]), axis=ax)
        edge = np.abs(a - b) > min_jump_px
        r = np.where(edge, np.maximum(np.abs(a), np.abs(b)), 0.0)
        sl = [slice(None)] * 2
        sl[ax] = slice(0, -1)
        reach[tuple(sl)] = np.maximum(reach[tuple(sl)], r)
    return reach


def nearest_edge(reach: np.ndarray):
    """Distance to the nearest depth-edge pixel (``reach > 0``) and its indices (``scipy``'s exact EDT), or None
    without edges. Shared by the edge band and the gate, whose edge pixels are the same."""
    from scipy import ndimage

    edge = reach > 0
    if not edge.any():
        return None
    return ndimage.distance_transform_edt(~edge, return_indices=True)


def edge_band(reach: np.ndarray, margin_px: float, feather_px: float, nearest=None) -> np.ndarray:
    """Weight in [0, 1]: 1 within (its nearest edge's reach + ``margin_px``) of a depth edge, a linear
    fall-off over ``feather_px`` beyond. A depth error at an edge changes the image only that far.
    ``nearest``: :func:`nearest_edge` of ``reach`` when already computed."""
    nearest = nearest_edge(reach) if nearest is None else nearest
    if nearest is None:
        return np.zeros(reach.shape, np.float32)
    dist, (iy, ix) = nearest
    limit = reach[iy, ix] + margin_px
    return np.clip((limit + feather_px - dist) / feather_px, 0.0, 1.0).astype(np.float32)


def tiles_to_refine(coc: np.ndarray, tile: int, min_jump_px: float) -> np.ndarray:
    """Boolean ``(ceil(h/tile), ceil(w/tile))`` map of tiles within reach of a depth edge that matters."""
    return tiles_near(edge_reach(coc, min_jump_px), tile)


def tiles_near(reach: np.ndarray, tile: int) -> np.ndarray:
    h, w = reach.shape
    ty, tx = -(-h // tile), -(-w // tile)
    padded = np.zeros((ty * tile, tx * tile), np.float32)
    padded[:h, :w] = reach
    tile_reach = padded.reshape(ty, tile, tx, tile).max(axis=(1, 3))  # largest reach of an edge in each tile
    has_edge = tile_reach > 0
    need = has_edge.copy()
    # the window of tiles an edge can reach, never wider than the grid itself: a reach of K = 1e5 px on a small
    # image must not loop over (2 K / tile)^2 offsets (it took 125 s at 256 x 256)
    n = min(int(np.ceil(tile_reach.max() / tile)) + 1, max(ty, tx)) if has_edge.any() else 0
    for dy in range(-n, n + 1):  # a tile is needed if an edge's reach crosses the gap between the tiles
        for dx in range(-n, n + 1):
            gap = tile * np.hypot(max(abs(dy) - 1, 0), max(abs(dx) - 1, 0))
            src = has_edge & (tile_reach + 1 >= gap)
            ys, xs = np.nonzero(src)
            yy, xx = ys + dy, xs + dx
            ok = (yy >= 0) & (yy < ty) & (xx >= 0) & (xx < tx)
            need[yy[ok], xx[ok]] = True
    return need


@torch.no_grad()
def refine(
    image: np.ndarray,
    disparity: np.ndarray,
    blur: BlurParams,
    classical: np.ndarray | None,
    model: BokehRefiner | None = None,
    options: RefineOptions = RefineOptions(),
    rerender: Callable[[np.ndarray], np.ndarray] | None = None,
    edge_model: EdgeNet | None = None,
) -> tuple[np.ndarray, RefineStats]:
    """Refine a classical render where depth discontinuities meet blur.

    First, with ``rerender``, the colour-guided depth correction (``bokehray_refiner.depthfix``): where a depth edge
    sits off the photo's colour edge, the disparity there is corrected and ``rerender(corrected)`` renders
    the classical level again; the neural residual (behind its gate) then corrects that render, seeing the
    corrected disparity. Without ``rerender``, or where nothing is corrected, the render is the given one.
    With ``classical=None`` the level has not rendered yet: the correction runs first and ``rerender`` renders
    the level once, on the corrected map (or the given one where nothing moved), which is what ``render --refine``
    does: the level renders once, not twice. That render is then not counted in ``stats.seconds``.

    Args:
        image: the all-in-focus ``H x W x 3`` scene-linear image.
        disparity: ``H x W`` in [0, 1], the map the classical render used.
        blur: its ``K`` and ``d_f``.
        classical: the classical render (``H x W x 3``, scene-linear), or None (rendered here by ``rerender``).
        model: a loaded refiner (default: the shipped weights).
        rerender: ``disparity -> H x W x 3`` render of the same classical level (the pipeline passes its own).
        edge_model: a loaded edge network, with ``options.edges`` (default: the shipped weights).

    Returns:
        The refined render (scene-linear float32; untouched pixels are the classical values exactly) and stats.
    """
    t0 = time.perf_counter()
    first = classical is None  # the level's only render happens here: it is not part of the refine pass's time
    if first and rerender is None:
        raise InputError("refine: without a classical render it needs the rerender callback that renders the level")
    fix = _correct_depth(image, disparity, blur, classical, options, rerender, edge_model)
    classical, disparity = fix.classical, fix.disparity
    c = fix.correction
    stats = RefineStats(depth_fixed_px=fix.fixed_px, fixed_share=c.share, found_wrong=c.found_wrong,
                        edge_disagreement=c.disagreement, edges_ran=c.edges_ran, depthfix_seconds=fix.seconds,
                        rerender_seconds=fix.render_seconds, disparity=fix.fixed)
    render_time = fix.render_seconds if first else 0.0
    if not c.found_wrong:  # as far as the correction can tell the map is right: the level's render, untouched
        stats.tiles_total = -(-disparity.shape[0] // options.tile) * -(-disparity.shape[1] // options.tile)
        stats.seconds = time.perf_counter() - t0 - render_time
        return classical.astype(np.float32, copy=True), stats
    edge_field = c.edge_field
    if edge_field is None or not _same_map(edge_field.disparity, disparity):
        coc = blur.signed_coc(disparity).astype(np.float32)
        edge_field = _EdgeField(disparity, coc, edge_reach(coc, options.min_jump_px))
    coc, reach = edge_field.coc, edge_field.reach
    need = tiles_near(reach, options.tile)
    if not options.neural:
        need[:] = False
    else:
        model = model or load_refiner()
    stats.tiles_total, stats.tiles_near_edges = int(need.size), int(need.sum())
    t1 = time.perf_counter()
    band, focus_srgb = None, fix.focus_srgb
    if need.any():
        if focus_srgb is None:
            focus_srgb = linear_to_srgb(np.clip(image[..., :3], 0.0, 1.0))
        frame = _Frame(image, focus_srgb, disparity, classical, coc)
        band = _gated_band(frame, reach, need, options, stats, edge_field)
    stats.tiles_refined = int(need.sum())
    stats.gate_seconds = time.perf_counter() - t1
    if not need.any():
        stats.seconds = time.perf_counter() - t0 - render_time
        return classical.astype(np.float32, copy=True), stats
    t1 = time.perf_counter()
    out = _network_pass(model, frame, band, need, blur, options)
    stats.neural_seconds = time.perf_counter() - t1
    stats.seconds = time.perf_counter() - t0 - render_time
    return np.maximum(out, 0.0) if classical.min() >= 0 else out, stats


def correct_and_render(image: np.ndarray, disparity: np.ndarray, blur: BlurParams,
                       rerender: Callable[[np.ndarray], np.ndarray],
                       options: RefineOptions = RefineOptions(),
                       edge_model: EdgeNet | None = None) -> tuple[np.ndarray, np.ndarray]:
    """What the network of :func:`refine` is given: the level's render after the depth correction, and the map it
    used (the corrected one, or the given one where nothing moved). The training pairs are made by this."""
    fix = _correct_depth(image, disparity, blur, None, options, rerender, edge_model)
    return fix.classical, fix.disparity


@dataclass
class _DepthFix:
    """What the first stage hands on: the level's render on the (maybe corrected) map, and what it did."""

    classical: np.ndarray
    disparity: np.ndarray
    fixed: np.ndarray | None  # the corrected map where any pixel moved, else None
    fixed_px: int
    seconds: float  # the correction's own time
    render_seconds: float  # the level's render on the corrected (or given) map, 0 when none was needed
    focus_srgb: np.ndarray | None  # the photo in sRGB, when the correction computed it
    correction: _Correction  # what the correction found and did (an empty one where it did not run)


@dataclass
class _Correction:
    """What :func:`corrected_disparity` found: the map refine renders and the pixels moved, the edge field of that map
    when computed (the edge network's band; refine's gate needs the same), the share of the band the depth
    correction's local passes moved (None: it did not run), whether that found the map wrong (True where it did not
    run), the disagreement left on the corrected map (None: not measured) and whether the edge network ran."""

    disparity: np.ndarray
    changed: np.ndarray
    edge_field: _EdgeField | None = None
    share: float | None = None
    found_wrong: bool = True
    disagreement: float | None = None
    edges_ran: bool = False


@dataclass
class _EdgeField:
    """A map's signed CoC, its depth edges' reach (:func:`edge_reach`) and the distance to them
    (:func:`nearest_edge`; None: not computed, or no edges): the edge network's band needs them, and refine's gate
    needs them again for the same map."""

    disparity: np.ndarray
    coc: np.ndarray
    reach: np.ndarray
    nearest: tuple | None = None
    agreement: np.ndarray | None = None  #: :func:`.gate.edge_gate` of the map, when computed (the disagreement's)


def _same_map(a: np.ndarray, b: np.ndarray) -> bool:
    """The same map: the same array, or equal values of the same type (a float64 map is not its float32 copy)."""
    return a is b or (a.dtype == b.dtype and np.array_equal(a, b))


def corrected_disparity(image: np.ndarray, disparity: np.ndarray, blur: BlurParams,
                        options: RefineOptions = RefineOptions(), edge_model: EdgeNet | None = None,
                        focus_srgb: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The map refine renders: the colour-guided depth correction (``bokehray_refiner.depthfix``), then, with
    ``options.edges``, the learned edge placement (:mod:`.edges`) on its result; and which pixels moved. Clipped
    lights (dilated by 2 px) never move and never vote. A map the correction does not find wrong
    (``options.min_fixed_share``) comes back as it is, with nothing moved, or only shifted back where the correction
    found the whole map misregistered."""
    c = _corrected(image, disparity, blur, options, edge_model, focus_srgb)
    return c.disparity, c.changed


def _corrected(image: np.ndarray, disparity: np.ndarray, blur: BlurParams, options: RefineOptions,
               edge_model: EdgeNet | None, focus_srgb: np.ndarray | None,
               ) -> _Correction:
    """:func:`corrected_disparity`, with what it found (:class:`_Correction`)."""
    from scipy import ndimage

    focus_srgb = linear_to_srgb(np.clip(image[..., :3], 0.0, 1.0)) if focus_srgb is None else focus_srgb
    lights = channel_max(image) >= 1.0
    if lights.any():
        lights = ndimage.binary_dilation(lights, iterations=2)
    d_new, changed, edge_field, share = disparity, np.zeros(disparity.shape, bool), None, None
    band = None
    steps = None
    if options.depthfix.enabled:
        steps = correction_steps(focus_srgb, disparity, blur.k_px, options.depthfix, keep=lights)
    if steps is not None and steps[0] is not None:  # it ran (not on a map of noise): its moves are the evidence
        (sy, sx), shifted, d_new = steps
        d32 = np.asarray(disparity, np.float32)
        changed = d_new != d32
        edge_field, band = _field_and_band(d_new, blur, options)  # float32, as the network's map is
        local = d_new != shifted  # the local passes' moves: a global shift moves every pixel and says nothing here
        share = fixed_share(local, band)
        if not map_found_wrong(local, band, options.min_fixed_share):  # their few moves are not evidence
            if not (sy or sx):
                return _Correction(disparity, np.zeros(disparity.shape, bool), share=share, found_wrong=False)
            return _Correction(shifted, shifted != d32, share=share, found_wrong=False)  # the shift stays
    if not options.edges or (band is None and options.min_fixed_share > 0):
        return _Correction(d_new, changed, edge_field, share)
    if band is None:  # no correction ran: the given map's band
        d_new = np.asarray(d_new, np.float32)
        edge_field, band = _field_and_band(d_new, blur, options)
    return _edge_stage(image, focus_srgb, blur, options, edge_model, lights,
                       _Correction(d_new, changed, edge_field, share), band)


def _field_and_band(d: np.ndarray, blur: BlurParams, options: RefineOptions) -> tuple[_EdgeField, np.ndarray]:
    """The edge field of ``d`` and its edge band."""
    coc = blur.signed_coc(d).astype(np.float32)
    reach = edge_reach(coc, options.min_jump_px)
    field = _EdgeField(d, coc, reach, nearest_edge(reach))
    return field, edge_band(reach, options.band_margin_px, options.band_feather_px, field.nearest)


def _edge_stage(image, focus_srgb, blur, options, edge_model, lights, c: _Correction, band) -> _Correction:
    """The edge network on the map ``c`` found wrong, where the correction left disagreement (else ``c`` with the
    disagreement measured, its edge field keeping the agreement for refine's gate)."""
    field = c.edge_field
    if options.edge_min_disagreement > 0:
        field.agreement = edge_gate(focus_srgb, field.disparity, field.coc, options.min_jump_px,
                                    replace(options.gate, enabled=True), _indices(field.nearest))
        c.disagreement = _open_share(field.agreement, band, options.gate.floor)
        if c.disagreement < options.edge_min_disagreement:
            return c
    model = load_edge_net() if edge_model is None else edge_model
    placement = Placement(options.edge_threshold, colour_margin=options.edge_colour_margin,
                          passes=options.edge_passes)
    placed = place_edges(model, focus_srgb, c.disparity, blur, band, keep=lights, placement=placement)
    return _Correction(placed, c.changed | (placed != c.disparity), None, c.share, True, c.disagreement, True)


def disagreement(focus_srgb: np.ndarray, disparity: np.ndarray, coc: np.ndarray, band: np.ndarray, nearest=None,
                 options: RefineOptions = RefineOptions()) -> float:
    """How much of the edge band the confidence gate's colour/depth agreement leaves open on ``disparity`` (its
    mean over ``band > 0``; no highlight guard, which needs a render): near 0 where every depth edge sits on a
    colour edge of the photo. ``nearest``: :func:`nearest_edge` of the map's edge reach, when computed."""
    if not (band > 0).any():
        return 0.0
    gate = edge_gate(focus_srgb, disparity, coc, options.min_jump_px, replace(options.gate, enabled=True),
                     _indices(nearest))
    return _open_share(gate, band, options.gate.floor)


def _indices(nearest):
    """The nearest edge pixel's indices ``(iy, ix)`` of :func:`nearest_edge`'s result (None: none)."""
    return None if nearest is None else nearest[1]


def _open_share(agreement: np.ndarray, band: np.ndarray, floor: float) -> float:
    """The mean over ``band > 0`` of the agreement gate, below ``floor`` counted as shut (as :func:`.gate.refine_gate`
    shuts it); 0 without a band."""
    inside = band > 0
    if not inside.any():
        return 0.0
    gate = agreement[inside]
    return float(np.where(gate < floor, np.float32(0.0), gate).mean())


def fixed_share(fixed: np.ndarray, band: np.ndarray) -> float:
    """The share of the edge band's pixels (``band > 0``) that the depth correction moved (``fixed``; those outside
    the band do not count); 0 without a band."""
    inside = band > 0
    band_px = int(inside.sum())
    return int((fixed & inside).sum()) / band_px if band_px else 0.0


def map_found_wrong(fixed: np.ndarray, band: np.ndarray, min_share: float) -> bool:
    """Whether the depth correction moved at least ``min_share`` of the edge band's pixels (:func:`fixed_share`):
    the evidence that the map's edges are off the photo's, without which refine changes nothing. No band: nothing
    to repair."""
    return bool((band > 0).any()) and fixed_share(fixed, band) >= min_share


def _correct_depth(image: np.ndarray, disparity: np.ndarray, blur: BlurParams, classical: np.ndarray | None,
                   options: RefineOptions, rerender: Callable[[np.ndarray], np.ndarray] | None,
                   edge_model: EdgeNet | None = None) -> _DepthFix:
    """Stage 1: the depth correction (:func:`corrected_disparity`), then the level on the corrected map (or on the
    given map when nothing was rendered yet)."""
    fixed_px, t_fix, t_re, d_fixed, focus_srgb = 0, 0.0, 0.0, None, None
    c = _Correction(disparity, np.zeros(disparity.shape, bool))
    if rerender is not None and (options.depthfix.enabled or options.edges):
        t1 = time.perf_counter()
        focus_srgb = linear_to_srgb(np.clip(image[..., :3], 0.0, 1.0))
        c = _corrected(image, disparity, blur, options, edge_model, focus_srgb)
        d_new, changed = c.disparity, c.changed
        t_fix = time.perf_counter() - t1
        if changed.any():
            t1 = time.perf_counter()
            classical = np.asarray(rerender(d_new), np.float32)
            t_re = time.perf_counter() - t1
            disparity, d_fixed, fixed_px = d_new, d_new, int(changed.sum())
    if classical is None:  # nothing moved (or the fix is off): the level on the given map
        t1 = time.perf_counter()
        classical = np.asarray(rerender(disparity), np.float32)
        t_re = time.perf_counter() - t1
    return _DepthFix(classical, disparity, d_fixed, fixed_px, t_fix, t_re, focus_srgb, c)


def blend_weight(image: np.ndarray, focus_srgb: np.ndarray, disparity: np.ndarray, classical: np.ndarray,
                 coc: np.ndarray, options: RefineOptions = RefineOptions(),
                 reach: np.ndarray | None = None, nearest=None,
                 agreement: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The edge band (:func:`edge_band`) and the weight :func:`refine` blends the network's output in by: the band
    times the confidence gate. ``classical`` is the level's render on ``disparity`` (scene-linear), ``coc`` its
    signed CoC; ``reach``: :func:`edge_reach` of ``coc``, ``nearest``: :func:`nearest_edge` of ``reach`` and
    ``agreement``: :func:`.gate.edge_gate` of the map, when already computed. Training counts its loss where this
    weight is (``PairBank(gated=True)``)."""
    reach = edge_reach(coc, options.min_jump_px) if reach is None else reach
    if nearest is None:  # the gate's edge pixels are the band's: one distance transform for both
        nearest = nearest_edge(reach)
    full_band = edge_band(reach, options.band_margin_px, options.band_feather_px, nearest)
    gate = refine_gate(image, focus_srgb, disparity, classical, coc, options.min_jump_px, options.gate,
                       nearest=_indices(nearest), agreement=agreement)
    return full_band, full_band * gate


class _Frame(NamedTuple):
    """The render refine works on: the photo (scene-linear and sRGB), the (corrected) map, the level's render on it
    and its signed CoC."""

    image: np.ndarray
    focus_srgb: np.ndarray
    disparity: np.ndarray
    classical: np.ndarray
    coc: np.ndarray


def _gated_band(frame: _Frame, reach: np.ndarray, need: np.ndarray, options: RefineOptions,
                stats: RefineStats, field: _EdgeField | None = None) -> np.ndarray:
    """Stage 2: the blend weight of the correction, the band near depth edges times the confidence gate; tiles the
    gate closes are dropped from ``need`` (in place). ``field``: the map's edge field, with what it already holds."""
    h, w = frame.disparity.shape
    t = options.tile
    full_band, band = blend_weight(*frame, options, reach, None if field is None else field.nearest,
                                   None if field is None else field.agreement)
    stats.band_pixels = int((full_band > 0).sum())
    stats.gate_open = float(band.sum() / full_band.sum()) if full_band.sum() > 0 else 0.0
    ty, tx = need.shape
    padded = np.zeros((ty * t, tx * t), np.float32)
    padded[:h, :w] = band
    need &= padded.reshape(ty, t, tx, t).max(axis=(1, 3)) > 0  # a tile the gate closes is not run
    return band


def _network_pass(model: BokehRefiner, frame: _Frame, band: np.ndarray, need: np.ndarray, blur: BlurParams,
                  options: RefineOptions) -> np.ndarray:
    """Stage 3: the network's residual on the tiles in ``need`` (with their halos), feathered across the halos and
    blended into the classical render by ``band``; every other pixel keeps the classical value bit for bit."""
    _, focus_srgb, disparity, classical, coc = frame
    h, w = disparity.shape
    t, halo = options.tile, options.halo
    size = t + 2 * halo
    ph, pw = need.shape[0] * t - h + halo, need.shape[1] * t - w + halo  # pad to whole tiles plus the halo
    pad3 = ((halo, ph), (halo, pw), (0, 0))
    base = np.clip(classical[..., :3], 0.0, 1.0)
    f_srgb = np.pad(focus_srgb, pad3, mode="reflect")
    base_pad = np.pad(base, pad3, mode="reflect")  # encoded to sRGB only where the model reads it
    d_pad = np.pad(disparity.astype(np.float32), pad3[:2], mode="reflect")
    coc_pad = np.pad(coc, pad3[:2], mode="reflect")
    feather = raised_cosine_ramp(size, halo)
    wt = (feather[:, None] * feather[None, :])[..., None].astype(np.float32)
    tiles = list(zip(*np.nonzero(need)))
    wsum = np.zeros(base_pad.shape[:2] + (1,), np.float32)
    for y, x in tiles:
        wsum[int(y) * t:int(y) * t + size, int(x) * t:int(x) * t + size] += wt
    device = next(model.parameters()).device
    opts = PisaMaskOptions()

    def masks(sls: list) -> PisaMaskProvider:
        pisa = PisaMaskProvider(np.stack([d_pad[s] for s in sls]), blur.focus_disparity, blur.k_px, opts,
                                torch_device=device)
        hh, ww = d_pad[sls[0]].shape
        f = model.size_multiple
        pisa.at(-(-hh // f), -(-ww // f))  # the grid the model's PISA block asks for (cached; Warp, off the GIL)
        return pisa

    def run(sls: list, pisa: PisaMaskProvider | None = None) -> np.ndarray:
        stack = lambda a: torch.from_numpy(np.stack([a[s] for s in sls])).to(device)  # noqa: E731
        focus = stack(f_srgb).permute(0, 3, 1, 2)
        render = torch.from_numpy(np.stack([linear_to_srgb(base_pad[s]) for s in sls])).to(device).permute(0, 3, 1, 2)
        pisa = masks(sls) if pisa is None else pisa
        return (model(focus, render, stack(coc_pad), pisa) - render).permute(0, 2, 3, 1).cpu().numpy()

    boxes = refine_boxes(need, t, halo) if options.merge_tiles else [((int(y), int(y) + 1, int(x), int(x) + 1),
                                                                      [(int(y), int(x))]) for y, x in tiles]
    full = d_pad.size
    area = sum(((b[1] - b[0]) * t + 2 * halo) * ((b[3] - b[2]) * t + 2 * halo) for b, _ in boxes)
    if area >= full and full <= options.full_frame_px:
        acc = run([(slice(None), slice(None))])[0] * wsum  # one pass over the frame costs less than the boxes
    else:
        acc = np.zeros(base_pad.shape, np.float32)
        by_shape: dict[tuple[int, int], list] = {}
        for (ty0, ty1, tx0, tx1), members in boxes:  # boxes of one shape run in batches
            by_shape.setdefault((ty1 - ty0, tx1 - tx0), []).append(((ty0, ty1, tx0, tx1), members))
        chunks = [group[i:i + options.batch] for group in by_shape.values()
                  for i in range(0, len(group), options.batch)]
        slices = [[(slice(ty0 * t, ty1 * t + 2 * halo), slice(tx0 * t, tx1 * t + 2 * halo))
                   for (ty0, ty1, tx0, tx1), _ in chunk] for chunk in chunks]
        # the next chunk's PISA masks (Warp kernels, which release the GIL) are computed on a second thread while
        # the network runs on this one
        with ThreadPoolExecutor(max_workers=1) as pool:
            nxt = pool.submit(masks, slices[0])
            for k, (chunk, sls) in enumerate(zip(chunks, slices)):
                pisa = nxt.result()
                if k + 1 < len(chunks):
                    nxt = pool.submit(masks, slices[k + 1])
                for sl, ((ty0, _, tx0, _), members), dlt in zip(sls, chunk, run(sls, pisa)):
                    # the box's correction, weighted by the blend weights of the tiles it stands for
                    wbox = np.zeros(dlt.shape[:2] + (1,), np.float32)
                    for y, x in members:
                        wbox[(y - ty0) * t:(y - ty0) * t + size, (x - tx0) * t:(x - tx0) * t + size] += wt
                    acc[sl] += dlt * wbox
    delta = (acc / np.maximum(wsum, 1.0))[halo:halo + h, halo:halo + w]
    out = classical.astype(np.float32, copy=True)
    touched = (wsum[halo:halo + h, halo:halo + w, 0] > 0) & (band > 0)  # elsewhere: the classical bits
    b_t = base[touched]
    fixed = srgb_to_linear(np.clip(linear_to_srgb(b_t) + delta[touched] * band[touched][:, None], 0.0, 1.0))
    out[..., :3][touched] = classical[..., :3][touched] + (fixed - b_t)
    return out
