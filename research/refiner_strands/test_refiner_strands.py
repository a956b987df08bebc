"""research/refiner_strands/refiner_strands.py: the lost pixels and the candidate depths are what its table says they are."""

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scripts import load_script

pytest.importorskip("torch")

from bokehray_refiner.training.data import corrupt_disparity


@pytest.fixture(scope="module")
def bench():
    return load_script(Path("research/refiner_strands/refiner_strands.py"), "refiner_strands")


def _scene():
    """A near block with a 2 px strand growing out of it, and a free 2 px strand far from anything near."""
    truth = np.full((128, 128), 0.2, np.float32)
    truth[10:40, 10:40] = 0.8
    truth[24:26, 40:60] = 0.8  # attached: the block's own depth
    truth[100:102, 70:120] = 0.6  # free: more than 48 px from the block
    return truth, np.clip(corrupt_disparity(truth, "missing", 2), 0.0, 1.0)


def test_the_lost_pixels_are_the_strands_the_corruption_erased(bench):
    truth, given_map = _scene()
    lost = bench.lost_pixels(truth, given_map)
    assert lost[24:26, 40:60].all() and lost[100:102, 70:120].all()
    rest = lost.copy()
    rest[24:26, 40:60] = rest[100:102, 70:120] = False
    corners = np.zeros_like(lost)  # a disc's opening rounds a square's corners, and nothing else of it
    for y, x in ((10, 10), (10, 38), (38, 10), (38, 38)):
        corners[y:y + 2, x:x + 2] = True
    assert rest.any() and not (rest & ~corners).any()
    assert not bench.lost_pixels(truth, truth).any()


def test_the_candidates_restore_an_attached_strand_and_not_a_free_one(bench):
    truth, given_map = _scene()
    c = bench.strand_candidates(given_map, truth, focus=0.5)
    np.testing.assert_array_equal(c["exact"], truth)
    attached, free = (slice(24, 26), slice(40, 60)), (slice(100, 102), slice(70, 120))
    assert np.all(c["near 24"][attached] == np.float32(0.8))  # the block is within 24 px of the whole strand
    assert np.all(c["near 3"][24:26, 50:60] == np.float32(0.2))  # its tip is not within 3 px
    assert np.all(c["near 48"][free] == np.float32(0.2))  # nothing near within 48 px of the free strand
    assert np.all(c["nearest"][free] == np.float32(0.8)) and np.all(c["focus"] == np.float32(0.5))
    assert np.all(c["best of the map's"][attached] == np.float32(0.8))
    assert np.all(c["best of the map's"][free] == np.float32(0.8))  # 0.8 is nearer 0.6 than 0.2 is


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**31 - 1))
def test_the_best_of_the_maps_candidates_is_never_farther_from_the_truth_than_any_of_them(bench, seed):
    rng = np.random.default_rng(seed)
    truth = rng.uniform(0.0, 1.0, (24, 24)).astype(np.float32)
    given_map = np.clip(truth - rng.uniform(0.0, 0.5, truth.shape), 0.0, 1.0).astype(np.float32)
    c = bench.strand_candidates(given_map, truth, focus=0.3, radii=(1, 3))
    best = np.abs(c["best of the map's"] - truth)
    for name in ("near 1", "near 3", "nearest"):
        assert np.all(best <= np.abs(c[name] - truth))
