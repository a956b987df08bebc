"""Random extreme cases of the kernels against their float64 NumPy references (tests/reference).

Each ``*_case(seed)`` builds one case from a seed, runs the Warp kernel and the
reference, and returns ``(relative error, radiance scale, description)`` with the relative error
``max(|kernel - reference| - DENORMAL_FLOOR) / max |reference|`` (0 when both are 0).
``DENORMAL_FLOOR`` is float32's underflow: with denormal radiance (1e-40) a
deposit of weight 1e-6 is below float32's smallest subnormal (1.4e-45) and
becomes 0, and the subnormal grid itself carries absolute rounding of that size
(a relative error of 1e-3 or more at 1e-42). Used by
tests/test_stress_numerics.py (few cases, asserted) and by
benchmarks/robustness/stress_reference.py (many cases, worst error recorded).
"""

from __future__ import annotations

import bokehray_kernels as bk
import numpy as np
import warp as wp

import bokehray as br
from bokehray.levels.preview import aperture_shape, no_routing, prefix_rows, pyramid_buffers, render_signed_coc
from bokehray.levels.raytrace import Layer, raytrace_layers
from bokehray.options import LayerOptions, PreviewOptions, RaytraceOptions
from bokehray.scene import LayerSupport, cap_coc, copy_tiles, grid_to_pixels, layer_edges

from . import raytrace_ref, scatter_ref

# radiance scales: black, denormal in float32 (< 1.18e-38), tiny, display range, HDR highlight
SCALES = (0.0, 1e-40, 1e-8, 1.0, 1e4)
APERTURES = (br.Aperture(), br.Aperture(blades=5, rotation_deg=17.0), br.Aperture(blades=6, curvature=0.4),
             br.Aperture(blades=3, rotation_deg=-40.0, curvature=1.0))


DENORMAL_FLOOR = 1e-43  # about 70 float32 subnormal steps: a few rounded deposits and a division


def _rel(got: np.ndarray, want: np.ndarray) -> float:
    if not np.isfinite(got).all():
        return float("inf")
    scale = float(np.abs(want).max())
    err = max(0.0, float(np.abs(got.astype(np.float64) - want).max()) - DENORMAL_FLOOR)
    return 0.0 if err == 0.0 else err / max(scale, 1e-300)


def _radii(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    kind = rng.choice(["zero", "subpixel", "half", "random", "huge", "mixed"])
    if kind == "zero":
        return np.zeros((h, w), np.float32)
    if kind == "subpixel":
        return rng.uniform(0, 0.4999, (h, w)).astype(np.float32)
    if kind == "half":
        return np.full((h, w), 0.5, np.float32)
    if kind == "random":
        return rng.uniform(0, 6, (h, w)).astype(np.float32)
    if kind == "huge":  # far beyond the image: almost everything lands outside
        return np.full((h, w), float(rng.choice([40.0, 300.0])), np.float32)
    r = rng.uniform(0, 8, (h, w))
    r[rng.random((h, w)) < 0.3] = 0.0
    return r.astype(np.float32)


def scatter_case(seed: int, device: str = "cpu") -> tuple[float, float, str]:
    """One level-0 scatter of random sources (any radius, sign, aperture, radiance scale) vs ``scatter_ref.scatter``."""
    rng = np.random.default_rng(seed)
    h, w = int(rng.integers(1, 13)), int(rng.integers(1, 13))
    scale = float(rng.choice(SCALES))
    ap = APERTURES[int(rng.integers(len(APERTURES)))]
    src = (rng.random((h, w, 4)) * scale).astype(np.float32)
    src[..., 3] = 1.0
    radius = _radii(rng, h, w) * rng.choice([-1.0, 1.0], (h, w)).astype(np.float32)
    bufs = [wp.zeros((h, w + 2), dtype=wp.vec4, device=device)]
    bufs += [bufs[0]] * (bk.MAX_LEVELS - 1)
    rows = ap.blade_discs()
    wp.launch(bk.scatter_kernel, dim=(h, w),
              inputs=[1, wp.array(src, dtype=wp.vec4, device=device), wp.array(radius, device=device),
                      LayerSupport.everywhere(device).struct(), no_routing(device).struct(),
                      aperture_shape(ap, rows, device), 1e6, 1, pyramid_buffers(bufs), 0],
              device=device)
    prefix_rows(bufs[0], device)
    got = bufs[0].numpy()[:, :w]
    want = scatter_ref.scatter(src.astype(np.float64), radius.astype(np.float64), rows, ap.vertical_extent())
    # colour channels relative to the radiance scale, coverage on its own
    err = max(_rel(got[..., :3], want[..., :3]) if scale > 0 else float(np.abs(got[..., :3]).max() > 0),
              _rel(got[..., 3], want[..., 3]))  # black must stay exactly black
    return err, scale, f"scatter {h}x{w} scale={scale:g} r<={float(np.abs(radius).max()):.3g} ap={ap}"


def layered_case(seed: int, device: str = "cpu") -> tuple[float, float, str]:
    """The layered preview without fill or pyramid (level 0 only) vs ``scatter_ref.layered``."""
    rng = np.random.default_rng(seed)
    h, w = int(rng.integers(1, 15)), int(rng.integers(1, 15))
    scale = float(rng.choice(SCALES[1:]))
    ap = APERTURES[int(rng.integers(len(APERTURES)))]
    image = (rng.random((h, w, 3)) * scale).astype(np.float32)
    pattern = rng.choice(["random", "steps", "edge", "constant", "zero", "one"])
    d = {"random": rng.random((h, w)), "steps": np.indices((h, w)).sum(0) % 2,
         "edge": (np.arange(w)[None, :] >= w // 2) * np.ones((h, 1)), "constant": np.full((h, w), rng.random()),
         "zero": np.zeros((h, w)), "one": np.ones((h, w))}[pattern].astype(np.float32)
    blur = br.BlurParams(float(rng.choice([0.0, 0.9, 3.0, 7.0, 25.0])), float(rng.choice([0.0, 1.0, rng.random()])))
    layers = LayerOptions(max_layer_px=1.5, fill=False, tile_px=4)
    got, _ = render_signed_coc(image, blur.signed_coc(d), ap, layers=layers, options=PreviewOptions(level_radius_px=1e6),
                               device=device)
    # the renderer compresses CoCs beyond twice the image diagonal (cap_coc, a policy, not a kernel;
    # not idempotent, so applied once): the reference gets the same radii
    s = cap_coc(blur.signed_coc(d))
    # the reference has no tile skipping: give it the same slices (copied pixels keep the input in both)
    copy = copy_tiles(np.abs(s), layers.tile_px)
    active = ~grid_to_pixels(copy, layers.tile_px, (h, w))
    if not active.any():
        want = image.astype(np.float64)
    else:
        edges = layer_edges(s[active], layers)
        want = scatter_ref.layered(image.astype(np.float64), s.astype(np.float64), edges, ap.blade_discs(),
                                   ap.vertical_extent())
        want = np.where(active[..., None], want, image)
    return _rel(got, want), scale, f"layered {h}x{w} {pattern} scale={scale:g} K={blur.k_px:g} d_f={blur.focus_disparity:.3g}"


def raytrace_case(seed: int, device: str = "cpu") -> tuple[float, float, str]:
    """Plane layers (alpha exactly 0 and 1, identical depths, hard edges, 1 ray) vs ``raytrace_ref.trace``."""
    rng = np.random.default_rng(seed)
    h, w = int(rng.integers(1, 11)), int(rng.integers(1, 11))
    n = int(rng.integers(1, 4))
    scale = float(rng.choice(SCALES[1:]))
    same_depth = rng.random() < 0.3
    layers = []
    for _ in range(n):
        tex = np.empty((h, w, 4), np.float32)
        tex[..., :3] = rng.random((h, w, 3)) * scale
        alpha = rng.choice(["zero", "one", "step", "random"])
        tex[..., 3] = {"zero": np.zeros((h, w)), "one": np.ones((h, w)),
                       "step": (np.arange(w)[None, :] >= w // 2) * np.ones((h, 1)),  # a hard edge rays graze
                       "random": rng.random((h, w))}[alpha]
        c = 0.5 if same_depth else float(rng.random())
        tilt = (0.0, 0.0) if rng.random() < 0.5 else tuple(rng.uniform(-0.01, 0.01, 2))
        layers.append((tex, (tilt[0], tilt[1], c)))
    layers.sort(key=lambda t: -t[1][2])  # nearest first
    k = float(rng.choice([0.0, 1.0, 4.0, 9.0]))
    d_f = float(rng.choice([0.0, 1.0, 0.5, rng.random()]))
    spp = int(rng.choice([1, 2, 7]))
    got, _ = raytrace_layers([Layer(t, plane=p) for t, p in layers], br.BlurParams(k, d_f),
                             options=RaytraceOptions(samples_per_px2=1e6, max_spp=spp, min_spp=spp), device=device)
    want = raytrace_ref.trace(layers, k, d_f, spp)
    return _rel(got, want), scale, f"raytrace {h}x{w} layers={n} same_depth={same_depth} K={k:g} spp={spp} scale={scale:g}"


CASES = {"scatter": scatter_case, "layered": layered_case, "raytrace": raytrace_case}
