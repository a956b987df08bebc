"""``bokehray render --thin-depth``: the option reaches the render (LayerOptions.thin_depth) and changes a soft
map's wires; without it the render is the default's."""

import numpy as np
from scipy import ndimage

import bokehray as br
from bokehray.app.cli import build_parser
from bokehray.app.render_job import layer_options_of


def test_the_flag_sets_the_option():
    parser = build_parser()
    on = parser.parse_args(["render", "in.png", "--disparity", "d.png", "-o", "o.png", "--thin-depth"])
    off = parser.parse_args(["render", "in.png", "--disparity", "d.png", "-o", "o.png"])
    assert layer_options_of(on).thin_depth is True
    assert layer_options_of(off).thin_depth is False


def test_thin_depth_moves_a_blurred_wire(tmp_path):
    n = 96
    img = np.full((n, n, 3), [0.1, 0.2, 0.5], np.float32)
    d = np.zeros((n, n), np.float32)
    img[:, 40:42] = [0.9, 0.8, 0.7]  # a 2 px wire in front
    d[:, 40:42] = 1.0
    soft = ndimage.gaussian_filter(d, 2.0).astype(np.float32)
    blur = br.BlurParams(16.0, 0.0)
    plain = br.render(img, soft, blur)
    thin = br.render(img, soft, blur, layers=br.LayerOptions(thin_depth=True))
    exact = br.render(img, d, blur)
    assert np.abs(thin - exact).mean() < np.abs(plain - exact).mean()
