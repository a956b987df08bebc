"""Colour-guided depth correction: move a misplaced depth edge onto the photo's colour edge.

Wrong disparity breaks a classical render mostly where a depth edge sits a few pixels away from the
colour edge of the object it belongs to (an eroded, dilated, smeared, shifted or estimated map). The
classical preview is exact where the disparity is right, so correcting the *disparity* near depth
edges and rendering again can be worth more than a learned residual on the image.

:func:`correct_disparity` works in three steps over the edge band only, NumPy/SciPy but for the vote (a Warp
kernel on the CPU, ``bokehray_kernels.vote``):

1. **Suspect pixels, per hypothesis.** Along the normal of every depth-edge pair (CoC jump >
   ``jump_px``) the colour step of the all-in-focus image is sampled on each side
   (:func:`colour_edge_offsets`). Where the strongest step on one side is clearly off the depth edge
   (the step on the edge over it, smoothed along the edge, below ``max_ratio``) and the stretch between
   edge and step looks like the *other* side of the edge, the pixels of that stretch are suspect
   (:func:`untrusted`): on the far side a too thin near region (erosion), on the near side a too fat one
   (dilation). A third hypothesis marks pixels inside a smeared edge (:func:`smeared`: the local largest
   and smallest disparity both differ from the pixel's by more than ``snap_px`` of CoC), only on a map
   whose edges the edge estimate the matting shares (``bokehray.edge_estimate.ramp_width``) measures as
   ramps: on a map of steps a pixel between two depths is a third surface.
2. **A colour vote of the trusted pixels.** For each suspect pixel, the other pixels within
   ``radius_px`` vote, weighted by colour similarity and distance, in three classes relative to the
   pixel's own disparity (farther, the same within ``snap_px`` of CoC, nearer). The pixel moves to the
   weighted median of the farther or nearer class only where that class is clearly more similar in
   colour (``contrast``, ``min_affinity``) and the evidence is two-sided (its own layer is seen among the
   trusted pixels, or both other classes are): a thin structure whose every pixel is suspect (a 2 px wire
   with nothing of its colour around) is left alone.
3. ``iterations`` passes, each from the corrected map.

Every output value is a disparity of the input within ``radius_px`` of the pixel (a median of
neighbours), so the correction never invents a disparity outside the local range; pixels that do not
move keep their input values bit for bit. The slow obvious reference is
``tests/reference/depthfix_ref.py`` (pixel by pixel, pair by pair); tests compare the two.
"""

from __future__ import annotations

from dataclasses import dataclass

import bokehray_kernels.vote as bk_vote
import numpy as np

from bokehray.edge_estimate import depth_edges, in_parts, ramp_width

__all__ = ["DepthFixOptions", "colour_edge_offsets", "correct_disparity", "correction_steps", "edge_pairs",
           "global_shift", "has_ramps", "pass_reach", "shift_map", "smeared", "step_flips", "untrusted", "vote",
           "vote_sides"]


@dataclass(frozen=True)
class DepthFixOptions:
    """Parameters of the colour-guided depth correction (docs/refiner.md).

    Args:
        enabled: False leaves the disparity as it is.
        jump_px: a depth edge is a pair of 4-neighbours whose CoC differs by more than this.
        band_px: how far across a depth edge the colour edge is searched (and pixels may be corrected).
        radius_px: the vote's window radius (a disc).
        step_px: the window is sampled on a grid of this pitch (1: every pixel).
        sigma_colour: colour similarity scale (sRGB, Euclidean over RGB).
        sigma_space_px: spatial fall-off of the votes.
        min_class: a class of voters is "seen" when its spatial weights sum to at least this.
        contrast: the winning class's mean colour similarity must exceed every other seen class's by this factor.
        min_affinity: and be at least this.
        snap_px: classes are relative to the pixel's own disparity, in CoC pixels.
        iterations: passes (each recomputes the edges from the corrected map).
        min_step: colour steps (sRGB, Euclidean) below this are no colour edge.
        min_score: how much more (colour distance) the stretch must look like the other side than like beyond.
        max_edge_share: a map with depth edges at more than this share of its pixels whose consecutive steps flip
            sign (:func:`step_flips` > 1/2) is left alone: that is noise in the disparity (an edge on nearly every
            pixel), not edges a few pixels off their colour edge, and the vote would cost 10-40x the preview for
            nothing (it moved no pixel on such maps). A blurred or estimated map can
            have steps on more than this share too (the dev set's wire mesh at K = 32: 42-47 %), but its steps
            agree along each ramp (flips <= 4 %; noise 72-89 %), and it is corrected.
        ramp_px: half-width of the window of the smeared-edge hypothesis (0: off).
        thin_dilated: under the dilation hypothesis a pixel may move without its own layer among the
            voters (a dilated thin structure, whose every pixel is suspect).
        incremental: passes after the first recompute only the neighbourhood (:func:`pass_reach`) of the pixels
            the pass before moved: the same result as a pass over the whole map (tested), at a fraction of its cost.
        max_shift_px: a misregistered map (the whole map shifted against the photo, as a depth sensor or an
            estimator's resampling can leave it) is searched for up to this many pixels per axis and shifted back
            first (:func:`global_shift`; 0: off).
        shift_gain: a shift along an axis is taken only where it makes the colour step across the depth edges at
            least this much stronger on *both* sides of the objects (depth edges whose near side lies before and
            after along that axis): an eroded or dilated map also gains on one side from a shift, never on both.
        min_shift_pairs: each side needs at least this many depth-edge pairs along the axis.
        max_ratio: a colour edge counts as off the depth edge where (step on the edge) / (strongest step) is below.
        sigma_edge_px: smoothing along the edge of the ratio, the score and the offset.
        ramps_only: look for smeared edges (``ramp_px``) only on a map whose edges the matting's shared edge
            estimate measures as ramps (``bokehray.edge_estimate.ramp_width`` > 0, with its ``max_ramp_px``): on a
            map whose edges are steps every pixel between two depths is a third surface, not a ramp (the dev set's
            exact maps: this alone moved 145 of the 197 pixels the fix moved on the wire mesh, -0.25 dB there).
    """

    enabled: bool = True
    jump_px: float = 1.0
    band_px: float = 6.0
    radius_px: float = 8.0
    step_px: int = 1
    sigma_colour: float = 0.08
    sigma_space_px: float = 4.0
    min_class: float = 1.0
    contrast: float = 1.5
    min_affinity: float = 0.2
    snap_px: float = 1.0
    iterations: int = 2
    min_step: float = 0.03
    min_score: float = 0.0
    max_edge_share: float = 0.4
    ramp_px: int = 3
    thin_dilated: bool = True
    incremental: bool = True
    max_shift_px: int = 3
    shift_gain: float = 1.25
    min_shift_pairs: int = 64
    max_ratio: float = 0.5
    sigma_edge_px: float = 3.0
    ramps_only: bool = True
    max_ramp_px: int = 6


def _offsets(options: DepthFixOptions) -> np.ndarray:
    r = int(np.floor(options.radius_px))
    s = max(1, int(options.step_px))
    g = np.arange(-(r // s) * s, r + 1, s)
    oy, ox = np.meshgrid(g, g, indexing="ij")
    keep = oy ** 2 + ox ** 2 <= options.radius_px ** 2
    return np.stack([oy[keep], ox[keep]], 1)


def edge_pairs(coc: np.ndarray, jump_px: float) -> list[tuple[np.ndarray, np.ndarray, int]]:
    """Per axis, the ``(ys, xs, axis)`` of pixels ``a`` whose pair ``(a, a + e_axis)`` is a depth edge."""
    out = []
    for ax in (0, 1):
        ys, xs = np.nonzero(np.abs(np.diff(coc, axis=ax)) > jump_px)
        out.append((ys, xs, ax))
    return out


def colour_edge_offsets(focus_srgb: np.ndarray, disparity: np.ndarray, pairs, radius_px: float):
    """Where the strongest colour step lies on each side of each depth-edge pair, along the edge's normal.

    For every pair ``(a, a + e_axis)`` it samples the sRGB colour step ``|f(t + 1/2) - f(t - 1/2)|``
    (bilinear, Euclidean over RGB) at ``t`` in ``[-radius_px, radius_px]`` (half-pixel steps) along the
    normal of the depth edge (the gradient of the lightly smoothed disparity, turned towards the pair's
    near pixel), ``t = 0`` on the edge.

    Returns ``(my, mx, uy, ux, t_far, r_far, s_far, c_far, t_near, r_near, s_near, c_near)`` per pair: the
    midpoint, the unit normal, and per side (far: ``t <= 0``, near: ``t >= 0``) the offset of the strongest
    step, the strongest step within half a pixel of the edge divided by that side's strongest, that strongest
    step, and how much more the stretch between edge and step looks like the other side of the edge than like
    what lies beyond the step (colour distances; > 0: like the other side).
    """
    from scipy import ndimage

    d = ndimage.gaussian_filter(disparity.astype(np.float32), 1.0)
    gy, gx = ndimage.sobel(d, 0), ndimage.sobel(d, 1)
    steps = np.arange(-radius_px, radius_px + 1e-6, 0.5, dtype=np.float32)
    at_edge = np.abs(steps) <= 0.5 + 1e-6
    far, near = steps <= 0.5 + 1e-6, steps >= -0.5 - 1e-6
    offs = np.concatenate([steps - 0.5, steps[-1:] + 0.5])
    # float64 samples of the float32 image: the argmax of nearly equal steps must not depend on rounding
    chans = [np.ascontiguousarray(focus_srgb[..., c], np.float32).astype(np.float64) for c in range(3)]
    cols = [[] for _ in range(12)]
    for ys, xs, axis in pairs:
        if ys.size == 0:
            continue
        my = ys + (0.5 if axis == 0 else 0.0)
        mx = xs + (0.5 if axis == 1 else 0.0)
        ny, nx = ys + (axis == 0), xs + (axis == 1)
        sign = np.where(disparity[ny, nx] >= disparity[ys, xs], 1.0, -1.0)  # towards the pair's near pixel
        gyy = (gy[ys, xs].astype(np.float64) + gy[ny, nx]) * 0.5
        gxx = (gx[ys, xs].astype(np.float64) + gx[ny, nx]) * 0.5
        along = gyy * (axis == 0) + gxx * (axis == 1)  # the gradient must point to the pair's near pixel
        nn = np.hypot(gyy, gxx)
        flat = (nn <= 1e-12) | (along * sign <= 0)
        uy = np.where(flat, sign * (axis == 0), gyy / np.where(nn > 0, nn, 1.0))
        ux = np.where(flat, sign * (axis == 1), gxx / np.where(nn > 0, nn, 1.0))
        py = my[:, None] + offs[None, :] * uy[:, None]
        px = mx[:, None] + offs[None, :] * ux[:, None]
        coords = np.stack([py.ravel(), px.ravel()])
        samp = np.stack([ndimage.map_coordinates(c, coords, order=1, mode="nearest").reshape(py.shape)
                         for c in chans], -1)
        step = np.sqrt((np.diff(samp.astype(np.float64), axis=1) ** 2).sum(-1))
        on = step[:, at_edge].max(axis=1)
        out = [my, mx, uy, ux]
        rows = np.arange(ys.size)

        def colour(pos, samp=samp, rows=rows):  # the sampled colour nearest to offset ``pos`` along the normal
            j = np.clip(np.rint((pos - offs[0]) / 0.5).astype(np.int64), 0, offs.size - 1)
            return samp[rows, j].astype(np.float64)

        dist = lambda a, b: np.sqrt(((a - b) ** 2).sum(-1))  # noqa: E731
        for side, sg in ((far, -1.0), (near, 1.0)):
            sub = step[:, side]
            best = sub.max(axis=1)
            t = steps[side][np.argmax(sub, axis=1)]
            # does the stretch between the edge and that colour step look like the *other* side of the edge
            # (what an erosion or dilation of the map would leave there) more than like what lies beyond it?
            mid = colour(t * 0.5)
            score = dist(mid, colour(t + sg * 1.0)) - dist(mid, colour(-sg * 1.0))
            out += [t, on / np.maximum(best, 1e-12), best, score]
        for c, v in zip(cols, out):
            c.append(np.asarray(v, np.float64))
    if not cols[0]:
        return tuple(np.zeros(0, np.float64) for _ in range(12))
    return tuple(np.concatenate(c) for c in cols)


def untrusted(focus_srgb: np.ndarray, disparity: np.ndarray, k_px: float,
              options: DepthFixOptions = DepthFixOptions()) -> tuple[np.ndarray, np.ndarray]:
    """Where the disparity is suspect: between a depth edge and a colour edge displaced from it, per side.

    Returns two masks. *Far side* (the near region may be too thin: eroded, shifted, smeared): at each
    depth-edge pair whose strongest colour step on the far side is strong (``min_step``) and clearly off the
    edge (the step on the edge over it, smoothed along the edge, below ``max_ratio``), the pixels along the
    normal from the edge to that colour step (its offset smoothed along the edge, plus half a pixel).
    *Near side* (the near region may be too fat): the same on the near side. The other side of the edge stays
    trusted: it is the side such an error did not touch.
    """
    from scipy import ndimage

    h, w = disparity.shape
    masks = (np.zeros((h, w), bool), np.zeros((h, w), bool))
    pairs = edge_pairs(np.float32(k_px) * disparity, options.jump_px)
    my, mx, uy, ux, *sides = colour_edge_offsets(focus_srgb, disparity, pairs, options.band_px)
    if my.size == 0:
        return masks
    iy = np.clip(np.floor(my).astype(np.int64), 0, h - 1)
    ix = np.clip(np.floor(mx).astype(np.int64), 0, w - 1)
    flat = iy * w + ix
    # the Gaussian is computed on the pairs' bounding box plus its truncation radius: outside it every input is 0,
    # so the values read at the pairs are the whole frame's bit for bit (only their box costs)
    r = int(4.0 * float(options.sigma_edge_px) + 0.5)  # scipy's truncate = 4
    y0, y1 = max(0, int(iy.min()) - r), min(h, int(iy.max()) + r + 1)
    x0, x1 = max(0, int(ix.min()) - r), min(w, int(ix.max()) + r + 1)

    def blurred(v):  # the splatted values, smoothed, read back at the pairs
        grid = np.bincount(flat, weights=v, minlength=h * w).reshape(h, w)  # adds in order, like np.add.at
        return ndimage.gaussian_filter(grid[y0:y1, x0:x1], options.sigma_edge_px)[iy - y0, ix - x0]

    ones = np.ones(my.size)
    den1 = np.maximum(blurred(ones), 1e-12)  # the weights of an unweighted smoothing: shared

    def smooth(v, wt=None):  # normalised convolution over the edge pairs
        if wt is None:
            return blurred(v * ones) / den1
        return blurred(v * wt) / np.maximum(blurred(wt), 1e-12)

    ss = np.arange(0.5, options.band_px + 1.0, 0.5)
    scores = [smooth(sides[3].astype(np.float64)), smooth(sides[7].astype(np.float64))]
    for k, (mask, (t, ratio, strength, _)) in enumerate(zip(masks, (sides[0:4], sides[4:8]))):
        strong = strength >= options.min_step
        r_s = smooth(np.where(strong, ratio, 1.0).astype(np.float64))
        mine, other = scores[k], scores[1 - k]
        act = strong & (r_s < options.max_ratio) & (mine > options.min_score) & (mine > other)
        if not act.any():
            continue
        t_s = smooth(t.astype(np.float64), act.astype(np.float64))
        ok = act & (np.abs(t_s) >= 0.75)
        sgn = np.sign(t_s[ok])
        use = ss[None, :] <= (np.abs(t_s[ok]) + 0.5)[:, None]
        py = my[ok, None] + (sgn[:, None] * ss[None, :]) * uy[ok, None]
        px = mx[ok, None] + (sgn[:, None] * ss[None, :]) * ux[ok, None]
        # pixel centres are at integer coordinates: a sample belongs to the nearest centre
        mask[np.clip(np.rint(py[use]).astype(np.int64), 0, h - 1),
             np.clip(np.rint(px[use]).astype(np.int64), 0, w - 1)] = True
    return masks


def smeared(disparity: np.ndarray, k_px: float, options: DepthFixOptions = DepthFixOptions()) -> np.ndarray:
    """Pixels inside a smeared depth edge: both the largest and the smallest disparity within ``ramp_px``
    (a square window) differ from the pixel's own by more than ``snap_px`` of CoC (a blurred or estimated
    map's ramp; a surface tilted less steeply than that is left alone)."""
    from scipy import ndimage

    size = 2 * int(options.ramp_px) + 1
    snap = options.snap_px / float(k_px)
    d = disparity.astype(np.float64)
    hi = ndimage.maximum_filter(d, size, mode="nearest")
    lo = ndimage.minimum_filter(d, size, mode="nearest")
    return (hi - d > snap) & (d - lo > snap)


@dataclass(frozen=True, eq=False)
class Voting:
    """What every vote of one correction reads: the window (offsets, nearest first, and their spatial weights),
    ``snap`` (a disparity difference below it is the pixel's own layer), the options and the blur's ``k_px``."""

    offs: np.ndarray
    space: np.ndarray
    snap: float
    options: DepthFixOptions
    k_px: float = 0.0


def vote(voting: Voting, img, cur, sus, new, keep=None, one_sided=False, targets=None):
    """Colour-weighted vote of the trusted pixels (not ``sus``, not ``keep``) for every pixel of ``sus``
    (not ``keep``; only those of ``targets`` when given); writes ``new``. Which side each pixel joins is
    ``bokehray_kernels.vote.vote_kernel``'s (:func:`vote_sides`), and so is the value it takes there, the weighted
    median of that side's voters."""
    trusted = ~sus if keep is None else ~(sus | keep)
    voters = sus if keep is None else sus & ~keep
    ys, xs = np.nonzero(voters if targets is None else voters & targets)
    if ys.size == 0:
        return
    side, value = vote_sides(voting, img, cur, trusted, ys, xs, one_sided)
    moves = side != bk_vote.VOTE_NONE
    new[ys[moves], xs[moves]] = value[moves]


def vote_sides(voting: Voting, img, cur, trusted, ys, xs, one_sided=False,
               threads=None) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel ``(ys, xs)``, the side the vote moves it to (``bokehray_kernels.vote``: ``VOTE_FAR``,
    ``VOTE_NEAR``, or ``VOTE_NONE``) and the disparity it takes (its own where it stays), on the CPU in ``threads``
    parts (Warp CPU launches release the GIL). ``img`` is ``H x W x 3``, ``cur`` and ``trusted`` ``H x W``, ``cur``
    float32 (the kernel reads them unchecked)."""
    import warp as wp

    if img.shape != cur.shape + (3,) or trusted.shape != cur.shape or cur.dtype != np.float32:
        raise ValueError(f"vote: image {img.shape}, map {cur.shape} {cur.dtype} and trusted pixels {trusted.shape} "
                         "must be H x W x 3, H x W float32 and H x W")

    dev = wp.get_device("cpu")
    options = voting.options
    votes = bk_vote.Votes()
    votes.image = wp.array(np.ascontiguousarray(img, np.float32), dtype=wp.vec3, device=dev, copy=False)
    votes.disparity = wp.array(np.ascontiguousarray(cur, np.float32), dtype=float, device=dev, copy=False)
    votes.trusted = wp.array(np.ascontiguousarray(trusted, bool).view(np.uint8), dtype=wp.uint8, device=dev,
                             copy=False)
    votes.offset_y = wp.array(voting.offs[:, 0].astype(np.int32), dtype=wp.int32, device=dev)
    votes.offset_x = wp.array(voting.offs[:, 1].astype(np.int32), dtype=wp.int32, device=dev)
    votes.space = wp.array(np.asarray(voting.space, np.float32), dtype=float, device=dev)
    votes.snap, votes.colour_scale = float(voting.snap), float(-1.0 / (2.0 * options.sigma_colour ** 2))
    rule = bk_vote.VoteRule()
    rule.min_class, rule.contrast, rule.min_affinity = (float(options.min_class), float(options.contrast),
                                                        float(options.min_affinity))
    rule.one_sided = int(bool(one_sided))

    def launch(a: int, b: int) -> tuple[np.ndarray, np.ndarray]:
        side, value = wp.empty(b - a, dtype=wp.int32, device=dev), wp.empty(b - a, dtype=float, device=dev)
        if b > a:
            wp.launch(bk_vote.vote_kernel, dim=b - a,
                      inputs=[votes, wp.array(ys[a:b].astype(np.int32), dtype=wp.int32, device=dev),
                              wp.array(xs[a:b].astype(np.int32), dtype=wp.int32, device=dev), rule],
                      outputs=[side, value], device=dev)
        return side.numpy(), value.numpy()

    parts = in_parts(ys.size, launch, threads=threads)
    return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])


def step_flips(coc: np.ndarray, jump_px: float) -> float:
    """Of the pairs of consecutive CoC steps (along either axis) that both exceed ``jump_px``, the share whose signs
    differ. Noise flips (two consecutive differences of independent noise have opposite signs two times in three),
    a smooth ramp does not (a blurred or estimated map's steps agree along the ramp): 0 without such pairs."""
    num = den = 0
    for ax in (0, 1):
        dd = np.diff(coc, axis=ax)
        a = np.take(dd, range(dd.shape[ax] - 1), axis=ax)
        b = np.take(dd, range(1, dd.shape[ax]), axis=ax)
        both = (np.abs(a) > jump_px) & (np.abs(b) > jump_px)
        num += int((both & (np.sign(a) != np.sign(b))).sum())
        den += int(both.sum())
    return num / den if den else 0.0


def global_shift(focus_srgb: np.ndarray, disparity: np.ndarray, k_px: float,  # noqa: C901
                 options: DepthFixOptions = DepthFixOptions()) -> tuple[int, int]:
    """The integer shift ``(sy, sx)`` that moves the map's depth edges onto the photo's colour edges, or (0, 0).

    Per axis, the depth-edge pairs across it (CoC jump > ``jump_px``; farther than ``max_shift_px`` from the
    border) are split by the side their near pixel lies on (before / after along the axis: the two sides of an
    object). For each shift ``s`` in ``[-max_shift_px, max_shift_px]`` the mean colour step (sRGB, Euclidean)
    across the pair moved by ``s`` is measured on each side. The best shift is taken only where *both* sides'
    steps gain at least ``shift_gain`` over no shift: a map misregistered by ``s`` has every edge ``s`` off, an
    eroded or dilated one has its two sides off in opposite directions, so no single shift helps both.
    Moving the map by ``(sy, sx)`` (``out[y, x] = d[y - sy, x - sx]``) puts the depth edges on the colour edges.
    """
    m = int(options.max_shift_px)
    h, w = disparity.shape
    if m <= 0 or h <= 2 * m + 1 or w <= 2 * m + 1:
        return 0, 0
    img = np.asarray(focus_srgb[..., :3], np.float32)
    coc = np.float32(k_px) * np.asarray(disparity, np.float32)
    groups = []  # per axis and side: the pairs' first pixels
    for ys, xs, ax in edge_pairs(coc, options.jump_px):
        ok = (ys >= m) & (ys < h - 1 - m) & (xs >= m) & (xs < w - 1 - m)
        ys, xs = ys[ok], xs[ok]
        after = coc[ys + (ax == 0), xs + (ax == 1)] > coc[ys, xs]  # the near pixel lies after the edge along the axis
        for side in (after, ~after):
            gy, gx = ys[side], xs[side]
            if gy.size > 20000:  # a regular subsample bounds the cost on large frames
                k = -(-gy.size // 20000)
                gy, gx = gy[::k], gx[::k]
            groups.append((gy, gx, ax))
    if min(g[0].size for g in groups) < options.min_shift_pairs:
        return 0, 0
    n = 2 * m + 1
    prof = np.zeros((4, n, n))  # per group, per shift (sy, sx): the mean colour step across the moved pairs
    for gi, (gy, gx, ax) in enumerate(groups):
        for iy in range(n):
            for ix in range(n):
                y0, x0 = gy + (iy - m), gx + (ix - m)
                d = img[y0 + (ax == 0), x0 + (ax == 1)].astype(np.float64) - img[y0, x0]
                prof[gi, iy, ix] = np.sqrt((d ** 2).sum(-1)).mean()
    score = np.exp(np.log(np.maximum(prof, 1e-12)).mean(0))  # all four groups must gain: their geometric mean
    by, bx = np.unravel_index(int(np.argmax(score)), score.shape)
    if (by, bx) == (m, m):
        return 0, 0
    gain = prof[:, by, bx] / np.maximum(prof[:, m, m], 1e-12)
    # the axes the shift moves along must gain on both sides of the objects; none may lose
    need = [gi for gi, (_, _, ax) in enumerate(groups) if (by - m, bx - m)[ax] != 0]
    if (gain[need] < options.shift_gain).any() or (gain < 1.0).any():
        return 0, 0
    for gi in need:  # and each side's own best shift along its axis must be this one (within a pixel): an eroded
        ax = groups[gi][2]  # or dilated map's two sides peak at opposite shifts
        peak = np.unravel_index(int(np.argmax(prof[gi])), (n, n))[ax]
        if abs(int(peak) - int((by, bx)[ax])) > 1:
            return 0, 0
    return int(by - m), int(bx - m)


def shift_map(disparity: np.ndarray, sy: int, sx: int) -> np.ndarray:
    """``out[y, x] = d[y - sy, x - sx]``, the border continued (edge values)."""
    if sy == 0 and sx == 0:
        return np.asarray(disparity, np.float32).copy()
    p = max(abs(sy), abs(sx))
    h, w = disparity.shape
    return np.pad(np.asarray(disparity, np.float32), p, mode="edge")[p - sy:p - sy + h, p - sx:p - sx + w].copy()


def pass_reach(options: DepthFixOptions) -> int:
    """How far (Chebyshev px) one pass's result at a pixel depends on the map: the vote's window, the suspect
    stretch along an edge's normal, the smoothing along the edge (scipy truncates its Gaussian at 4 sigma), the
    edge normal (Gaussian of 1 px truncated at 4, then Sobel) and the pair itself, the smeared-edge window, plus
    a margin of 4 px."""
    return (int(np.ceil(options.radius_px)) + int(np.ceil(options.band_px)) + 2
            + int(4.0 * float(options.sigma_edge_px) + 0.5) + 6 + int(options.ramp_px) + 4)


def has_ramps(disparity: np.ndarray, k_px: float, options: DepthFixOptions = DepthFixOptions()) -> bool:
    """Whether the smeared-edge hypothesis applies to the map: always without ``ramps_only``, else where the
    shared edge estimate (``bokehray.edge_estimate.ramp_width``, the matting's measure of how many pixels a depth
    edge's CoC ramp spans) finds ramps."""
    if not options.ramps_only:
        return True
    coc = np.float32(k_px) * np.asarray(disparity, np.float32)
    return ramp_width(coc, options.jump_px, options.max_ramp_px) > 0


def _pass(voting: Voting, img, cur, active, keep, new, targets, ramps):
    """One pass of the correction on ``cur``, written into ``new``; only pixels of ``targets`` (None: all) vote;
    ``ramps``: :func:`has_ramps` of the map as given."""
    options, k_px = voting.options, voting.k_px
    hyps = list(untrusted(img, cur, k_px, options))
    if options.ramp_px > 0 and ramps:
        hyps.append(smeared(cur, k_px, options))
    for h_i, sus in enumerate(hyps):  # each hypothesis with its own trusted pixels
        if active is not None:
            sus &= active
        if sus.any():
            vote(voting, img, cur, sus, new, keep, one_sided=options.thin_dilated and h_i == 1, targets=targets)


def correct_disparity(focus_srgb: np.ndarray, disparity: np.ndarray, k_px: float,
                      options: DepthFixOptions = DepthFixOptions(),
                      active: np.ndarray | None = None,
                      keep: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The disparity with depth edges moved onto the colour edges, and the mask of changed pixels.

    Args:
        focus_srgb: ``H x W x 3`` all-in-focus image, sRGB in [0, 1].
        disparity: ``H x W`` in [0, 1].
        k_px: the blur's ``K`` (CoC radius per unit disparity): edges and thresholds are in CoC pixels.
        active: optional ``H x W`` bool, where corrections are allowed (with it, no global shift is searched).
        keep: optional ``H x W`` bool, pixels that neither change nor vote (clipped lights: their sRGB colour
            says nothing about them, and a light moved to another depth moves its whole bokeh ball).

    Every output value is one of the input's values within ``radius_px`` (a median of trusted neighbours),
    so the correction never invents a disparity outside the local range.
    """
    shift, _shifted, out = correction_steps(focus_srgb, disparity, k_px, options, active, keep)
    if shift is None:  # it did not run: nothing moved (NaN pixels included)
        return out, np.zeros(out.shape, bool)
    return out, out != np.asarray(disparity, np.float32)  # moved by the passes or by the shift, and not back


def correction_steps(focus_srgb: np.ndarray, disparity: np.ndarray, k_px: float,
                     options: DepthFixOptions = DepthFixOptions(), active: np.ndarray | None = None,
                     keep: np.ndarray | None = None) -> tuple[tuple[int, int] | None, np.ndarray, np.ndarray]:
    """:func:`correct_disparity` in its two steps: the global shift found (``(0, 0)``: none; None: the correction
    did not run, being off, or the map being noise rather than misplaced edges), the map shifted back by it, and that
    map after the local passes (the corrected disparity). Those who weigh the local passes' moves (``refine``'s
    map-level gate) need them apart from the shift, which moves every pixel."""
    d = np.asarray(disparity, np.float32)
    out = d.copy()
    if not options.enabled or k_px <= 0:
        return None, out, out
    from scipy import ndimage

    img = np.ascontiguousarray(focus_srgb[..., :3], np.float32)
    offs = _offsets(options)
    space = np.exp(-(offs ** 2).sum(1) / (2.0 * options.sigma_space_px ** 2))
    h, w = d.shape
    coc = d * np.float32(k_px)
    if depth_edges(coc, options.jump_px).mean() > options.max_edge_share and step_flips(coc, options.jump_px) > 0.5:
        return None, out, out  # noise in the map, not misplaced edges
    snap = options.snap_px / float(k_px)
    sy, sx = global_shift(img, d, k_px, options) if active is None else (0, 0)  # a shift moves every pixel
    if sy or sx:  # a misregistered map: shifted back first, all of it (lights too: the whole map was off)
        out = shift_map(d, sy, sx)
    shifted = out
    ramps = has_ramps(out, k_px, options)  # of the map as given (shifted back): the passes do not change it
    voting = Voting(offs, space, snap, options, float(k_px))
    todo = None  # the first pass looks at the whole map, later ones only where the last one moved pixels
    reach = pass_reach(options)
    for _ in range(max(1, options.iterations)):
        cur = out
        new = cur.copy()
        if todo is None:
            _pass(voting, img, cur, active, keep, new, None, ramps)
        else:
            # a pixel farther than ``reach`` from every pixel the last pass moved sees the same inputs as in that
            # pass and so gives the same (unmoved) value: each cluster of moved pixels is recomputed on its window,
            # cut ``reach`` wider so that the window's border cannot change what the cluster's pixels see
            lab, _n = ndimage.label(todo, structure=np.ones((3, 3), bool))
            for n_c, (cy, cx) in enumerate(ndimage.find_objects(lab), start=1):
                wy = slice(max(0, cy.start - reach), min(h, cy.stop + reach))
                wx = slice(max(0, cx.start - reach), min(w, cx.stop + reach))
                mine = lab[wy, wx] == n_c
                part = cur[wy, wx].copy()
                _pass(voting, img[wy, wx], cur[wy, wx], None if active is None else active[wy, wx],
                      None if keep is None else keep[wy, wx], part, mine, ramps)
                new[wy, wx][mine] = part[mine]
        moved = new != cur
        if not moved.any():
            break
        out = new
        if options.incremental:
            todo = ndimage.maximum_filter(moved, size=2 * reach + 1, mode="constant")
    return (int(sy), int(sx)), shifted, out
