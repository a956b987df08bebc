"""The painted astronaut portrait's hair against the blurred backdrop at 100 % (shown 5x): the photo, then the
render of each checkout given (this one by default), focused on the eyes at ``--amount 50``.

The map is painted (``portrait.py``: the head an ellipse softened by a Gaussian of 8 px at 1024 px) and ramps
across the hair's rim, where the hair is in focus and the backdrop behind it is blurred by about 32 px.

Usage (from the repository root)::

    python benchmarks/photo/figure_portrait_edge.py docs/img/portrait_edge.png
    python benchmarks/photo/figure_portrait_edge.py out.png --src OTHER/src:OTHER/kernels .   # before | after
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
CROP = (110, 170, 545, 615)  # y0, y1, x0, x1 at 1024 px: the hair's rim over the backdrop
ZOOM = 5

RENDER = """
import sys, numpy as np
sys.path.insert(0, {root!r})
import bokehray as br
from benchmarks.photo.portrait import portrait, D_HEAD
from bokehray.photo.subject import k_from_amount
img, d = portrait(1024)
np.save({out!r}, br.render(img, d, br.BlurParams(k_from_amount(50.0, *d.shape), D_HEAD)))
"""


def render_with(src: str, out: Path) -> np.ndarray:
    """The portrait rendered by the code on ``src`` (a PYTHONPATH; "." this checkout) in a fresh process."""
    env = dict(os.environ)
    if src != ".":
        env["PYTHONPATH"] = src
    subprocess.run([sys.executable, "-c", RENDER.format(root=str(ROOT), out=str(out))], check=True, env=env,
                   stderr=subprocess.DEVNULL)
    return np.load(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("figure", type=Path)
    ap.add_argument("--src", nargs="+", default=["."], help="PYTHONPATHs of the checkouts to render with")
    args = ap.parse_args()
    from PIL import Image

    sys.path.insert(0, str(ROOT))
    from benchmarks.photo.portrait import portrait
    from bokehray.colour import linear_to_srgb

    y0, y1, x0, x1 = CROP

    def crop(a: np.ndarray) -> np.ndarray:
        c = (np.clip(linear_to_srgb(np.clip(a, 0, 1)), 0, 1) * 255 + 0.5).astype(np.uint8)[y0:y1, x0:x1]
        return np.kron(c, np.ones((ZOOM, ZOOM, 1), np.uint8))

    with tempfile.TemporaryDirectory() as tmp:
        panels = [crop(portrait(1024)[0])]
        panels += [crop(render_with(src, Path(tmp) / f"{i}.npy")) for i, src in enumerate(args.src)]
    gap = np.full((panels[0].shape[0], 6, 3), 255, np.uint8)
    row = [p for panel in panels for p in (panel, gap)][:-1]
    args.figure.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.concatenate(row, axis=1)).save(args.figure)
    print(f"wrote {args.figure}")


if __name__ == "__main__":
    main()
