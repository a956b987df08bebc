"""The pictures of docs/usage.md, made by running the commands the page shows on a phone-style input.

The input is the built-in demo scene, as a phone would hand it over: a JPEG stored sideways with EXIF
Orientation 6 (rotated for display), and a relative inverse-depth map of range 0.39..6.87 made on the upright
photo, as a monocular depth model writes it (float NPY). The script runs ``bokehray render`` the way
docs/usage.md does, keeps what it printed, and puts the results side by side in ``docs/img/usage_workflow.png``.

Usage (from the repository root)::

    python benchmarks/photo/usage_figures.py              # writes docs/img/usage_workflow.png and prints the logs
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "src"))

import bokehray as br  # noqa: E402
from bokehray.app.demo import build_demo_scene  # noqa: E402

CLI = [sys.executable, "-c", "import sys; from bokehray.app.cli import main; sys.exit(main())"]


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT / "src"), str(ROOT / "kernels"), str(ROOT / "refiner")]
                                        + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else []))
    return env


def main() -> int:
    from PIL import Image

    scene = build_demo_scene(width=960, height=640)
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        codes = np.round(br.colour.linear_to_srgb(np.clip(scene.image, 0, 1)) * 255).astype(np.uint8)
        stored = np.ascontiguousarray(np.rot90(codes, 1))  # stored sideways: Orientation 6 turns it upright
        exif = Image.Exif()
        exif[0x0112] = 6
        exif[0x010F] = "PhoneCam"
        Image.fromarray(stored).save(tmp / "photo.jpg", quality=92, exif=exif.tobytes())
        np.save(tmp / "depth.npy", (0.39 + 6.48 * scene.disparity).astype(np.float32))  # relative inverse depth
        runs = {
            "defaults": ["--normalize"],
            "--amount 80 --focus-at 330,380": ["--normalize", "--amount", "80", "--focus-at", "330,380"],
            "--aperture polygon --blades 6": ["--normalize", "--aperture", "polygon", "--blades", "6"],
        }
        outs = {}
        for label, extra in runs.items():
            out = tmp / f"{len(outs)}.jpg"
            cmd = [*CLI, "render", str(tmp / "photo.jpg"), "--disparity", str(tmp / "depth.npy"), *extra, "-o",
                   str(out)]
            p = subprocess.run(cmd, capture_output=True, text=True, env=_env(), cwd=ROOT)
            if p.returncode != 0:
                print(p.stderr)
                return 1
            print(f"$ bokehray render photo.jpg --disparity depth.npy {' '.join(extra)} -o out.jpg\n{p.stdout}")
            outs[label] = br.read_image(out)
        photo = br.read_image(tmp / "photo.jpg")
        depth = np.load(tmp / "depth.npy")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [("photo.jpg (upright from its EXIF orientation)", br.colour.linear_to_srgb(np.clip(photo, 0, 1))),
              ("depth.npy: relative, 0.39..6.87", depth)]
    panels += [(f"render: {k}", br.colour.linear_to_srgb(np.clip(v, 0, 1))) for k, v in outs.items()]
    fig, axes = plt.subplots(1, len(panels), figsize=(4.2 * len(panels), 3.3))
    for ax, (title, img) in zip(axes, panels):
        ax.imshow(img, cmap="gray" if img.ndim == 2 else None)
        ax.set_title(title, fontsize=9)
        ax.set_xticks([]), ax.set_yticks([])
    fig.tight_layout()
    path = ROOT / "docs" / "img" / "usage_workflow.png"
    fig.savefig(path, dpi=80)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
