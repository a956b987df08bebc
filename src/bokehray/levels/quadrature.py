"""Deterministic aperture quadrature for the layered ray tracer: the aperture cut into box cells.

The ray tracer (``bokehray_kernels.raytrace``) does not point-sample the
aperture. It traces one ray through the centre of each *cell* of a fixed
partition of the aperture and, where that ray meets a layer, takes the mean of
the layer's texture over the cell's footprint there (a box, from a summed-area
table). For a layer at CoC radius ``r`` the cells' footprints tile the
aperture's footprint exactly, so a fronto-parallel layer is integrated exactly
over the (slightly polygonised) aperture whatever the number of cells: no
noise, a flat plateau for a point light at any radius, energy conserved. The
number of cells sets only how finely occlusion *between* layers is resolved
(within a cell, the nearer layer's mean coverage multiplies the farther
layer's mean colour) and how well a tilted plane's footprint is approximated.

The partition for ``g >= 2`` strips across the aperture's diameter: the aperture
(unit circumradius, rows as in ``bokehray_kernels.aperture.chord``) is cut
into ``g`` horizontal strips of height ``2 / g``. In each strip the interval
common to all its sub-rows is split into square-ish full-height cells; what
is left at the two ends is covered, sub-row by sub-row, by thin rectangles
whose outer edge is the chord's end at the sub-row's centre (consecutive
sub-rows whose ends differ by less than a tolerance are merged, keeping
their area). The cells are boxes ``(ux, uy, hx, hy)`` (centre and half
sizes) and their weights are their areas over the total, so they sum to 1.
With ``g = 1`` the partition is one cell: the square of the aperture's area on
its centroid (a box blur of the right size, for a cap of one ray per pixel).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..lens import Aperture

OUTLINE = 0.02
"""Default outline tolerance of the cell partitions (unit-circumradius units)."""

__all__ = ["OUTLINE", "CellTable", "cell_table", "cells", "strips_for_radius"]


def _merge_ends(ends: np.ndarray, tol: float) -> list[tuple[int, int, float]]:
    """Greedy runs ``[k0, k1)`` of sub-rows whose end positions stay within ``tol`` of their mean."""
    runs = []
    k0 = 0
    n = len(ends)
    while k0 < n:
        k1 = k0 + 1
        while k1 < n:
            seg = ends[k0 : k1 + 1]
            if seg.max() - seg.min() > 2.0 * tol:
                break
            k1 += 1
        runs.append((k0, k1, float(ends[k0:k1].mean())))
        k0 = k1
    return runs


def cells(aperture: Aperture, strips: int, *, sub_rows: int = 32, tol: float | None = None) -> np.ndarray:  # noqa: C901
    """The partition of the aperture into boxes for ``strips`` strips: ``(n, 5)`` float64 rows
    ``(ux, uy, hx, hy, weight)``, weights summing to 1.

    Args:
        sub_rows: resolution of the aperture's outline inside each strip.
        tol: largest deviation (unit-circumradius units) of a merged end piece's edge from the
            chord ends it stands for; default an eighth of a sub-row's height.
    """
    g = int(strips)
    if g < 1:
        raise ValueError("strips must be >= 1")
    if g == 1:
        # one cell: the square of the aperture's area on its centroid (a box blur of the right size)
        yy = np.linspace(-1.0, 1.0, 4001)
        lo, hi = aperture.chords(yy)
        wdt = np.maximum(hi - lo, 0.0)
        area = float(np.trapezoid(wdt, yy))
        cy = float(np.trapezoid(wdt * yy, yy)) / area
        cx = float(np.trapezoid(wdt * 0.5 * (lo + hi), yy)) / area
        half = 0.5 * math.sqrt(area)
        return np.array([[cx, cy, half, half, 1.0]])
    hs = 2.0 / g
    m = max(1, int(sub_rows))
    dv = hs / m
    tol = dv / 8.0 if tol is None else float(tol)
    out: list[tuple[float, float, float, float, float]] = []

    def add(x0: float, x1: float, y0: float, y1: float, split: bool = True) -> None:
        if x1 - x0 <= 1e-12 or y1 - y0 <= 1e-12:
            return
        n = max(1, int(round((x1 - x0) / hs))) if split else 1
        w = (x1 - x0) / n
        for i in range(n):
            a = x0 + i * w
            out.append((a + 0.5 * w, 0.5 * (y0 + y1), 0.5 * w, 0.5 * (y1 - y0), w * (y1 - y0)))

    for j in range(g):
        v0 = -1.0 + j * hs
        vc = v0 + (np.arange(m) + 0.5) * dv
        lo, hi = aperture.chords(vc)
        ok = hi > lo
        if not ok.any():
            continue
        ks = np.flatnonzero(ok)
        # sub-rows with content are contiguous (the shape is convex)
        k_lo, k_hi = int(ks[0]), int(ks[-1]) + 1
        lo, hi = lo[k_lo:k_hi], hi[k_lo:k_hi]
        y_top = v0 + k_lo * dv
        a, b = float(lo.max()), float(hi.min())
        if b - a > 0.25 * hs:
            add(a, b, y_top, y_top + (k_hi - k_lo) * dv)  # interior: full-height cells
            for k0, k1, edge in _merge_ends(lo, tol):
                add(edge, a, y_top + k0 * dv, y_top + k1 * dv)
            for k0, k1, edge in _merge_ends(hi, tol):
                add(b, edge, y_top + k0 * dv, y_top + k1 * dv)
        else:  # a sliver (the tip of the shape): sub-row runs whose two ends both stay within tol
            k0 = 0
            while k0 < len(lo):
                k1 = k0 + 1
                while k1 < len(lo) and max(np.ptp(lo[k0 : k1 + 1]), np.ptp(hi[k0 : k1 + 1])) <= 2.0 * tol:
                    k1 += 1
                add(float(lo[k0:k1].mean()), float(hi[k0:k1].mean()), y_top + k0 * dv, y_top + k1 * dv)
                k0 = k1
    table = np.asarray(out, np.float64)
    table[:, 4] /= table[:, 4].sum()
    return table


@dataclass(frozen=True)
class CellTable:
    """Cell partitions for several strip counts, packed for the kernel.

    ``boxes`` (n, 4) float32 ``(ux, uy, hx, hy)``, ``weights`` (n,) float32,
    ``offsets`` (levels + 1,) int32: level ``i`` (``strips[i]`` strips) is rows
    ``offsets[i]:offsets[i + 1]``. Level 0 is always the single centre ray (a
    point of the aperture with a zero-size cell), used where the CoC is below
    half a pixel.
    """

    strips: tuple[int, ...]
    boxes: np.ndarray
    weights: np.ndarray
    offsets: np.ndarray
    parts: tuple = ()  #: (strips, outline) of levels 1, 2, ...

    def count(self, level: np.ndarray | int) -> np.ndarray:
        return np.diff(self.offsets)[level]


def cell_table(aperture: Aperture, strips: list[int] | tuple[int, ...], outline: float = OUTLINE) -> CellTable:
    """Tables for ``strips`` (level 1, 2, ...; level 0 is the centre ray).

    ``outline`` (unit-circumradius units) bounds how far a cell's outer edge strays from the
    aperture's outline (the end pieces' merge tolerance; sub-rows are at most twice as tall): the
    polygonised aperture differs from the true one by about ``outline`` of its area at every
    radius (measured in tests/test_raytrace.py).
    """
    rows = [np.array([[0.0, 0.0, 0.0, 0.0, 1.0]])]
    for g in strips:
        m = int(min(256, max(2, math.ceil((2.0 / g) / (2.0 * outline)))))
        rows.append(cells(aperture, g, sub_rows=m, tol=outline))
    offsets = np.cumsum([0] + [len(r) for r in rows]).astype(np.int32)
    allrows = np.concatenate(rows, axis=0)
    return CellTable(strips=(0, *map(int, strips)), boxes=np.ascontiguousarray(allrows[:, :4], np.float32),
                     weights=np.ascontiguousarray(allrows[:, 4], np.float32), offsets=offsets,
                     parts=tuple((int(g), float(outline)) for g in strips))


def strips_for_radius(r_px: np.ndarray, samples_per_px2: float) -> np.ndarray:
    """Strips across the aperture for a CoC radius: cells of about ``1 / sqrt(samples_per_px2)`` px.

    ``(pi / 4) g^2`` cells cover the CoC's ``pi r^2`` px^2, so ``g = ceil(2 r sqrt(samples_per_px2))``.
    """
    return np.ceil(2.0 * np.asarray(r_px, np.float64) * math.sqrt(samples_per_px2)).astype(np.int64)
