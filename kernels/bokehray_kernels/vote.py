"""The colour-weighted vote of the depth correction (``bokehray_refiner.depthfix.vote``): which side a suspect pixel joins.

One thread a suspect pixel, over its window (``Votes.offset_y``, ``offset_x``; spatial weight ``space``). Every trusted
window pixel inside the image votes with weight ``space * exp(-|colour step|^2 / (2 sigma_colour^2))`` for one of
three classes by its disparity relative to the pixel's own: the far side (less by more than ``snap``), the pixel's
own layer, the near side (more by more than ``snap``). A class is known where its spatial weights sum to
``min_class``; its affinity is its colour weight over its spatial weight. The pixel joins the side of the higher
affinity (far on ties) where that side is known and its affinity beats the rest by ``contrast`` and reaches
``min_affinity``, and where there is evidence on both sides of it (its own layer known, or both sides known, or
``one_sided``). It then takes the weighted median of that side's voters' disparities (:func:`side_median`).

Oracle: ``tests/reference/depthfix_ref.py`` (``vote_ref``).
"""

import warp as wp

wp.set_module_options({"enable_backward": False})

VOTE_NONE = wp.constant(-1)
"""``side`` of a pixel the vote leaves where it is."""
VOTE_FAR = wp.constant(0)
VOTE_NEAR = wp.constant(2)


@wp.struct
class Votes:
    """What a suspect pixel's vote reads: the photo, the map, the trusted pixels (nonzero), the window (offsets and
    their spatial weights), ``snap`` (a voter's disparity is on a side when it differs from the pixel's by more) and
    ``colour_scale`` (``-1 / (2 sigma_colour^2)``)."""

    image: wp.array2d(dtype=wp.vec3)
    disparity: wp.array2d(dtype=float)
    trusted: wp.array2d(dtype=wp.uint8)
    offset_y: wp.array(dtype=wp.int32)
    offset_x: wp.array(dtype=wp.int32)
    space: wp.array(dtype=float)
    snap: float
    colour_scale: float


@wp.struct
class VoteRule:
    """When a side wins (``bokehray_refiner.depthfix.DepthFixOptions``): ``min_class``, ``contrast``,
    ``min_affinity``, and ``one_sided`` (1: evidence of the winning side alone suffices)."""

    min_class: float
    contrast: float
    min_affinity: float
    one_sided: int


@wp.kernel
def vote_kernel(  # noqa: C901
    votes: Votes,
    pixel_y: wp.array(dtype=wp.int32),
    pixel_x: wp.array(dtype=wp.int32),
    rule: VoteRule,
    side: wp.array(dtype=wp.int32),
    value: wp.array(dtype=float),
):
    """``side[i]``: ``VOTE_FAR`` or ``VOTE_NEAR`` where suspect pixel ``i`` joins that side, else ``VOTE_NONE``;
    ``value[i]``: the disparity it takes there (else its own)."""
    i = wp.tid()
    h = votes.disparity.shape[0]
    w = votes.disparity.shape[1]
    y = pixel_y[i]
    x = pixel_x[i]
    c = votes.image[y, x]
    own = votes.disparity[y, x]
    seen_far = float(0.0)
    seen_own = float(0.0)
    seen_near = float(0.0)
    sim_far = float(0.0)
    sim_own = float(0.0)
    sim_near = float(0.0)
    for k in range(votes.offset_y.shape[0]):
        qy = y + votes.offset_y[k]
        qx = x + votes.offset_x[k]
        if qy >= 0 and qy < h and qx >= 0 and qx < w:
            if votes.trusted[qy, qx] != wp.uint8(0):
                sp = votes.space[k]
                diff = votes.image[qy, qx] - c
                wt = sp * wp.exp(wp.dot(diff, diff) * votes.colour_scale)
                rel = votes.disparity[qy, qx] - own
                if rel < -votes.snap:
                    seen_far += sp
                    sim_far += wt
                elif rel > votes.snap:
                    seen_near += sp
                    sim_near += wt
                elif wp.abs(rel) <= votes.snap:  # not NaN: a pixel without a disparity is of no class
                    seen_own += sp
                    sim_own += wt
    known_far = seen_far >= rule.min_class
    known_own = seen_own >= rule.min_class
    known_near = seen_near >= rule.min_class
    aff_far = float(0.0)
    aff_own = float(0.0)
    aff_near = float(0.0)
    if known_far:  # a class known with nothing seen (min_class <= 0) has affinity 0, not 0 / 0
        aff_far = sim_far / wp.max(seen_far, 1.0e-30)
    if known_own:
        aff_own = sim_own / wp.max(seen_own, 1.0e-30)
    if known_near:
        aff_near = sim_near / wp.max(seen_near, 1.0e-30)
    result = VOTE_NONE
    two_sided = known_own or (known_far and known_near) or rule.one_sided != 0
    if aff_far >= aff_near:
        if two_sided and known_far and aff_far >= rule.contrast * wp.max(aff_own, aff_near) \
                and aff_far >= rule.min_affinity:
            result = VOTE_FAR
    else:
        if two_sided and known_near and aff_near >= rule.contrast * wp.max(aff_own, aff_far) \
                and aff_near >= rule.min_affinity:
            result = VOTE_NEAR
    med = own
    if result != VOTE_NONE:
        med = side_median(votes, y, x, result == VOTE_NEAR)
        if wp.isnan(med):
            result = VOTE_NONE
            med = own
    side[i] = result
    value[i] = med


@wp.func
def _voter(votes: Votes, y: int, x: int, k: int, near: bool) -> wp.vec2:
    """Window pixel ``k`` of pixel ``(y, x)`` as a voter for the side ``near`` (or far): its weight and its
    disparity. The weight is 0 outside the image, where not trusted, and where the disparity is not on that side by
    more than ``snap``."""
    qy = y + votes.offset_y[k]
    qx = x + votes.offset_x[k]
    if qy < 0 or qy >= votes.disparity.shape[0] or qx < 0 or qx >= votes.disparity.shape[1]:
        return wp.vec2(0.0, 0.0)
    if votes.trusted[qy, qx] == wp.uint8(0):
        return wp.vec2(0.0, 0.0)
    v = votes.disparity[qy, qx]
    rel = v - votes.disparity[y, x]
    if near:
        if not (rel > votes.snap):
            return wp.vec2(0.0, 0.0)
    else:
        if not (rel < -votes.snap):
            return wp.vec2(0.0, 0.0)
    diff = votes.image[qy, qx] - votes.image[y, x]
    return wp.vec2(votes.space[k] * wp.exp(wp.dot(diff, diff) * votes.colour_scale), v)


@wp.func
def _side_range(votes: Votes, y: int, x: int, near: bool) -> wp.vec3:
    """The side's total weight, and its voters' smallest and largest value (total 0: no voter)."""
    total = float(0.0)
    lo = float(0.0)
    hi = float(0.0)
    for k in range(votes.offset_y.shape[0]):
        p = _voter(votes, y, x, k, near)
        if p[0] > 0.0:
            if total == 0.0:
                lo = p[1]
                hi = p[1]
            lo = wp.min(lo, p[1])
            hi = wp.max(hi, p[1])
            total += p[0]
    return wp.vec3(total, lo, hi)


@wp.func
def _split(votes: Votes, y: int, x: int, near: bool, lo: float, hi: float, lo_open: int, mid: float) -> wp.vec3:
    """One scan of the side at ``mid``: the weight of the values at most ``mid``, the largest such value (``lo``
    if none), and 1 if a value lies inside the interval ``(lo, hi)`` (``[lo, hi)`` while ``lo_open``), else 0."""
    below = float(0.0)
    top = lo
    inside = float(0.0)
    for k in range(votes.offset_y.shape[0]):
        p = _voter(votes, y, x, k, near)
        if p[0] > 0.0:
            if p[1] <= mid:
                below += p[0]
                top = wp.max(top, p[1])
            if p[1] < hi and (p[1] > lo or (lo_open == 1 and p[1] == lo)):
                inside = 1.0
    return wp.vec3(below, top, inside)


@wp.func
def _smallest_reaching(votes: Votes, y: int, x: int, near: bool, lo: float, hi: float, lo_open: int,
                       half: float) -> float:
    """By brute force, the smallest voter's value in ``(lo, hi]`` (``[lo, hi]`` while ``lo_open``) whose weight up
    to it reaches ``half``."""
    best = hi
    for k in range(votes.offset_y.shape[0]):
        p = _voter(votes, y, x, k, near)
        if p[0] > 0.0 and (p[1] > lo or (lo_open == 1 and p[1] == lo)) and p[1] < best:
            upto = _split(votes, y, x, near, lo, hi, 0, p[1])[0]
            if upto >= half:
                best = p[1]
    return best


@wp.func
def side_median(votes: Votes, y: int, x: int, near: bool) -> float:
    """The weighted median of the disparities of the side's voters: the smallest value whose weight, with that of
    all smaller values, reaches half the total (NaN where the total is 0). Found by halving a value interval that
    holds it, ``[lo, hi]`` at first, ``(lo, hi]`` once ``lo`` has moved, each step snapping ``hi`` down to a
    voter's value, until no voter's value lies strictly inside: no sort, no storage, a few scans of the window."""
    r = _side_range(votes, y, x, near)
    if r[0] <= 0.0:
        return wp.nan
    half = 0.5 * r[0]
    lo = r[1]
    hi = r[2]
    lo_open = int(1)
    for _step in range(64):
        mid = lo + 0.5 * (hi - lo)
        # lo and hi neighbouring floats (the halfway point rounds up to hi), or either infinite (it is NaN or
        # infinite): test lo itself
        if not wp.isfinite(mid) or mid >= hi:
            mid = lo
        s = _split(votes, y, x, near, lo, hi, lo_open, mid)
        if s[2] == 0.0:
            return hi
        if s[0] >= half:
            hi = s[1]  # the largest value at most mid: the weight up to it is the weight up to mid
            if lo_open == 1 and hi == lo:
                return hi
        else:
            lo = mid
            lo_open = 0
    # values that 64 halvings of the range could not part (powers of two apart, say): brute force
    return _smallest_reaching(votes, y, x, near, lo, hi, lo_open, half)
