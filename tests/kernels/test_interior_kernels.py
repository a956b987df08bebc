"""A layer covers whole the pixels whose cone meets no farther surface (bokehray_kernels.interior): the frame's map
against the float64 oracle, and a surface whose CoC varies a little no longer lets the blurred layer behind it
show through."""

from __future__ import annotations

import numpy as np
import warp as wp
from hypothesis import given, settings
from hypothesis import strategies as st

import bokehray as br
from bokehray import scene as sc
from bokehray.edge_estimate import MattingRule
from bokehray.levels.preview import opaque_pixels, render_signed_coc
from tests.reference import interior_ref

DEVICE = "cpu"


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**16), h=st.integers(1, 40), w=st.integers(1, 40), n_layers=st.integers(1, 3))
def test_the_opaque_map_matches_the_oracle(seed, h, w, n_layers):
    rng = np.random.default_rng(seed)
    ids = np.kron(rng.integers(0, n_layers, (h // 6 + 1, w // 6 + 1)), np.ones((6, 6), int))[:h, :w].astype(np.int32)
    ids[rng.random((h, w)) < 0.01] = -1  # copied pixels
    coc = (rng.uniform(-3.0, 3.0, (h, w)) * rng.random() ** 2 + 4.0 * ids).astype(np.float32)
    split = rng.random((h, w)) < 0.01
    sy, sx = np.nonzero(split)
    parts = (wp.array(sy.astype(np.int32), dtype=wp.int32), wp.array(sx.astype(np.int32), dtype=wp.int32))
    arrays = sc.LayerSources(wp.zeros((h, w), dtype=wp.vec3), wp.array(coc, dtype=float),
                             wp.array(ids, dtype=wp.int32), wp.zeros(1, dtype=wp.int32), DEVICE,
                             parts if len(sy) else None)
    got = opaque_pixels(arrays, DEVICE).numpy() != 0
    want = interior_ref.opaque_pixels(ids, split, coc, MattingRule().jump_px)
    # float32 against float64 at a threshold only: a distance is an integer, the reach sqrt(2) (|coc| + 1) not;
    # a CoC step of exactly the jump
    reach = np.sqrt(2.0) * (np.abs(coc.astype(np.float64)) + 1.0)
    tie = np.abs(reach - np.round(reach)) < 1e-5
    assert np.array_equal(got[~tie], want[~tie])


def test_a_surface_of_varying_coc_hides_the_blur_behind_it():
    """An in-focus dark surface whose CoC varies between 0.5 and 0.6 px, beside a bright plane blurred by 31 px
    behind it: its pixels 3 px or more inside its edge are the photo's (the footprints of unequal discs do not
    tile; before, up to 56 % brighter)."""
    rng = np.random.default_rng(0)
    h, w = 96, 160
    img = np.full((h, w, 3), 0.05, np.float32)
    img[:, 80:] = 0.6
    s = np.full((h, w), -31.5, np.float32)
    s[:, :80] = rng.uniform(-0.6, -0.5, (h, 80))
    out, _ = render_signed_coc(img, s, br.Aperture(), layers=br.LayerOptions(soft_edges=False))
    np.testing.assert_allclose(out[:, :77], 0.05, atol=1e-4)
