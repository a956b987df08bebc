"""A portrait with a painted depth map, for the measurements of the default focus, white surfaces and grain.

``skimage.data.astronaut()`` (512 x 512, shipped inside scikit-image: a studio portrait with a face, a white
helmet and a studio backdrop) with a disparity map painted over it the way a photographer paints one with a
brush: the backdrop far (0.10), the flag and the shuttle model a little nearer (0.25, 0.30), the head at 0.839,
the suit (shoulders, chest) nearer at 0.859 and the helmet held in front at 0.88; every edge softened by a
Gaussian of 4 px (a brush). The head is painted behind the chest, as in the portrait that showed the default
focus landing on the chest. :func:`portrait` scales both up (bicubic photo, bilinear map) to a given size, e.g.
12 MP (``side=3464``).
"""

from __future__ import annotations

import numpy as np

D_HEAD, D_SUIT, D_HELMET = 0.839, 0.859, 0.88
EYES_512 = (180, 90, 275, 120)  # the eyes' box (x0, y0, x1, y1) in the 512 px original


def painted_map() -> np.ndarray:
    """The 512 x 512 painted disparity map of the astronaut."""
    from scipy.ndimage import gaussian_filter
    from skimage.draw import disk, ellipse, polygon

    d = np.full((512, 512), 0.10, np.float32)
    d[:, :100] = 0.25  # the flag
    d[:300, 355:470] = 0.30  # the shuttle model
    rr, cc = polygon([512, 300, 215, 150, 150, 215, 300, 512], [15, 25, 95, 120, 300, 345, 365, 365], d.shape)
    d[rr, cc] = D_SUIT  # shoulders, chest, arms, collar ring
    rr, cc = ellipse(105, 226, 95, 78, shape=d.shape)
    d[rr, cc] = D_HEAD  # the head, hair included
    rr, cc = disk((455, 392), 118, shape=d.shape)
    d[rr, cc] = D_HELMET  # the helmet
    return np.clip(gaussian_filter(d, 4.0), 0.0, 1.0).astype(np.float32)


def portrait(side: int = 512) -> tuple[np.ndarray, np.ndarray]:
    """``(linear RGB image, disparity)`` at ``side`` x ``side`` pixels."""
    from PIL import Image
    from skimage.data import astronaut

    from bokehray.colour import srgb_to_linear

    codes = astronaut()
    d = painted_map()
    if side != 512:
        codes = np.asarray(Image.fromarray(codes).resize((side, side), Image.BICUBIC))
        d = np.asarray(Image.fromarray(d).resize((side, side), Image.BILINEAR), np.float32)
    return srgb_to_linear(codes.astype(np.float32) / 255.0).astype(np.float32), np.ascontiguousarray(d)
