"""100 % crops of the dev set focused far (d1 on the print, d3 on the writing, K = 32) from a soft map (Gaussian 2 px):
the path-traced reference, the exact map's render, the soft map's without and with the thin structures' depth
restored (``LayerOptions(thin_depth=True)``), and the soft and the restored maps.

    python research/soft_thin/crops.py docs/img/thin_depth_crops.png
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402
from PIL import Image  # noqa: E402

import bokehray as br  # noqa: E402
from benchmarks.renderer.bench_soft_maps import _scorer, soften  # noqa: E402
from bokehray.thin_depth import restore_thin  # noqa: E402

# the dev set beside the checkout (a worktree one folder deeper finds it one level further up)
DATA = next((p / "shared" / "data" / "pathtraced-dev" for p in (ROOT.parent, ROOT.parent.parent)
             if (p / "shared" / "data" / "pathtraced-dev").is_dir()), ROOT.parent / "shared" / "data" / "pathtraced-dev")
CASES = (("d1_wire_mesh", "bokeh_f1_k2", (90, 90)), ("d3_lamps_ring_writing", "bokeh_f1_k2", (120, 100)))
SIZE = 140


def row(sc, name: str, render: str, corner: tuple[int, int]) -> np.ndarray:
    sd = DATA / name
    info = {r["file"]: r for r in json.loads((sd / "info.json").read_text())["renders"]}[render]
    image, disp = br.read_image(sd / "image.exr"), br.read_disparity(sd / "disparity.exr")
    soft = soften(disp, "gauss2")
    blur = br.BlurParams(info["K"], min(1.0, max(0.0, info["focus_disparity"])))
    gt = sc.to_srgb(sc.read_exr(str(sd / (render + ".exr"))))
    renders = [br.render(image, disp, blur), br.render(image, soft, blur),
               br.render(image, soft, blur, layers=br.LayerOptions(thin_depth=True))]
    tiles = [gt] + [sc.to_srgb(p) for p in renders]
    for r, p in zip(("exact", "soft", "soft + thin depth"), tiles[1:]):
        print(f"{name} {render} {r:18s} PSNR {sc.psnr(gt, p):.2f}")
    k, f = blur.k_px, blur.focus_disparity
    s, _ = restore_thin(image, (k * (soft - f)).astype(np.float32), bounds=(-k * f, k * (1 - f)))
    restored = s / k + f  # the map the render used, as disparity
    tiles += [np.repeat(m[..., None], 3, 2) for m in (soft, restored)]
    y, x = corner
    return np.concatenate([t[y : y + SIZE, x : x + SIZE] for t in tiles], 1)


def main() -> int:
    out = Path(sys.argv[1])
    sc = _scorer(DATA)
    img = np.concatenate([row(sc, *case) for case in CASES], 0)
    out.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray((np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)).save(out)
    print(f"wrote {out}: columns reference | exact map | soft map | soft map + thin depth | soft map | restored map")
    return 0


if __name__ == "__main__":
    sys.exit(main())
