"""Soft depth maps: a ramp between two depths is an edge, not a surface (docs/soft-scene.md, "Soft maps").

A depth model's output, a brush-painted mask or an upsampled map ramps over 5-30 px between a subject and its
background, and every pixel of the ramp gets a depth no surface in the scene has. Where the ramp crosses the
focus those pixels render sharp inside the blur (a torn seam); elsewhere they smear the blur's edge.
:func:`snap_ramps` gives each pixel strictly inside such a ramp the depth of one of the two plateaus it joins,
chosen by its colour, so that the map has a step where the photo has its boundary; the matting
(``bokehray.matting``) then splits the mixed pixels of that step as it does on any hard map.

The rule (``bokehray_kernels.ramps``): a ramp is a run of pixels whose CoC gradient exceeds ``grad_min`` that
ends on a plateau (a pixel at most ``grad_min``) within ``max_walk`` px on both sides, along the gradient. A slope
that does not end so close (a floor, a wall going away) keeps its depths, and so does a pixel at a plateau's value
(a hard map is left exactly as it is). The side: the pixel's colour projected on the line between the two
plateaus' colours, weighed against its place in the ramp (where the plateaus' colours hardly differ, the ramp's
middle decides).
"""

from __future__ import annotations

from dataclasses import dataclass

import bokehray_kernels.ramps as bk_ramps
import numpy as np

from .edge_estimate import in_parts, in_row_parts

__all__ = ["RampRule", "snap_ramps"]


@dataclass(frozen=True, slots=True)
class RampRule:
    """The constants of :func:`snap_ramps` (chosen on the two-plane scene and the dev set's soft maps:
    docs/design/soft-maps.md)."""

    grad_min: float = 0.2
    """A plateau's CoC gradient is at most this (CoC px per px): 0.2 px/px is a floor's slope at a strong blur."""
    max_walk: int = 40
    """The longest walk to a plateau (px): a Gaussian of sigma 8 px ramps over about 40 px at a CoC range of 24 px."""
    min_range: float = 1.5
    """Plateaus whose CoC differs by less than this (px) are one surface: nothing to tear."""
    min_len: int = 5
    """Fewer steps from plateau to plateau are a hard edge (the gradient spreads 2 px either side of a step), not a
    ramp."""
    samples: int = 5
    """A plateau's colour: the mean of this many pixels from its start outwards, along the walk."""
    place: float = 0.01
    """A pixel within this share of the range from a plateau's value is at that plateau: kept."""
    min_contrast: float = 0.05
    """Plateau colours closer than this share of the brighter one (Euclidean, linear RGB) say nothing."""
    place_weight: float = 2.0
    """The weight of the pixel's place in the ramp against its colour (which counts in [-1, 1])."""

    def struct(self) -> bk_ramps.RampParams:
        p = bk_ramps.RampParams()
        p.grad_min, p.max_walk, p.min_range, p.min_len = self.grad_min, self.max_walk, self.min_range, self.min_len
        p.samples, p.place, p.min_contrast, p.place_weight = self.samples, self.place, self.min_contrast, \
            self.place_weight
        return p


def snap_ramps(image: np.ndarray, signed_coc: np.ndarray, rule: RampRule | None = None, *, device: str = "cpu",
               threads: int | None = None, check=None) -> tuple[np.ndarray, int]:
    """The signed CoC map with every pixel strictly inside an edge's ramp set to one of the ramp's plateaus, and
    how many pixels changed. ``image``: ``H x W x 3`` float32 linear RGB; ``signed_coc``: ``H x W`` float32, both
    finite (checked by the caller). The map is returned as given (not copied) when nothing changes. ``check()``:
    called between rounds of the kernel (it raises to stop)."""
    import warp as wp

    rule = rule or RampRule()
    s = np.ascontiguousarray(signed_coc, np.float32)
    h, w = s.shape
    if h < 3 or w < 3:
        return signed_coc, 0
    dev = wp.get_device(device)
    copy = not dev.is_cpu  # on the CPU the kernels read the (contiguous) arrays in place
    coc = wp.array(s, dtype=float, device=dev, copy=copy)
    flat = wp.empty((h, w), dtype=wp.uint8, device=dev)

    def plateaus(a: int, b: int) -> None:  # pixels a to b: the rows from ceil(a / w) on (the parts tile the rows)
        y0, y1 = -(-a // w), -(-b // w)
        if y1 > y0:
            wp.launch(bk_ramps.ramp_plateau_kernel, dim=y1 - y0, inputs=[coc, y0, float(rule.grad_min)],
                      outputs=[flat], device=dev)

    in_parts(h * w, plateaus, threads=threads, cpu=dev.is_cpu)
    f = flat.numpy()

    def candidates(a: int, b: int) -> np.ndarray:  # the rows [a, b)'s pixels steeper than a plateau, row-major
        return (np.flatnonzero(f[a:b] == 0) + a * w).astype(np.int32)  # a frame's pixels fit an int32 (Warp's)

    cand = np.concatenate(in_row_parts(h, w, candidates, threads=threads))
    if cand.size == 0:
        return signed_coc, 0
    img = wp.array(np.ascontiguousarray(image, np.float32), dtype=wp.vec3, device=dev, copy=copy)
    where = wp.array(cand, dtype=wp.int32, device=dev, copy=copy)
    value = wp.empty(cand.size, dtype=float, device=dev)
    snapped = wp.empty(cand.size, dtype=wp.uint8, device=dev)
    params = rule.struct()

    def launch(a: int, b: int) -> None:  # candidates a to b, their results in place
        if b > a:
            wp.launch(bk_ramps.snap_ramps_kernel, dim=b - a, inputs=[img, coc, flat, where, a, params],
                      outputs=[value, snapped], device=dev)

    in_parts(cand.size, launch, threads=threads, cpu=dev.is_cpu, check=check)
    moved = snapped.numpy().view(bool)  # 0 or 1
    n = int(np.count_nonzero(moved))
    if n == 0:
        return signed_coc, 0
    out = s.copy()
    out.reshape(-1)[cand[moved]] = value.numpy()[moved]
    return out, n
