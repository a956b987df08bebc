"""``bokehray_kernels.vote.vote_kernel`` (through ``bokehray_refiner.depthfix.vote``) against its float64 oracle
(``reference.depthfix_ref.vote_ref``): random layered maps with texture, suspect and kept pixels, both vote modes;
and the weighted median where the side's values are ties, and where they lie closer than the halving can part."""

import bokehray_kernels.vote as bk_vote
import numpy as np
import pytest
from bokehray_refiner.depthfix import DepthFixOptions, Voting, _offsets, vote, vote_sides
from hypothesis import given
from hypothesis import strategies as st
from reference.depthfix_ref import vote_ref, weighted_median_ref
from scipy import ndimage

OPTIONS = DepthFixOptions()


def _window(options=OPTIONS):
    offs = _offsets(options)
    return offs, np.exp(-(offs ** 2).sum(1) / (2.0 * options.sigma_space_px ** 2))


def _both(img, cur, sus, snap, keep=None, one_sided=False, options=OPTIONS):
    """The kernel's vote and the oracle's, each written over a copy of ``cur``."""
    offs, space = _window(options)
    got, want = cur.copy(), cur.copy()
    vote(Voting(offs, space, snap, options), img, cur, sus, got, keep, one_sided=one_sided)
    vote_ref(img, cur, sus, snap, options, want, keep, one_sided=one_sided)
    return got, want


@given(seed=st.integers(0, 2**16), h=st.integers(4, 28), w=st.integers(4, 28), levels=st.integers(2, 5),
       shift=st.integers(0, 3), noisy=st.booleans(), with_keep=st.booleans(), one_sided=st.booleans(),
       holes=st.booleans())
def test_the_vote_matches_the_oracle(seed, h, w, levels, shift, noisy, with_keep, one_sided, holes):
    rng = np.random.default_rng(seed)
    # blocky layers of a few disparities, each with its own colour and texture; the map's layers lie ``shift`` px
    # off the colour's, and the pixels near its depth edges are suspect: pixels to move, and pixels to leave
    lab = np.kron(rng.integers(0, levels, (-(-h // 4), -(-w // 4))), np.ones((4, 4), int))[:h, :w]
    depth = rng.uniform(0, 1, levels).astype(np.float32)
    colour = rng.uniform(0, 1, (levels, 3))
    cur = depth[np.roll(lab, (shift, -shift), (0, 1))]
    if noisy:  # distinct values: no ties in the medians
        cur = cur + rng.normal(0, 0.005, (h, w)).astype(np.float32)
    if holes:  # pixels without a disparity: of no class, never a median
        cur = np.where(rng.uniform(size=(h, w)) < 0.05, np.float32(np.nan), cur)
    img = np.clip(colour[lab] + rng.normal(0, 0.05, (h, w, 3)), 0, 1).astype(np.float32)
    edges = (np.abs(np.diff(cur, axis=0, prepend=cur[:1])) > 0.05) | (np.abs(np.diff(cur, axis=1, prepend=cur[:, :1])) > 0.05)
    sus = ndimage.binary_dilation(edges, iterations=3) & (rng.uniform(size=(h, w)) < 0.8)
    keep = rng.uniform(size=(h, w)) < 0.1 if with_keep else None
    got, want = _both(img, cur.astype(np.float32), sus, 1.0 / 16.0, keep, one_sided)
    np.testing.assert_array_equal(got, want)


def test_the_vote_moves_a_misplaced_strip():
    """A strip of the near layer's colour that the map puts on the far side joins the near side (and takes the
    near value); so the comparison above covers pixels that move, not only pixels left alone."""
    h, w = 24, 24
    near = np.zeros((h, w), bool)
    near[:, :12] = True
    img = np.where(near[..., None], [0.9, 0.2, 0.1], [0.1, 0.3, 0.8]).astype(np.float32)
    cur = np.where(near, 0.8, 0.2).astype(np.float32)
    cur[:, 9:12] = 0.2  # the map's edge 3 px off the colour edge
    sus = np.zeros((h, w), bool)
    sus[:, 8:14] = True
    got, want = _both(img, cur, sus, 1.0 / 16.0)
    np.testing.assert_array_equal(got, want)
    assert (got[:, 9:12] == np.float32(0.8)).all()


@pytest.mark.parametrize("values", [
    np.repeat(np.float32([0.05, 0.1, 0.15]), 40),  # ties: the median is one of three values
    np.float32([0.0, 1e-30, 2e-30, 3e-30, 0.3]),  # values far apart in scale
    # powers of two, the smallest nearest (the heaviest): more than 64 halvings from the range to the median
    np.float32(2.0) ** -np.arange(120, 0, -1, dtype=np.float32),
    np.full(6, 0.2, np.float32),  # one value
    # neighbouring floats, the smaller heavier: the halfway point between them rounds to the larger
    np.float32([np.nextafter(np.float32(0.5), np.float32(0))] * 3 + [0.5] * 2),
    np.float32([-np.inf, 0.1, 0.1, 0.1, 0.2]),  # an infinite end: the halfway point is NaN
    np.float32([-np.inf] * 4 + [0.1]),
])
def test_the_side_median_is_the_weighted_median(values):
    """The far side of one suspect pixel holds ``values`` (nearest first around it, its own disparity 0.9); the
    value it takes is the float64 weighted median of them, weighted as the vote weighs them."""
    rng = np.random.default_rng(0)
    offs, space = _window()
    ring = sorted((k for k, (dy, dx) in enumerate(offs) if (dy or dx)), key=lambda k: (offs[k] ** 2).sum())
    h = w = 2 * int(OPTIONS.radius_px) + 1
    c = h // 2
    cur = np.full((h, w), 0.9, np.float32)
    img = np.full((h, w, 3), 0.5, np.float32)
    trusted = np.zeros((h, w), bool)
    picks = ring[:values.size]  # the nearest: enough spatial weight for the side to count
    for v, k in zip(values, picks):
        y, x = c + offs[k, 0], c + offs[k, 1]
        cur[y, x] = v
        img[y, x] = img[c, c] + rng.normal(0, 0.03, 3)
        trusted[y, x] = True
    side, value = vote_sides(Voting(offs, space, 1.0 / 16.0, OPTIONS), img, cur, trusted, np.array([c]),
                             np.array([c]), one_sided=True)
    assert side[0] == bk_vote.VOTE_FAR
    vals, wts = [], []
    for k in picks:
        y, x = c + offs[k, 0], c + offs[k, 1]
        dc2 = float(((img[y, x].astype(np.float64) - img[c, c]) ** 2).sum())
        vals.append(float(cur[y, x]))
        wts.append(space[k] * np.exp(-dc2 / (2 * OPTIONS.sigma_colour ** 2)))
    assert value[0] == np.float32(weighted_median_ref(vals, wts))


def test_an_exact_tie_takes_the_smaller_value():
    """Two voters of equal weight (mirror offsets, the pixel's own colour): the weight up to the smaller value is
    exactly half the total, and the weighted median is that value, as the oracle's."""
    offs, space = _window()
    h = w = 9
    cur = np.full((h, w), 0.9, np.float32)
    img = np.full((h, w, 3), 0.5, np.float32)
    trusted = np.zeros((h, w), bool)
    cur[4, 3], cur[4, 5] = 0.2, 0.1
    trusted[4, 3] = trusted[4, 5] = True
    side, value = vote_sides(Voting(offs, space, 1.0 / 16.0, OPTIONS), img, cur, trusted, np.array([4]),
                             np.array([4]), one_sided=True)
    assert side[0] == bk_vote.VOTE_FAR
    assert value[0] == np.float32(0.1) == np.float32(weighted_median_ref([0.2, 0.1], [1.0, 1.0]))


def test_a_class_known_with_nothing_seen_has_no_affinity():
    """``min_class = 0`` makes every class known, an empty one too: its affinity is 0 (not 0 / 0), as the
    oracle's. One suspect pixel among pixels of another layer of its colour moves to them."""
    from dataclasses import replace

    options = replace(OPTIONS, min_class=0.0)
    cur = np.full((5, 5), 0.1, np.float32)
    cur[2, 2] = 0.9
    img = np.full((5, 5, 3), 0.5, np.float32)
    sus = np.zeros((5, 5), bool)
    sus[2, 2] = True
    got, want = _both(img, cur, sus, 1.0 / 16.0, options=options)
    assert got[2, 2] == want[2, 2] == np.float32(0.1)


def test_arrays_that_do_not_fit_are_refused():
    """The kernel reads its arrays unchecked: shapes and the map's dtype are checked before the launch."""
    offs, space = _window()
    img, cur, trusted = np.zeros((6, 8, 3), np.float32), np.zeros((6, 8), np.float32), np.ones((6, 8), bool)
    for args in ((img[:4], cur, trusted), (img, cur, trusted[:, :4]), (img, cur.astype(np.float64), trusted)):
        with pytest.raises(ValueError, match="must be H x W x 3"):
            vote_sides(Voting(offs, space, 0.1, OPTIONS), *args, np.array([1]), np.array([1]))
