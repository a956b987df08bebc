"""``bokehray_kernels.soft.near_sources_kernel`` against its NumPy oracle (``reference.soft_ref.near_sources``):
random near parts (layers, positions inside and outside the box, window offsets), sources that come zeroed."""

import bokehray_kernels as bk
import numpy as np
import warp as wp
from hypothesis import given
from hypothesis import strategies as st
from reference import soft_ref

DEVICE = "cpu"


@given(seed=st.integers(0, 2**16), n=st.integers(1, 40), h=st.integers(1, 12), w=st.integers(1, 12),
       y0=st.integers(0, 4), x0=st.integers(0, 4), layer=st.integers(0, 3))
def test_near_sources_kernel_matches_the_oracle(seed, n, h, w, y0, x0, layer):
    rng = np.random.default_rng(seed)
    flat = rng.choice((h + 8) * (w + 8), size=min(n, (h + 8) * (w + 8)), replace=False)  # unique pixels
    parts = dict(y=(flat // (w + 8)).astype(np.int32), x=(flat % (w + 8)).astype(np.int32),
                 value=rng.random((len(flat), 4)).astype(np.float32), coc=rng.normal(0, 10, len(flat)).astype(np.float32),
                 layer=rng.integers(0, 4, len(flat)).astype(np.int32))
    want_src, want_coc = np.zeros((h, w, 4), np.float32), np.zeros((h, w), np.float32)
    soft_ref.near_sources(want_src, want_coc, parts, layer, y0, x0)
    src, coc = wp.zeros((h, w), dtype=wp.vec4, device=DEVICE), wp.zeros((h, w), dtype=float, device=DEVICE)
    wp.launch(bk.near_sources_kernel, dim=len(flat),
              inputs=[wp.array(parts["y"], dtype=wp.int32, device=DEVICE),
                      wp.array(parts["x"], dtype=wp.int32, device=DEVICE),
                      wp.array(parts["value"], dtype=wp.vec4, device=DEVICE),
                      wp.array(parts["coc"], dtype=float, device=DEVICE),
                      wp.array(parts["layer"], dtype=wp.int32, device=DEVICE), layer, x0, y0],
              outputs=[src, coc], device=DEVICE)
    np.testing.assert_array_equal(src.numpy(), want_src)
    np.testing.assert_array_equal(coc.numpy(), want_coc)
