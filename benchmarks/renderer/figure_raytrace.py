"""Figure for docs/raytracer.md: what the quadrature renders look like (a point light, a layer-stack crop).

Usage (from the repository root)::

    python benchmarks/renderer/figure_raytrace.py docs/img/raytrace_quadrature.png
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import numpy as np

import bokehray as br
from benchmarks.renderer.bench_raytrace import scene


def main() -> int:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(sys.argv[1] if len(sys.argv) > 1 else "docs/img/raytrace_quadrature.png")
    n, c = 160, 80
    tex = np.zeros((n, n, 4), np.float32)
    tex[..., 3] = 1.0
    tex[c, c, :3] = [60000.0, 45000.0, 30000.0]
    light, _ = br.raytrace_layers([br.Layer(tex, plane=(0, 0, 0.0))], br.BlurParams(64.0, 1.0),
                                  br.Aperture(blades=5, curvature=0.3))
    layers = scene()
    blur = br.BlurParams(k_px=24.0 / 0.9, focus_disparity=0.0)
    crops = []
    for cap in (128, 8):
        img, st = br.raytrace_layers(layers, blur, options=br.RaytraceOptions(max_spp=cap))
        crops.append((img[150:330, 200:380, :3], f"3-layer stack, max_spp {cap} ({st.spp_mean:.0f} rays/px)"))
    fig, axes = plt.subplots(1, 3, figsize=(12, 4.2))
    srgb = lambda x: br.colour.linear_to_srgb(np.clip(x, 0, 1))  # noqa: E731
    axes[0].imshow(srgb(light[..., :3]))
    axes[0].set_title("point light, R = 64 px, curved pentagon", fontsize=9)
    for ax, (img, title) in zip(axes[1:], crops):
        ax.imshow(srgb(img))
        ax.set_title(title, fontsize=9)
    for ax in axes:
        ax.set_xticks([]), ax.set_yticks([])
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=90)
    return 0


if __name__ == "__main__":
    sys.exit(main())
