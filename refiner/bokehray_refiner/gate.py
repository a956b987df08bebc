"""The refiner's confidence gate: where the depth map can be trusted, the classical render is already right.

A depth edge that sits exactly on a colour edge of the all-in-focus image is
most likely right, and then the classical render is exact there (up to what no
single image holds); the refiner, trained on synthetic pairs, can only make it
worse. A depth edge a few pixels away from the strongest colour edge across it
(an eroded, dilated, smeared or shifted map) is where a depth error breaks the
classical render, and where the refiner is allowed to act.

:func:`edge_agreement` measures this at every depth-edge pixel: along the depth
edge's normal it samples the colour step ``|f(t + 1/2) - f(t - 1/2)|`` (sRGB,
bilinear) at offsets ``t`` in ``[-radius, radius]``, and takes the ratio of the
strongest step within ``near_px`` of the depth edge to the strongest one in the
whole window. Ratios are averaged along the edge (a Gaussian over edge pixels),
because real depth errors are coherent along an edge while texture near an edge
is not. The gate is ``1 - smoothstep(lo, hi, ratio)``: closed (0) where the colour
edge sits on the depth edge, open (1) where it is displaced. Edges without a
colour step worth the name (``min_step``) are trusted: there a displaced depth edge
changes little.

:func:`highlight_guard` closes the gate over the footprint of every clipped light
of the all-in-focus image and wherever the classical render is above 1: the model
sees clipped sRGB there, so its correction could neither conserve the light's
energy nor tell a bokeh ball from its in-focus core.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bokehray_refiner.depthfix import edge_pairs

__all__ = ["GateOptions", "edge_agreement", "edge_gate", "highlight_guard", "refine_gate"]


@dataclass(frozen=True)
class GateOptions:
    """Parameters of the confidence gate (chosen on synthetic validation pairs, docs/refiner.md).

    Args:
        enabled: False lets every band pixel through (the ungated refiner, for measurements).
        agreement: False skips the colour/depth edge agreement: the whole band is open but for the highlight guard
            (a refiner trained to leave right edges alone decides there by itself).
        radius_px: how far across a depth edge the colour edge is searched.
        near_px: a colour edge within this distance of the depth edge counts as "on" it.
        lo, hi: agreement ratios below ``lo`` open the gate fully, above ``hi`` close it.
        sigma_px: smoothing of the agreement along the edge.
        min_step: colour steps (sRGB, Euclidean over RGB) below this are "no colour edge".
        highlight: close the gate over clipped lights (see :func:`highlight_guard`).
        highlight_margin_px: extra reach around a clipped light's CoC.
        open_dilated: also open where the colour edge lies on the depth edge's near side (a too fat near region).
            Off: the shipped model made dilated edges worse on the dev set (docs/refiner.md).
        floor: gates below this are 0, so tiles with only a trace of an open gate are not run.
    """

    enabled: bool = True
    agreement: bool = True
    radius_px: float = 6.0
    near_px: float = 0.5
    lo: float = 0.55
    hi: float = 0.85
    sigma_px: float = 6.0
    min_step: float = 0.03
    highlight: bool = True
    highlight_margin_px: float = 3.0
    open_dilated: bool = False
    floor: float = 0.05


def _normals(disparity: np.ndarray, box: tuple[int, int, int, int]) -> tuple[np.ndarray, np.ndarray]:
    """The unit gradient of the lightly smoothed disparity on ``box`` (y0, y1, x0, x1) of the frame, equal bit for
    bit to the whole frame's wherever it is read (see ``_edges_box``)."""
    from scipy import ndimage

    y0, y1, x0, x1 = box
    d = ndimage.gaussian_filter(disparity[y0:y1, x0:x1].astype(np.float32), 1.0)
    gy, gx = ndimage.sobel(d, 0), ndimage.sobel(d, 1)
    n = np.hypot(gy, gx)
    n = np.where(n > 0, n, 1.0)
    return gy / n, gx / n


def _edges_box(shape: tuple[int, int], edges, margin: int) -> tuple[int, int, int, int]:
    # the edge pixels' bounding box grown by ``margin``, clipped to the frame: a filter reaching at most
    # ``margin`` px gives the same values at the edge pixels on it as on the whole frame (where it is clipped, the
    # frame's own border mode applies in both)
    ys = np.concatenate([e[0] for e in edges])
    xs = np.concatenate([e[1] for e in edges])
    h, w = shape
    return (max(0, int(ys.min()) - margin), min(h, int(ys.max()) + margin + 1),
            max(0, int(xs.min()) - margin), min(w, int(xs.max()) + margin + 1))


def edge_agreement(focus_srgb: np.ndarray, disparity: np.ndarray, edges: list[tuple[np.ndarray, np.ndarray, int]],
                   options: GateOptions = GateOptions()) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Agreement ratio in [0, 1] of colour and depth edges, per depth-edge pixel.

    Args:
        focus_srgb: ``H x W x 3`` all-in-focus image, sRGB in [0, 1].
        disparity: ``H x W`` disparity the render used.
        edges: per axis, the ``(ys, xs, axis)`` of edge pixels ``a`` whose pair ``(a, a + e_axis)`` is a depth edge.

    Returns:
        ``(ys, xs, ratio)`` over all edge pixels (the midpoint's pixel ``a``), smoothed along the edge;
        ratio 1 where there is no colour step (``min_step``).
    """
    from scipy import ndimage

    if sum(e[0].size for e in edges) == 0:
        e = np.zeros(0, np.int64)
        return e, e, np.zeros(0, np.float32)
    box = _edges_box(disparity.shape, edges, 4 + 1)  # the Gaussian's truncation (4 sigma) and the Sobel's reach
    ny, nx = _normals(disparity, box)
    steps = np.arange(-options.radius_px, options.radius_px + 1e-6, 0.5, dtype=np.float32)
    near = np.abs(steps) <= options.near_px + 1e-6
    all_y, all_x, all_r = [], [], []
    chans = [np.ascontiguousarray(focus_srgb[..., c], np.float32) for c in range(3)]
    for ys, xs, axis in edges:
        if ys.size == 0:
            continue
        my = ys + (0.5 if axis == 0 else 0.0)
        mx = xs + (0.5 if axis == 1 else 0.0)
        uy, ux = ny[ys - box[0], xs - box[2]], nx[ys - box[0], xs - box[2]]
        zero = (uy == 0) & (ux == 0)  # flat gradient after smoothing: use the pair's own axis
        uy = np.where(zero, 1.0 if axis == 0 else 0.0, uy)
        ux = np.where(zero, 1.0 if axis == 1 else 0.0, ux)
        offs = np.concatenate([steps - 0.5, steps[-1:] + 0.5])  # sample points between which the steps lie
        py = my[:, None] + offs[None, :] * uy[:, None]
        px = mx[:, None] + offs[None, :] * ux[:, None]
        coords = np.stack([py.ravel(), px.ravel()])
        samp = np.stack([ndimage.map_coordinates(c, coords, order=1, mode="nearest").reshape(py.shape)
                         for c in chans], -1)
        step = np.linalg.norm(np.diff(samp, axis=1), axis=-1)  # (edges, len(steps))
        # without open_dilated only the far side is searched: a colour edge beyond the depth edge on its near
        # side means a too fat near region (or the far edge of a thin structure), where the gate stays closed
        best = (step if options.open_dilated else step[:, steps <= options.near_px + 1e-6]).max(axis=1)
        ratio = np.where(best >= options.min_step, step[:, near].max(axis=1) / np.maximum(best, 1e-12), 1.0)
        all_y.append(ys)
        all_x.append(xs)
        all_r.append(ratio.astype(np.float32))
    if not all_y:
        e = np.zeros(0, np.int64)
        return e, e, np.zeros(0, np.float32)
    ys, xs, r = np.concatenate(all_y), np.concatenate(all_x), np.concatenate(all_r)
    if options.sigma_px > 0:  # normalised convolution over the edge pixels only
        # on the edge pixels' bounding box plus the Gaussian's truncation radius: outside it every input is 0,
        # so the values read at the edge pixels are the whole frame's bit for bit (only the box costs)
        h, w = disparity.shape
        t = int(4.0 * float(options.sigma_px) + 0.5)  # scipy's truncate = 4
        y0, y1 = max(0, int(ys.min()) - t), min(h, int(ys.max()) + t + 1)
        x0, x1 = max(0, int(xs.min()) - t), min(w, int(xs.max()) + t + 1)
        by, bx = ys - y0, xs - x0
        num, den = np.zeros((y1 - y0, x1 - x0), np.float32), np.zeros((y1 - y0, x1 - x0), np.float32)
        np.add.at(num, (by, bx), r)
        np.add.at(den, (by, bx), 1.0)
        num = ndimage.gaussian_filter(num, options.sigma_px)
        den = ndimage.gaussian_filter(den, options.sigma_px)
        r = num[by, bx] / np.maximum(den[by, bx], 1e-12)
    return ys, xs, np.clip(r, 0.0, 1.0).astype(np.float32)


def _smoothstep(lo: float, hi: float, x: np.ndarray) -> np.ndarray:
    t = np.clip((x - lo) / max(hi - lo, 1e-6), 0.0, 1.0)
    return t * t * (3 - 2 * t)


def channel_max(rgb: np.ndarray) -> np.ndarray:
    """The largest of R, G, B per pixel (a reduction over the last axis of an H x W x C array is 10x slower)."""
    return np.maximum(np.maximum(rgb[..., 0], rgb[..., 1]), rgb[..., 2])


def highlight_guard(image: np.ndarray, classical: np.ndarray, coc: np.ndarray, margin_px: float) -> np.ndarray:
    """1 where the refiner may act, 0 over clipped lights' footprints and wherever the classical render is > 1."""
    from scipy import ndimage

    lit = channel_max(image) >= 1.0
    hot = channel_max(classical) > 1.0
    guard = np.ones(coc.shape, np.float32)
    if lit.any():
        dist, (iy, ix) = ndimage.distance_transform_edt(~lit, return_indices=True)
        guard[dist <= np.abs(coc[iy, ix]) + margin_px] = 0.0
    if hot.any():
        guard[ndimage.binary_dilation(hot, iterations=int(np.ceil(margin_px)))] = 0.0
    return guard


def edge_gate(focus_srgb: np.ndarray, disparity: np.ndarray, coc: np.ndarray, min_jump_px: float,
              options: GateOptions = GateOptions(), nearest: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """The colour/depth agreement part of :func:`refine_gate`, per pixel: the gate of its nearest depth-edge pixel
    (edges where the CoC jumps by more than ``min_jump_px``), before the highlight guard and the floor; 0 everywhere
    without depth edges, 1 with the gate disabled. ``nearest``: the indices ``(iy, ix)`` of every pixel's nearest
    edge pixel when the caller has them (the refiner's edge band)."""
    from scipy import ndimage

    h, w = coc.shape
    if not options.enabled:
        return np.ones((h, w), np.float32)
    pairs = edge_pairs(coc, min_jump_px)
    if options.agreement:
        ys, xs, ratio = edge_agreement(focus_srgb, disparity, pairs, options)
        opened = 1.0 - _smoothstep(options.lo, options.hi, ratio)
    else:
        ys, xs = np.concatenate([e[0] for e in pairs]), np.concatenate([e[1] for e in pairs])
        opened = np.ones(ys.shape, np.float32)
    if ys.size == 0:
        return np.zeros((h, w), np.float32)
    open_ = np.zeros((h, w), np.float32)
    mark = np.zeros((h, w), bool)
    np.maximum.at(open_, (ys, xs), opened)
    mark[ys, xs] = True
    if nearest is None:
        _, (iy, ix) = ndimage.distance_transform_edt(~mark, return_indices=True)
    else:
        iy, ix = nearest
    return open_[iy, ix]


def refine_gate(image: np.ndarray, focus_srgb: np.ndarray, disparity: np.ndarray, classical: np.ndarray,
                coc: np.ndarray, min_jump_px: float, options: GateOptions = GateOptions(),
                nearest: tuple[np.ndarray, np.ndarray] | None = None,
                agreement: np.ndarray | None = None) -> np.ndarray:
    """The gate in [0, 1] per pixel: how much of the refiner's correction is let through.

    Each pixel takes the gate of its nearest depth-edge pixel (:func:`edge_gate`; ``agreement``: it, when already
    computed for this map and these options), times the highlight guard. Without depth edges the gate is 0
    everywhere. ``nearest``: the indices ``(iy, ix)`` of every pixel's nearest edge pixel when the caller has them (the
    refiner's edge band).
    """
    if not options.enabled:
        return np.ones(coc.shape, np.float32)
    gate = (edge_gate(focus_srgb, disparity, coc, min_jump_px, options, nearest) if agreement is None
            else agreement.copy())
    if options.highlight:
        gate *= highlight_guard(image, classical, coc, options.highlight_margin_px)
    gate[gate < options.floor] = 0.0
    return gate.astype(np.float32)
