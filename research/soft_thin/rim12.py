"""The 12 MP soft map's restored depth along the demo cat's rim: how many pixels ``restore_thin`` puts nearer than
anything the exact map has there (its largest value within 2 px), in the 400 x 300 crop at (900, 2300) over the
cat's top, and over the whole frame; optionally the crop's maps side by side (photo, exact, soft, restored).

    python research/soft_thin/rim12.py                       # the counts
    python research/soft_thin/rim12.py --png rim12.png       # and the crop (maps: black = far, white = near)
    python research/soft_thin/rim12.py --module /path/to/thin_depth.py   # another version of the module

The input is ``cost.py edge12``'s: the demo at 1500 x 1000 zoomed to 4000 x 3000, its map blurred by 6 px, amount
50, focused on the subject; the exact map is the demo's zoomed the same way (nearest neighbour).
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
from pathlib import Path

import numpy as np
from scipy import ndimage

from bokehray import scene
from bokehray.app.demo import build_demo_scene

CROP = (slice(900, 1200), slice(2300, 2700))


def _module(path: str | None):
    if not path:
        from bokehray import thin_depth

        return thin_depth
    spec = importlib.util.spec_from_file_location("bokehray.thin_other", path)  # its relative imports
    mod = importlib.util.module_from_spec(spec)
    sys.modules["bokehray.thin_other"] = mod
    spec.loader.exec_module(mod)
    return mod


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--png", type=Path)
    ap.add_argument("--module")
    args = ap.parse_args()
    import bokehray as br
    from bokehray.photo.subject import k_from_amount, subject_focus

    sc = build_demo_scene(1500, 1000)
    z = (3000 / 1000, 4000 / 1500)
    img = np.clip(ndimage.zoom(sc.image, (*z, 1), order=1), 0, None).astype(np.float32)
    exact = ndimage.zoom(sc.disparity, z, order=0).astype(np.float32)
    d = np.clip(ndimage.gaussian_filter(exact, 6.0), 0, 1).astype(np.float32)
    blur = br.BlurParams(k_from_amount(50.0, *d.shape), subject_focus(d).d_f)
    bounds = (float(blur.signed_coc(np.float32(0.0))), float(blur.signed_coc(np.float32(1.0))))
    soft, ex = scene.cap_coc(blur.signed_coc(d)), scene.cap_coc(blur.signed_coc(exact))
    out, n = _module(args.module).restore_thin(img, soft, bounds=bounds)
    over = out - ndimage.maximum_filter(ex, 5)  # nearer than anything the exact map has within 2 px
    print(f"{n} px moved; nearer than the exact map by more than t CoC px (K = {blur.k_px:.1f}):")
    for t in (0.5, 1.0, 1.5, 2.0, 4.0):
        print(f"  t = {t}: crop {int((over[CROP] > t).sum())}, frame {int((over > t).sum())}")
    if args.png:
        from PIL import Image

        from bokehray.colour import linear_to_srgb

        lo, hi = float(ex.min()), float(ex.max())

        def grey(m):
            return np.repeat(np.clip((m[CROP] - lo) / (hi - lo), 0, 1)[..., None], 3, 2)

        tiles = [np.clip(linear_to_srgb(np.clip(img[CROP], 0, 1)), 0, 1), grey(ex), grey(soft), grey(out)]
        Image.fromarray((np.concatenate(tiles, 1) * 255 + 0.5).astype(np.uint8)).save(args.png)
        print(f"wrote {args.png}: photo | exact map | soft map | restored map")
    return 0


if __name__ == "__main__":
    sys.exit(main())
