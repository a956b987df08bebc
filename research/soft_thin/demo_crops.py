"""100 % crops of the demo at 1536 x 1024 with its map blurred by 4 px (amount 50), focused on the subject and far
(0.1): the exact map's render, the soft map's, the soft map's with the thin structures' depth restored
(``LayerOptions(thin_depth=True)``), and the soft and restored maps (focused far).

    python research/soft_thin/demo_crops.py docs/img/thin_depth_demo_crops.png
"""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402
from PIL import Image  # noqa: E402

import bokehray as br  # noqa: E402
from benchmarks.renderer.bench_soft_maps import soften  # noqa: E402
from bokehray.app.demo import build_demo_scene  # noqa: E402
from bokehray.colour import linear_to_srgb  # noqa: E402
from bokehray.photo.subject import k_from_amount, subject_focus  # noqa: E402
from bokehray.thin_depth import restore_thin  # noqa: E402

CROP = (420, 740, 240, 320)  # y, x, height, width: the cat's head, the wire and the sky


def main() -> int:
    out = Path(sys.argv[1])
    sc = build_demo_scene(1536, 1024)
    soft = soften(sc.disparity, "gauss4")
    k = k_from_amount(50.0, 1024, 1536)
    y, x, hh, ww = CROP
    rows = []
    for focus in (subject_focus(soft).d_f, 0.1):
        blur = br.BlurParams(k, focus)
        tiles = [br.render(sc.image, sc.disparity, blur), br.render(sc.image, soft, blur),
                 br.render(sc.image, soft, blur, layers=br.LayerOptions(thin_depth=True))]
        tiles = [np.clip(linear_to_srgb(np.clip(t, 0, 1)), 0, 1) for t in tiles]
        s, n = restore_thin(sc.image, blur.signed_coc(soft), bounds=(float(-k * focus), float(k * (1 - focus))))
        print(f"focus {focus:.3f}: {n} px restored")
        tiles += [np.repeat(m[..., None], 3, 2) for m in (soft, s / k + focus)]
        rows.append(np.concatenate([t[y : y + hh, x : x + ww] for t in tiles], 1))
    img = (np.concatenate(rows, 0) * 255 + 0.5).astype(np.uint8)
    out.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(img).save(out)
    print(f"wrote {out}: columns exact map | soft map | soft map + thin depth | soft map | restored map; rows focus "
          "subject, far")
    return 0


if __name__ == "__main__":
    sys.exit(main())
