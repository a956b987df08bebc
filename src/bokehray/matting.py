"""Soft edges: split the mixed pixels at depth edges into a near and a far part (local linear-model matting).

A pixel on the edge of a near object holds both colours, ``I = alpha F + (1 - alpha) B``, but a disparity map
gives it one depth. :func:`split_mixed_pixels` finds those pixels and estimates ``alpha``, the decontaminated
foreground ``F`` and the background ``B`` behind it, so the layered scene (``bokehray.scene.SoftEdges``) can
blur the two parts with their own CoC. NumPy for the edges and the band, one Warp kernel a band pixel
(``bokehray_kernels.matting``) for the matting:

1. **Depth edges.** Pairs of 4-neighbours whose signed CoC differs by more than ``jump_px``
   (``depthfix.depth_edges``). A map whose edges are noise (most pixels differ from all their neighbours:
   :func:`isolated_share`) is left alone.
2. **Trimap.** The unknown band is every pixel within ``band_px`` (Chebyshev) of a depth-edge pixel (0: the
   depth-edge pixels themselves, where the alpha >= 0.5 rule of a sensor or an estimator leaves the mixed
   pixels of a sharp edge). A soft map
   (an estimator's, a blurred one) has ramps: runs of consecutive same-sign steps across the edge; the band and
   the window widen with the measured ramp width (:func:`ramp_width`, capped by ``max_ramp_px``), so the colour
   edge, wherever it lies inside the ramp, decides. Around each band pixel the window's CoC range is split at
   its middle: pixels above are the near side, below the far side. Pixels outside the band are known (pure near
   or pure far); band pixels are unknown.
3. **Alpha: a local linear model of colour.** Per band pixel, ``alpha = w . I + c`` is fitted by ridge
   regression on its window (Gaussian weights): known pixels are 1 (near) or 0 (far), unknown ones count their
   side at a lower weight (``unknown_weight``), so a strand narrower than the band, with no known pixel of its
   own, is still found by its colour. The model is the colour direction that separates the two sides locally
   (closed-form matting's local model, solved per pixel instead of as one global system).
4. **F and B: the model's purest samples.** The same model gives every window pixel an alpha; F is the mean of
   the near side's colours weighted by ``alpha^purity`` and B of the far side's by ``(1 - alpha)^purity``
   (times the Gaussian), so the purest nearby samples dominate: a strand's own core, not the body it grows
   from. The parts' CoC are the window's largest and smallest CoC (the plateaus either side of the edge), not
   the pixel's own value, which a soft map's ramp leaves in between.
5. **Compositing identity.** Per channel, the change of (F, B) that makes ``alpha F + (1 - alpha) B`` the
   photo's colour while moving each part the least relative to the spread of its side's colours (a light
   behind a strand stays in B instead of lighting up the strand), then kept between 0 and the photo's colour
   over the part's share (no negative light). Where ``|F - B|`` is below ``min_contrast`` the colour says nothing
   about alpha and the pixel is left alone.

A band pixel is split when its alpha (on a sharp map also the projection of its colour on the F-B line) lies
in ``[min_alpha, 1 - min_alpha]``, or when its own CoC puts it on the side its alpha says it is not (a misplaced
depth edge): then alpha is clipped into that range. Every other
pixel is untouched. Results and the choice of method: docs/soft-scene.md.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

import bokehray_kernels.matting as bk_matting
import numpy as np

from .depthfix import depth_edges
from .errors import InputError
from .scene import SoftEdges, dilate
from .validate import check_finite

__all__ = ["isolated_share", "ramp_width", "split_mixed_pixels", "window_offsets"]

PIXELS_PER_THREAD = 4096
"""Fewest band pixels a CPU thread of the kernel gets (fewer are not worth a thread)."""


def ramp_width(signed_coc: np.ndarray, jump_px: float, cap: int) -> int:
    """How many pixels a depth edge's CoC ramp spans (0 for a hard edge): the 90th percentile, over the map's
    depth-edge pairs, of the length of the run of consecutive same-sign steps above ``jump_px`` a pair belongs
    to (along its axis), minus one; at most ``cap``."""
    lengths = []
    for ax in (0, 1):
        dd = np.diff(signed_coc, axis=ax)
        if dd.size == 0:
            continue
        pos = np.flatnonzero(np.abs(dd) > jump_px)  # row-major positions of the steps (the edge pairs only)
        if pos.size == 0:
            continue
        sign = np.sign(dd.ravel()[pos]).astype(np.int8)
        rows, cols = np.divmod(pos, dd.shape[1])
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


def _check(image: np.ndarray, signed_coc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    img = np.asarray(image)
    s = np.asarray(signed_coc)
    if img.ndim == 2:
        img = img[..., None]
    if img.ndim != 3 or img.shape[2] not in (1, 3, 4):
        raise InputError(f"image: expected an H x W x 3 linear RGB array, got shape {np.shape(image)}")
    if s.ndim == 3 and s.shape[2] == 1:
        s = s[..., 0]
    if s.shape != img.shape[:2]:
        raise InputError(f"signed_coc: expected an H x W map of the image's size {img.shape[:2]}, got {s.shape}")
    if not (np.issubdtype(img.dtype, np.number) and np.issubdtype(s.dtype, np.number)):
        raise InputError(f"image, signed_coc: expected numeric arrays, got {img.dtype} and {s.dtype}")
    img = np.asarray(img[..., :3] if img.shape[2] >= 3 else np.repeat(img, 3, axis=2), np.float32)
    s = np.asarray(s, np.float32)
    check_finite(img, "image", "(y, x, c)")
    check_finite(s, "signed_coc")
    return np.ascontiguousarray(img), np.ascontiguousarray(s)


def split_mixed_pixels(
    image: np.ndarray,
    signed_coc: np.ndarray,
    *,
    jump_px: float = 1.0,
    band_px: int = 0,
    max_ramp_px: int = 6,
    unknown_weight: float = 0.3,
    ridge: float = 0.03,
    purity: float = 8.0,
    min_contrast: float = 0.02,
    min_alpha: float = 0.1,
    max_isolated_share: float = 0.25,
    device: str = "cpu",
    threads: int | None = None,
) -> SoftEdges:
    """Split the mixed pixels at the depth edges of ``signed_coc`` into a near and a far part.

    Args:
        image: ``H x W x 3`` float32, scene-linear (1 or 4 channels are taken as grey / RGB).
        signed_coc: ``H x W`` signed CoC ``K (d - d_f)`` in px (> 0 in front of the focus).
        jump_px: a depth edge is a pair of 4-neighbours whose CoC differs by more than this.
        band_px: how far (Chebyshev px) the unknown band reaches beyond the depth-edge pixels of a hard edge.
        max_ramp_px: the widest CoC ramp (px) the band and the window widen for (a soft map's edges).
        unknown_weight: weight of the unknown (band) pixels, at their side's value, in the alpha model's fit.
        ridge: regularisation of the alpha model, relative to the window's mean colour.
        purity: F and B are means of the window's near / far side weighted by ``alpha^purity`` /
            ``(1 - alpha)^purity`` (the model's alpha of each window pixel): the purest samples dominate.
        min_contrast: pixels whose F and B differ by less than this share of the brighter of the two (Euclidean,
            linear RGB) are left alone: their colour says nothing about alpha.
        min_alpha: a pixel is split when its alpha (on a sharp map also its colour's projection on the F-B line)
            lies in ``[min_alpha, 1 - min_alpha]``; otherwise it keeps its one depth, unless the depth map puts it
            on the other side than its alpha (then alpha is clipped into the range).
        max_isolated_share: a map where more than this share of the pixels differ by more than ``jump_px`` from
            all their neighbours is noise, not edges: nothing is split (a strand one pixel wide, even diagonal,
            has neighbours of its own depth along it).
        device: the Warp device of the band's kernel.
        threads: CPU threads of the kernel (None: all cores); the result does not depend on it.

    Returns:
        The split pixels (:class:`~bokehray.scene.SoftEdges`); ``SoftEdges.empty()`` when the map has no edge.
        For every split pixel ``alpha F + (1 - alpha) B`` is the photo's colour (up to float32 rounding),
        ``near_coc > far_coc`` (the largest and smallest CoC of the pixel's window), and F, B lie between 0 and
        the colour over the part's share.

    Raises:
        InputError: mismatched shapes, non-numeric or non-finite input.
    """
    img, s = _check(image, signed_coc)
    photo = img
    h, w = s.shape
    if h < 2 and w < 2:
        return SoftEdges.empty()
    edges = depth_edges(s, float(jump_px))
    if not edges.any():
        return SoftEdges.empty()
    # isolated pixels are edge pixels: only a map with more edge pixels than the share allows can be noise
    if edges.mean() > max_isolated_share and isolated_share(s, float(jump_px)) > max_isolated_share:
        return SoftEdges.empty()  # noise in the map, not edges

    scale = float(np.abs(img).max()) or 1.0
    img = img / np.float32(scale)  # every threshold below is relative: the result does not depend on the exposure
    ramp = ramp_width(s, float(jump_px), int(max_ramp_px))
    b = int(band_px) + (ramp + 1) // 2
    radius = ramp + 2 * b + 2
    # work on the box of the edges, padded by everything a band pixel's window reaches
    ey, ex = np.nonzero(edges)
    pad = b + radius
    y0, y1 = max(0, int(ey.min()) - pad), min(h, int(ey.max()) + pad + 1)
    x0, x1 = max(0, int(ex.min()) - pad), min(w, int(ex.max()) + pad + 1)
    band = dilate(edges[y0:y1, x0:x1], b)
    by, bx = np.nonzero(band)
    out = launch_band_kernel(img[y0:y1, x0:x1], s[y0:y1, x0:x1], band, by, bx, radius, jump_px, unknown_weight, ridge,
                       purity, device, threads)
    alpha, F, B, vF, vB, near, far, flags = out
    ok = (flags & bk_matting.BAND_OK) != 0
    own_near = (flags & bk_matting.BAND_OWN_NEAR) != 0

    d = F - B
    den = (d * d).sum(1)
    contrast = (den > np.float32(min_contrast) ** 2 * np.maximum((F * F).sum(1), (B * B).sum(1))) & (den > 1e-20)
    lo_a, hi_a = np.float32(min_alpha), np.float32(1.0 - min_alpha)
    mixed = (alpha >= lo_a) & (alpha <= hi_a)
    if ramp == 0:
        # a sharp map's labels are trusted: a pixel the model calls mixed but whose colour's place on the F-B line
        # is F or B stays whole (a pure corner whose window is mostly the other side's texture). A soft map's
        # F and B are rougher; there the model alone decides (the check lost 0.4 dB on the estimated maps)
        proj = np.clip(((img[y0:y1, x0:x1][by, bx] - B) * d).sum(1) / np.maximum(den, np.float32(1e-30)), 0.0, 1.0)
        mixed &= (proj >= lo_a) & (proj <= hi_a)
    misplaced = ((alpha < lo_a) & own_near) | ((alpha > hi_a) & ~own_near)
    split = ok & contrast & (mixed | misplaced) & (near > far)
    if not split.any():
        return SoftEdges.empty()
    a = np.clip(alpha[split], lo_a, hi_a).astype(np.float32)
    Fk, Bk = F[split], B[split]
    floor = np.float32(1e-4) * (Fk ** 2 + Bk ** 2) + np.float32(1e-20)
    Fs, Bs = _composite_exact(photo[y0:y1, x0:x1][by[split], bx[split]], a, Fk * np.float32(scale),
                              Bk * np.float32(scale), vF[split] + floor, vB[split] + floor)
    index = (by[split] + y0).astype(np.int64) * w + (bx[split] + x0)  # row-major: sorted, unique
    return SoftEdges(index, a, Fs, Bs, near[split], far[split])


def launch_band_kernel(img, s, band, by, bx, radius, jump_px, unknown_weight, ridge, purity, device, threads):
    """Launch ``bokehray_kernels.matting.matting_band_kernel`` over the band pixels (in ``threads`` row bands on
    the CPU: Warp CPU launches release the GIL). Returns NumPy arrays: alpha, F, B, their variances, the near and
    far CoC and the flags."""
    import warp as wp

    n = by.size
    offs, dist = window_offsets(radius)
    dev = wp.get_device(device)
    image = wp.array(np.ascontiguousarray(img, np.float32), dtype=wp.vec3, device=dev)
    coc = wp.array(np.ascontiguousarray(s, np.float32), dtype=float, device=dev)
    unknown = wp.array(band.astype(np.uint8), dtype=wp.uint8, device=dev)
    oy = wp.array(offs[:, 0].astype(np.int32), dtype=wp.int32, device=dev)
    ox = wp.array(offs[:, 1].astype(np.int32), dtype=wp.int32, device=dev)
    sigma = 0.5 * radius
    og = wp.array(np.exp(-(dist.astype(np.float64) ** 2) / (2.0 * sigma * sigma)).astype(np.float32), dtype=float,
                  device=dev)
    parts = 1 if dev.is_cuda else max(1, min(int(threads or os.cpu_count() or 1), -(-n // PIXELS_PER_THREAD)))
    cuts = np.linspace(0, n, parts + 1).astype(np.int64)
    outs = [None] * parts

    def launch(j: int) -> None:
        a, b = int(cuts[j]), int(cuts[j + 1])
        m = b - a
        res = [wp.empty(m, dtype=float, device=dev)] + [wp.empty(m, dtype=wp.vec3, device=dev) for _ in range(4)] \
            + [wp.empty(m, dtype=float, device=dev), wp.empty(m, dtype=float, device=dev),
               wp.empty(m, dtype=wp.int32, device=dev)]
        if m:
            wp.launch(bk_matting.matting_band_kernel, dim=m,
                      inputs=[image, coc, unknown, wp.array(by[a:b].astype(np.int32), dtype=wp.int32, device=dev),
                              wp.array(bx[a:b].astype(np.int32), dtype=wp.int32, device=dev), oy, ox, og,
                              float(jump_px), float(unknown_weight), float(ridge), float(purity)],
                      outputs=res, device=dev)
        outs[j] = [r.numpy() for r in res]

    if parts == 1:
        launch(0)
    else:
        with ThreadPoolExecutor(max_workers=parts) as pool:
            list(pool.map(launch, range(parts)))
    return tuple(np.concatenate([o[k] for o in outs]) for k in range(8))


def _composite_exact(I: np.ndarray, a: np.ndarray, F: np.ndarray, B: np.ndarray, var_f: np.ndarray,
                     var_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(F, B) moved the least, per channel, so that ``a F + (1 - a) B = I``: the change minimises
    ``dF^2 / var_f + dB^2 / var_b`` (the side whose colours vary more nearby takes more of it: a light behind a
    strand stays in B instead of lighting up the strand), then F is kept between 0 and ``I / a`` and B between 0
    and ``I / (1 - a)`` (no negative light, no part brighter than its share of the pixel allows)."""
    I64, F64, B64 = I.astype(np.float64), F.astype(np.float64), B.astype(np.float64)
    vf, vb = var_f.astype(np.float64), var_b.astype(np.float64)
    a64 = a.astype(np.float64)[:, None]
    r = I64 - a64 * F64 - (1.0 - a64) * B64
    norm = a64 * a64 * vf + (1.0 - a64) * (1.0 - a64) * vb
    Fn = F64 + r * a64 * vf / norm
    lo = np.minimum(0.0, I64 / a64)
    hi = np.maximum(0.0, I64 / a64)
    Fn = np.clip(Fn, lo, hi)
    Bn = (I64 - a64 * Fn) / (1.0 - a64)
    Bn = np.clip(Bn, np.minimum(0.0, I64 / (1.0 - a64)), np.maximum(0.0, I64 / (1.0 - a64)))  # rounding only
    return Fn.astype(np.float32), Bn.astype(np.float32)
