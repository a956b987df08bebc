"""Soft edges: split the mixed pixels at depth edges into a near and a far part (local linear-model matting).

A pixel on the edge of a near object holds both colours, ``I = alpha F + (1 - alpha) B``, but a disparity map
gives it one depth. :func:`split_mixed_pixels` finds those pixels and estimates ``alpha``, the decontaminated
foreground ``F`` and the background ``B`` behind it, so the layered scene (``bokehray.scene.SoftEdges``) can
blur the two parts with their own CoC. NumPy for the edges and the band, one Warp kernel a band pixel
(``bokehray_kernels.matting``) for the matting:

1. **Depth edges.** Pairs of 4-neighbours whose signed CoC differs by more than ``jump_px``
   (``edge_estimate.depth_edges``). A map whose edges are noise (most pixels differ from all their neighbours:
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
4b. **Alpha fused with the projection.** The model's alpha (biased towards the window's mean by the ridge) and the
   projection of the pixel's colour on its F-B line are fused by their inverse variances (:func:`fuse_alpha`):
   over flat sides the projection decides, over texture the model.
5. **Compositing identity.** Per channel, the change of (F, B) that makes ``alpha F + (1 - alpha) B`` the
   photo's colour while moving each part the least relative to the spread of its side's colours (a light
   behind a strand stays in B instead of lighting up the strand), then kept between 0 and the photo's colour
   over the part's share (no negative light). Where ``|F - B|`` is below ``min_contrast`` the colour says nothing
   about alpha and the pixel is left alone.

A band pixel is split when its alpha (on a sharp map also the projection of its colour on the F-B line) lies
in ``[min_alpha, max_alpha]``, or when its own CoC puts it on the side its alpha says it is not (a misplaced
depth edge): then alpha is clipped into that range. Every other
pixel is untouched. Results and the choice of method: docs/soft-scene.md.
"""

from __future__ import annotations

import numpy as np

from .edge_estimate import CHECK_ITEMS, MattingRule, edge_band
from .errors import InputError, ResourceError
from .scene import SoftEdges
from .validate import check_finite

__all__ = ["SPLIT_B", "MattingRule", "check_split_fits", "fuse_alpha", "split_mixed_pixels"]

SPLIT_B = 44
"""Bytes a split pixel holds (``SoftEdges``: its flat index, alpha, F, B and the two CoC) from the split on."""
SPLIT_CHUNK = CHECK_ITEMS
"""Band pixels matted at a time: the kernel's outputs and the split's float64 temporaries are a chunk's."""

def _check(image: np.ndarray, signed_coc: np.ndarray, finite: bool = True) -> tuple[np.ndarray, np.ndarray]:
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
    if finite:
        check_finite(img, "image", "(y, x, c)")
        check_finite(s, "signed_coc")
    return np.ascontiguousarray(img), np.ascontiguousarray(s)


def split_mixed_pixels(
    image: np.ndarray,
    signed_coc: np.ndarray,
    rule: MattingRule | None = None,
    *,
    device: str = "cpu",
    threads: int | None = None,
    finite_checked: bool = False,
    check=None,
    budget_bytes: int | None = None,
) -> SoftEdges:
    """Split the mixed pixels at the depth edges of ``signed_coc`` into a near and a far part.

    Args:
        image: ``H x W x 3`` float32, scene-linear (1 or 4 channels are taken as grey / RGB).
        signed_coc: ``H x W`` signed CoC ``K (d - d_f)`` in px (> 0 in front of the focus).
        rule: the constants (:class:`~bokehray.edge_estimate.MattingRule`; default: its defaults):

            * ``jump_px``: a depth edge is a pair of 4-neighbours whose CoC differs by more than this.
            * ``band_px``: how far (Chebyshev px) the unknown band reaches beyond the depth-edge pixels of a hard
              edge.
            * ``max_ramp_px``: the widest CoC ramp (px) the band and the window widen for (a soft map's edges).
            * ``unknown_weight``: weight of the unknown (band) pixels, at their side's value, in the alpha model's fit.
            * ``ridge``: regularisation of the alpha model, relative to the window's mean colour.
            * ``purity``: F and B are means of the window's near / far side weighted by ``alpha^purity`` /
              ``(1 - alpha)^purity`` (the model's alpha of each window pixel): the purest samples dominate.
            * ``min_contrast``: pixels whose F and B differ by less than this share of the brighter of the two
              (Euclidean, linear RGB) are left alone: their colour says nothing about alpha.
            * ``min_alpha``, ``max_alpha``: a pixel is split when its alpha (on a sharp map also its colour's
              projection on the F-B line) lies in this range; otherwise it keeps its one depth, unless the depth
              map puts it on the other side than its alpha (then alpha is clipped into the range). A nearly pure
              foreground pixel stays whole (splitting it would leave a sharp sliver ``I - alpha F`` of the
              foreground's colour where F is a little off), a faint background one is split (whole, its share of
              the strand would stay sharp and feed the fill behind the strand).
            * ``model_sd``: the standard deviation given to the model's alpha when it is fused with the projection
              of the pixel's colour on the F-B line (:func:`fuse_alpha`); None: the model's alpha alone.
            * ``max_isolated_share``: a map where more than this share of the pixels differ by more than
              ``jump_px`` from all their neighbours is noise, not edges: nothing is split (a strand one pixel wide,
              even diagonal, has neighbours of its own depth along it).
            * ``light_level``, ``light_ratio``, ``light_reach``, ``light_thin``, ``light_share``: a far side
              brighter than ``light_level`` (mean of RGB, the photo's units: above a white surface, a light) and
              ``light_ratio`` times F, behind a near side under ``light_thin`` of the window's weight (a strand)
              whose F holds over ``light_share`` more of the light's colour than the F of its unlit samples out to
              ``light_reach`` px: F is that F and alpha the pixel's place on the line from B to it
              (``light_reach = 0``: never).
        device: the Warp device of the band's kernel.
        threads: CPU threads of the kernel (None: all cores); the result does not depend on it.
        finite_checked: the caller has already refused NaN and Inf in both arrays (the render pipeline: a checked
            photo, a CoC computed from a checked map): the scans for them (a pass over the frame each) are skipped.
        check: called between the steps and between rounds of the band's kernel; it raises to stop the split (a
            render superseded or interrupted). None: no checks.
        budget_bytes: refuse (``ResourceError``) a band whose split cannot fit this many bytes, before the matting
            (:func:`check_split_fits`); None: no check.

    Returns:
        The split pixels (:class:`~bokehray.scene.SoftEdges`); ``SoftEdges.empty()`` when the map has no edge.
        For every split pixel ``alpha F + (1 - alpha) B`` is the photo's colour (up to float32 rounding),
        ``near_coc > far_coc`` (the largest and smallest CoC of the pixel's window), and F, B lie between 0 and
        the colour over the part's share.

    Raises:
        InputError: mismatched shapes, non-numeric or non-finite input.
    """
    rule = rule or MattingRule()
    img, s = _check(image, signed_coc, finite=not finite_checked)
    band = edge_band(img, s, rule, check)
    if band is None:
        return SoftEdges.empty()
    if budget_bytes is not None:
        check_split_fits(band.size, s.shape, budget_bytes)
    pieces = []
    for a in range(0, band.size, SPLIT_CHUNK):  # the work of a chunk at a time (its float64 temporaries)
        est = band.estimate(a, min(band.size, a + SPLIT_CHUNK), rule, device=device, threads=threads, check=check)
        pieces.append(_split_estimate(img, est, rule))
    return pieces[0] if len(pieces) == 1 else SoftEdges(*(np.concatenate([getattr(p, f) for p in pieces])
                                                          for f in ("index", "alpha", "foreground", "background",
                                                                    "near_coc", "far_coc")))


def check_split_fits(band_pixels: int, shape: tuple[int, int], budget_bytes: int) -> None:
    """Refuse a split whose result cannot fit ``budget_bytes`` at worst (every band pixel split; held through the
    layers), before the matting allocates it. A chunk's work (at most ``SPLIT_CHUNK`` band pixels at about 900 B
    each, the kernel's outputs and the split's float64 temporaries: 120 MB) is transient, freed before the layers,
    and bounded whatever the image."""
    need = SPLIT_B * band_pixels
    if need > budget_bytes:
        h, w = shape
        raise ResourceError(f"soft edges of the {w} x {h} px image: its {band_pixels} pixels at depth edges need up "
                            f"to {need / 2**20:.0f} MB, over the memory budget of {budget_bytes / 2**20:.0f} MB "
                            "(a map that is edges everywhere; give more memory, or LayerOptions(soft_edges=False))")


def _split_estimate(photo: np.ndarray, est, rule: MattingRule) -> SoftEdges:
    """The split pixels among the band pixels of one edge estimate (``bokehray.edge_estimate.EdgeEstimate``)."""
    band = est.band
    w = band.shape[1]
    y0, y1, x0, x1 = band.box
    by, bx, ramp, scale = est.by, est.bx, band.ramp, band.scale
    alpha, F, B, vF, vB, near, far = est.alpha, est.fg, est.bg, est.fg_var, est.bg_var, est.near, est.far
    ok, own_near = est.ok, est.own_near
    min_alpha, max_alpha, model_sd = rule.min_alpha, rule.max_alpha, rule.model_sd

    d = F - B
    den = (d * d).sum(1)
    contrast = est.contrast(rule.min_contrast)
    if model_sd is not None:
        alpha = fuse_alpha(alpha, band.image[by, bx], F, B, vF, vB, float(model_sd))
    lo_a = np.float32(min_alpha)
    hi_a = np.float32(max_alpha)
    mixed = (alpha >= lo_a) & (alpha <= hi_a)
    if ramp == 0:
        # a sharp map's labels are trusted: a pixel the model calls mixed but whose colour's place on the F-B line
        # is F or B stays whole (a pure corner whose window is mostly the other side's texture). A soft map's
        # F and B are rougher; there the model alone decides (the check lost 0.4 dB on the estimated maps)
        proj = np.clip(((band.image[by, bx] - B) * d).sum(1) / np.maximum(den, np.float32(1e-30)), 0.0, 1.0)
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


def fuse_alpha(alpha: np.ndarray, I: np.ndarray, F: np.ndarray, B: np.ndarray, var_f: np.ndarray,
               var_b: np.ndarray, model_sd: float) -> np.ndarray:
    """The linear model's alpha fused with the projection of the pixel's colour on its F-B line, each weighted by
    the inverse of its variance: the model's is ``model_sd^2``; the projection's is the spread of F and B's samples
    carried through it, ``(a^2 |var F| + (1 - a)^2 |var B|) / |F - B|^2``. Where both sides are uniform (a wire
    over the sky) the projection is exact and the model's ridge bias goes; over texture the model decides."""
    a = alpha.astype(np.float64)
    d = (F - B).astype(np.float64)
    den = np.maximum((d * d).sum(1), 1e-30)
    proj = ((I.astype(np.float64) - B) * d).sum(1) / den
    vp = (a * a * var_f.astype(np.float64).sum(1) + (1 - a) ** 2 * var_b.astype(np.float64).sum(1)) / den
    vm = model_sd * model_sd
    out = (a * vp + proj * vm) / (vp + vm)
    return np.clip(out, 0.0, 1.0).astype(np.float32)


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
