"""Soft edges: split the mixed pixels at depth edges into a near and a far part (local linear-model matting).

A pixel on the edge of a near object holds both colours, ``I = alpha F + (1 - alpha) B``, but a disparity map
gives it one depth. :func:`split_mixed_pixels` finds those pixels and estimates ``alpha``, the decontaminated
foreground ``F`` and the background ``B`` behind it, so the layered scene (``bokehray.scene.SoftEdges``) can
blur the two parts with their own CoC. NumPy for the edges and the band, Warp kernels a band pixel
for the matting (``bokehray_kernels.matting``) and the split (``bokehray_kernels.split``):

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
   projection of the pixel's colour on its F-B line are fused by their inverse variances:
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

import bokehray_kernels.matting as bk_matting
import bokehray_kernels.split as bk_split
import numpy as np

from .edge_estimate import CHECK_ITEMS, MattingRule, edge_band, in_parts
from .errors import InputError, ResourceError
from .scene import SoftEdges
from .validate import check_finite

__all__ = ["SPLIT_B", "MattingRule", "check_split_fits", "split_mixed_pixels"]

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
              of the pixel's colour on the F-B line (whose variance is the spread of F's and B's samples carried
              through it); None: the model's alpha alone.
            * ``max_isolated_share``: a map where more than this share of the pixels differ by more than
              ``jump_px`` from all their neighbours is noise, not edges: nothing is split (a strand one pixel wide,
              even diagonal, has neighbours of its own depth along it).
            * ``light_level``, ``light_ratio``, ``light_reach``, ``light_thin``, ``light_share``: a far side
              brighter than ``light_level`` (mean of RGB, the photo's units: above a white surface, a light) and
              ``light_ratio`` times F, behind a near side under ``light_thin`` of the window's weight (a strand)
              whose F holds over ``light_share`` more of the light's colour than the F of its unlit samples out to
              ``light_reach`` px: F is that F and alpha the pixel's place on the line from B to it
              (``light_reach = 0``: never).
        device: the Warp device of the band's kernels.
        threads: CPU threads of the kernels (None: all cores); the result does not depend on it.
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
        pieces.append(_split_estimate(img, est, rule, device=device, threads=threads))
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


def _split_estimate(photo: np.ndarray, est, rule: MattingRule, *, device: str = "cpu",
                    threads: int | None = None) -> SoftEdges:
    """The split pixels among the band pixels of one edge estimate (``bokehray.edge_estimate.EdgeEstimate``):
    ``bokehray_kernels.split.split_kernel`` decides and splits each (steps 4b and 5 above), on the threads of
    :func:`~bokehray.edge_estimate.in_parts`; the split ones are gathered here."""
    import warp as wp

    band = est.band
    w = band.shape[1]
    y0, x0 = band.box[0], band.box[2]
    n = est.by.size
    dev = wp.get_device(device)
    copy = not dev.is_cpu  # on the CPU the kernel reads the (contiguous) arrays in place
    fields = {"alpha": (est.alpha, float), "fg": (est.fg, wp.vec3), "bg": (est.bg, wp.vec3),
              "fg_var": (est.fg_var, wp.vec3), "bg_var": (est.bg_var, wp.vec3), "near_coc": (est.near, float),
              "far_coc": (est.far, float), "flags": (est.flags, wp.int32)}
    image = wp.array(band.image, dtype=wp.vec3, device=dev, copy=copy)
    frame = wp.array(photo, dtype=wp.vec3, device=dev, copy=copy)
    params = _split_rule(rule, band)
    split = np.zeros(n, np.uint8)
    alpha, fg, bg = np.empty(n, np.float32), np.empty((n, 3), np.float32), np.empty((n, 3), np.float32)

    def launch(a: int, b: int) -> None:
        if b == a:
            return
        inp = bk_matting.BandEstimate()
        for name, (values, dtype) in fields.items():
            setattr(inp, name, wp.array(np.ascontiguousarray(values[a:b]), dtype=dtype, device=dev, copy=copy))
        out = bk_split.SplitOut()
        out.split, out.alpha = wp.empty(b - a, dtype=wp.uint8, device=dev), wp.empty(b - a, dtype=float, device=dev)
        out.fg, out.bg = wp.empty(b - a, dtype=wp.vec3, device=dev), wp.empty(b - a, dtype=wp.vec3, device=dev)
        wp.launch(bk_split.split_kernel, dim=b - a, device=dev,
                  inputs=[inp, image, frame, wp.array(est.by[a:b], dtype=wp.int32, device=dev),
                          wp.array(est.bx[a:b], dtype=wp.int32, device=dev), params, out])
        split[a:b], alpha[a:b], fg[a:b], bg[a:b] = (v.numpy() for v in (out.split, out.alpha, out.fg, out.bg))

    in_parts(n, launch, threads=threads, cpu=dev.is_cpu)
    k = np.flatnonzero(split)
    if k.size == 0:
        return SoftEdges.empty()
    index = (est.by[k] + y0).astype(np.int64) * w + (est.bx[k] + x0)  # row-major: sorted, unique
    return SoftEdges(index, alpha[k], fg[k], bg[k], est.near[k], est.far[k])


def _split_rule(rule: MattingRule, band) -> bk_split.SplitRule:
    p = bk_split.SplitRule()
    p.min_alpha, p.max_alpha, p.min_contrast = float(rule.min_alpha), float(rule.max_alpha), float(rule.min_contrast)
    p.model_sd = -1.0 if rule.model_sd is None else float(rule.model_sd)
    p.sharp = int(band.ramp == 0)  # a sharp map's labels are trusted: its projection must be mixed too
    p.scale = float(band.scale)
    p.y0, p.x0 = int(band.box[0]), int(band.box[2])
    return p
