"""Synthetic paired data (paper sec. 3.3): RGBA foregrounds over all-in-focus backgrounds, ray traced.

Each scene is a stack of planar layers, nearest first: one or two RGBA
foregrounds (photo cut-outs, or procedural hard cases: hair-like strands with
partial alpha, foliage, a fence mesh, small very bright lights; on request fur,
whiskers and cut-outs with soft rims, with per-kind weights) at random
scale, placement, facing angle (tilted planes) and depth, over a tilted photo
background. The all-in-focus image is the same layers seen through a pinhole;
the targets are exact thin-lens renders (``bokehray.raytrace_layers``) for
every blur level ``K`` and for focus on the nearest foreground's and on the
background's mean disparity (alpha-weighted). Scenes are written in the BLB layout
(``bokehray.data.datasets.write_blb_scene``).

Deterministic: scene ``i`` of seed ``s`` depends only on ``(s, i)``, not on the
number of worker processes.
"""

from __future__ import annotations

import math
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..lens import Aperture, BlurParams
from ..levels.raytrace import Layer, raytrace_layers
from ..options import RaytraceOptions

__all__ = ["ALL_KINDS", "DEPTH_RULES", "SynthConfig", "bundled_photo", "cutout_layer", "fit_crop", "generate",
           "generate_one", "make_scene", "mean_disparity", "pinhole_layers", "procedural_layer", "stroke_coverage"]

BUILTIN_BACKGROUNDS = ("astronaut", "coffee", "chelsea", "rocket", "brick", "gravel", "page", "coins", "camera")
FOREGROUND_KINDS = ("cutout", "strands", "foliage", "mesh", "lights")
"""The kinds drawn, uniformly, when no weights are given (scene ``i`` of a seed is then what it always was)."""
EXTRA_KINDS = ("fur", "whiskers", "softcut")
"""Further hard kinds, drawn only when :attr:`SynthConfig.kinds` names them: fur (a body fringed by many short
strands), whiskers (a few long sub-pixel to 1 px strands) and cut-outs whose rim is a 1 - 4 px alpha ramp."""
ALL_KINDS = FOREGROUND_KINDS + EXTRA_KINDS
DEPTH_RULES = ("any", "half")
"""Which pixels a foreground labels in the map (:func:`pinhole_layers`)."""


@dataclass(frozen=True)
class SynthConfig:
    """What to generate.

    Args:
        size: side of the square images in pixels.
        blur_levels: the ``K`` values (CoC px per unit disparity) of the targets.
        aperture: aperture of every target.
        max_spp: ray cap per pixel (see docs/raytracer.md for the error it buys).
        fg_dir, bg_dir: optional folders of RGBA foregrounds (PNG with alpha) and
            background photos; when absent, built-in sources are used.
        kinds: ``((kind, weight), ...)``: draw the built-in foregrounds with these relative weights (any of
            :data:`ALL_KINDS`); None draws :data:`FOREGROUND_KINDS` uniformly.
        depth_rule: which pixels a foreground labels in the written map (:func:`pinhole_layers`).
    """

    size: int = 512
    blur_levels: tuple[float, ...] = (10.0, 20.0, 30.0)
    aperture: Aperture = field(default_factory=Aperture)
    max_spp: int = 64
    fg_dir: str | None = None
    bg_dir: str | None = None
    kinds: tuple[tuple[str, float], ...] | None = None
    depth_rule: str = "any"

    def __post_init__(self) -> None:
        _check_depth_rule(self.depth_rule)
        if self.kinds is not None:
            names = [k for k, _ in self.kinds]
            weights = [w for _, w in self.kinds]
            bad = [k for k in names if k not in ALL_KINDS]
            if bad or not names or len(set(names)) != len(names):
                raise InputError(f"kinds: expected distinct names from {ALL_KINDS}, got {names}")
            if any(not (math.isfinite(w) and w >= 0) for w in weights) or sum(weights) <= 0:
                raise InputError(f"kinds: expected weights >= 0 with a positive sum, got {weights}")
        if not 32 <= self.size <= 4096:
            raise InputError(f"size: expected 32..4096 px, got {self.size}")
        if not self.blur_levels or any(not (math.isfinite(k) and 0 < k <= 1e4) for k in self.blur_levels):
            raise InputError(f"blur levels: expected K values in (0, 10000], got {self.blur_levels}")
        RaytraceOptions(max_spp=self.max_spp)  # validates the ray cap


def _check_depth_rule(rule: str) -> None:
    if rule not in DEPTH_RULES:
        raise InputError(f"depth rule: expected one of {DEPTH_RULES}, got {rule!r}")


def _scene_rng(seed: int, index: int) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence([int(seed), int(index)]))


def _linear(rgb_u8: np.ndarray) -> np.ndarray:
    from ..colour import srgb_to_linear

    return srgb_to_linear(np.asarray(rgb_u8, np.float32) / 255.0)


def bundled_photo(name: str) -> np.ndarray:
    from skimage import data

    img = getattr(data, name)()
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    return _linear(img[..., :3])


def _files(folder: str, what: str) -> list[Path]:
    p = Path(folder)
    if not p.is_dir():
        raise InputError(f"{folder}: {what} folder does not exist or is not a directory")
    files = sorted(f for f in p.iterdir() if f.suffix.lower() in (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".exr"))
    if not files:
        raise InputError(f"{folder}: no images found for the {what}")
    return files


def fit_crop(img: np.ndarray, size: int, rng: np.random.Generator) -> np.ndarray:
    """Random square crop (at least half the short side), resized to ``size``."""
    from skimage.transform import resize

    h, w = img.shape[:2]
    side = int(rng.uniform(0.5, 1.0) * min(h, w))
    y0, x0 = rng.integers(0, h - side + 1), rng.integers(0, w - side + 1)
    crop = img[y0:y0 + side, x0:x0 + side]
    return resize(crop, (size, size), order=1, anti_aliasing=True).astype(np.float32)


def stroke_coverage(dist: np.ndarray, width: float) -> np.ndarray:
    """Antialiased coverage of a stroke of ``width`` px given the distance to its centre line."""
    return np.clip(width / 2 + 0.5 - dist, 0.0, 1.0) * min(1.0, width)


def _fur_layer(size: int, rng: np.random.Generator) -> np.ndarray:
    """A body fringed by many short strands pointing outwards, one tint with some variation."""
    yy, xx = (np.mgrid[0:size, 0:size] + 0.5).astype(np.float32)
    rgba = np.zeros((size, size, 4), np.float32)
    colour = np.asarray(rng.choice([[0.35, 0.22, 0.12], [0.8, 0.65, 0.4], [0.08, 0.06, 0.05], [0.9, 0.9, 0.85]]))
    cx, cy = rng.uniform(0.3, 0.7, 2) * size
    rx, ry = rng.uniform(0.12, 0.28, 2) * size
    body = np.clip(0.5 - (np.hypot((xx - cx) / rx, (yy - cy) / ry) - 1.0) * min(rx, ry), 0, 1)
    rgba[..., 3] = body
    for _ in range(int(rng.integers(80, 200))):
        t = rng.uniform(0, 2 * np.pi)
        ox, oy = cx + rx * np.cos(t), cy + ry * np.sin(t)
        a0 = t + rng.normal(0, 0.35)
        length = rng.uniform(4, 18)
        u = (xx - ox) * np.cos(a0) + (yy - oy) * np.sin(a0)
        v = -(xx - ox) * np.sin(a0) + (yy - oy) * np.cos(a0)
        cov = stroke_coverage(np.abs(v), rng.uniform(0.3, 1.5)) * ((u > -4) & (u < length))
        rgba[..., 3] = np.maximum(rgba[..., 3], cov)
    shade = 0.85 + 0.3 * np.clip(rng.normal(0, 0.3, (size, size)), -1, 1)
    rgba[..., :3] = np.clip(colour * shade[..., None], 0, 1)
    return rgba


def _whiskers_layer(size: int, rng: np.random.Generator) -> np.ndarray:
    """A few long, straight-ish, sub-pixel to 1 px strands, light or dark."""
    yy, xx = (np.mgrid[0:size, 0:size] + 0.5).astype(np.float32)
    rgba = np.zeros((size, size, 4), np.float32)
    colour = rng.choice([[0.95, 0.95, 0.92], [0.05, 0.04, 0.04], [0.7, 0.6, 0.45]])
    cx, cy = rng.uniform(0.3, 0.7, 2) * size
    for _ in range(int(rng.integers(6, 16))):
        a0, bend = rng.uniform(0, 2 * np.pi), rng.uniform(-0.003, 0.003)
        u = (xx - cx) * np.cos(a0) + (yy - cy) * np.sin(a0)
        v = -(xx - cx) * np.sin(a0) + (yy - cy) * np.cos(a0) - bend * u * u
        reach = rng.uniform(0.2, 0.45) * size
        cov = stroke_coverage(np.abs(v), rng.uniform(0.3, 1.0)) * ((u > 0.02 * size) & (u < reach))
        rgba[..., 3] = np.maximum(rgba[..., 3], cov)
    rgba[..., :3] = colour
    return rgba


def procedural_layer(kind: str, size: int, rng: np.random.Generator) -> np.ndarray:
    if kind in ("fur", "whiskers"):
        return (_fur_layer if kind == "fur" else _whiskers_layer)(size, rng)
    yy, xx = (np.mgrid[0:size, 0:size] + 0.5).astype(np.float32)
    rgba = np.zeros((size, size, 4), np.float32)
    if kind == "strands":  # hair / fur: many thin curved strands, partial alpha, one tint
        colour = rng.choice([[0.35, 0.22, 0.12], [0.8, 0.65, 0.4], [0.08, 0.06, 0.05], [0.9, 0.9, 0.85]])
        cx, cy, spread = rng.uniform(0.3, 0.7) * size, rng.uniform(0.3, 0.7) * size, rng.uniform(0.15, 0.35) * size
        for _ in range(int(rng.integers(40, 90))):
            a0, bend = rng.uniform(0, 2 * np.pi), rng.uniform(-0.004, 0.004)
            ox, oy = cx + rng.normal(0, spread / 3), cy + rng.normal(0, spread / 3)
            # distance to a gently bent line through (ox, oy) with direction a0
            u = (xx - ox) * np.cos(a0) + (yy - oy) * np.sin(a0)
            v = -(xx - ox) * np.sin(a0) + (yy - oy) * np.cos(a0) - bend * u * u
            cov = stroke_coverage(np.abs(v), rng.uniform(0.4, 2.0)) * (np.abs(u) < rng.uniform(0.2, 0.6) * size)
            rgba[..., 3] = np.maximum(rgba[..., 3], cov)
        rgba[..., :3] = colour
    elif kind == "foliage":  # pointed leaves on thin stems
        for _ in range(int(rng.integers(5, 14))):
            cx, cy = rng.uniform(0.1, 0.9, 2) * size
            ang, length = rng.uniform(0, np.pi), rng.uniform(0.05, 0.15) * size
            u = (xx - cx) * np.cos(ang) + (yy - cy) * np.sin(ang)
            v = -(xx - cx) * np.sin(ang) + (yy - cy) * np.cos(ang)
            half_width = 0.35 * length * np.clip(1 - (u / length) ** 2, 0, 1)
            cov = np.clip(half_width - np.abs(v) + 0.5, 0, 1)
            green = np.array([rng.uniform(0.03, 0.15), rng.uniform(0.2, 0.5), rng.uniform(0.02, 0.1)])
            rgba[..., :3] = np.where(cov[..., None] > rgba[..., 3:], green, rgba[..., :3])
            rgba[..., 3] = np.maximum(rgba[..., 3], cov)
            stem = stroke_coverage(np.abs(v), 1.0) * (u < -length) * (u > -2.5 * length)
            rgba[..., :3] = np.where(stem[..., None] > rgba[..., 3:], [0.15, 0.1, 0.05], rgba[..., :3])
            rgba[..., 3] = np.maximum(rgba[..., 3], stem)
    elif kind == "mesh":  # chain-link fence: two families of thin lines
        pitch, width, ang = rng.uniform(18, 40), rng.uniform(1.0, 2.6), rng.uniform(0.5, 1.0)
        c = np.array([0.5, 0.5, 0.52]) * rng.uniform(0.6, 1.2)
        d1 = np.abs(((xx * np.cos(ang) + yy * np.sin(ang)) % pitch) - pitch / 2)
        d2 = np.abs(((xx * np.cos(-ang) + yy * np.sin(-ang)) % pitch) - pitch / 2)
        rgba[..., 3] = np.maximum(stroke_coverage(pitch / 2 - d1, width), stroke_coverage(pitch / 2 - d2, width))
        rgba[..., :3] = c
    elif kind == "lights":  # small, very bright lights (bokeh balls when defocused)
        for _ in range(int(rng.integers(6, 20))):
            cx, cy = rng.uniform(0.05, 0.95, 2) * size
            r = rng.uniform(1.0, 3.5)
            cov = np.clip(r + 0.5 - np.hypot(xx - cx, yy - cy), 0, 1)
            hue = rng.choice([[1.0, 0.75, 0.45], [0.6, 0.8, 1.0], [1.0, 1.0, 1.0], [1.0, 0.5, 0.6]])
            rgba[..., :3] = np.where(cov[..., None] > 0, np.asarray(hue) * rng.uniform(5, 20), rgba[..., :3])
            rgba[..., 3] = np.maximum(rgba[..., 3], cov)
    else:
        raise InputError(f"foreground kind: expected one of {ALL_KINDS}, got {kind!r}")
    return rgba


def cutout_layer(photo: np.ndarray, size: int, rng: np.random.Generator, rim_px: float = 1.0) -> np.ndarray:
    """An elliptical cut-out of a photo at a random scale and place; its alpha ramps over ``rim_px`` pixels."""
    yy, xx = (np.mgrid[0:size, 0:size] + 0.5).astype(np.float32)
    tex = fit_crop(photo, size, rng)
    cx, cy = rng.uniform(0.25, 0.75, 2) * size
    ax, ay = rng.uniform(0.12, 0.3, 2) * size
    dist = (np.hypot((xx - cx) / ax, (yy - cy) / ay) - 1.0) * min(ax, ay)
    alpha = np.clip(0.5 - dist / rim_px, 0, 1)
    return np.concatenate([tex, alpha[..., None]], axis=2)


def _load_rgba(path: Path, size: int, rng: np.random.Generator) -> np.ndarray:
    from ..photo.read import read_image

    img = read_image(path)
    if img.shape[2] != 4:
        raise InputError(f"{path}: a foreground needs an alpha channel (RGBA), got {img.shape[2]} channels")
    return fit_crop(img, size, rng)


def make_scene(config: SynthConfig, seed: int, index: int) -> tuple[list[Layer], dict]:
    """Layers (nearest first) and a description of scene ``index`` of ``seed``."""
    rng = _scene_rng(seed, index)
    n = config.size
    if config.bg_dir:
        from ..photo.read import read_image

        bg_rgb = fit_crop(read_image(rng.choice(_files(config.bg_dir, "background")))[..., :3], n, rng)
        bg_name = "user"
    else:
        bg_name = str(rng.choice(BUILTIN_BACKGROUNDS))
        bg_rgb = fit_crop(bundled_photo(bg_name), n, rng)
    # background: a tilted plane in the far third of the disparity range
    c_bg = rng.uniform(0.0, 0.2)
    g_bg = rng.uniform(-1, 1, 2) * rng.uniform(0.0, 0.12) / n
    corner = np.abs(g_bg).sum() * n
    layers = [Layer(np.concatenate([bg_rgb, np.ones((n, n, 1), np.float32)], 2),
                    plane=(float(g_bg[0]), float(g_bg[1]), float(c_bg + corner)))]
    desc = [{"kind": "background", "source": bg_name}]
    floor = c_bg + 2 * corner + 0.1
    n_fg = int(rng.integers(1, 3))
    for _ in range(n_fg):
        if config.fg_dir:
            tex, kind = _load_rgba(rng.choice(_files(config.fg_dir, "foreground")), n, rng), "user"
        else:
            if config.kinds is None:
                kind = str(rng.choice(FOREGROUND_KINDS))
            else:
                w = np.array([wk for _, wk in config.kinds], np.float64)
                kind = str(rng.choice([k for k, _ in config.kinds], p=w / w.sum()))
            if kind in ("cutout", "softcut"):
                photo = bundled_photo(str(rng.choice(BUILTIN_BACKGROUNDS)))
                tex = cutout_layer(photo, n, rng, rim_px=1.0 if kind == "cutout" else float(rng.uniform(1.0, 4.0)))
            else:
                tex = procedural_layer(kind, n, rng)
        # facing angle: a tilt of up to 0.15 in disparity across the image, above everything behind it
        g = rng.uniform(-1, 1, 2) * rng.uniform(0.0, 0.15) / n
        span = np.abs(g).sum() * n
        c = rng.uniform(floor, max(floor, 1.0 - span)) if floor + span < 1.0 else floor
        c = min(c, 1.0 - span)
        layers.insert(0, Layer(tex.astype(np.float32), plane=(float(g[0]), float(g[1]), float(c + span / 2))))
        desc.insert(0, {"kind": kind})
        floor = c + span + 0.05
        if floor >= 0.95:
            break
    return layers, {"layers": desc}


FOREGROUND_COVERAGE = 1.0 / 255.0
"""A foreground layer labels a pixel's disparity wherever its alpha exceeds this (any visible coverage)."""


def pinhole_layers(layers: list[Layer], rule: str = "any") -> tuple[np.ndarray, np.ndarray]:
    """All-in-focus image and disparity: the front-most foreground that covers a pixel gives its depth.

    ``rule``: ``"any"`` (the default): a foreground labels every pixel it covers at all (alpha > 1/255);
    ``"half"``: only where it covers at least half (alpha >= 0.5), the rule of a point-sampled depth sensor,
    of the path-traced dev set's maps and of the soft scene's matting, which splits the mixed pixels below
    one half itself.

    ``"any"`` was chosen when the renderer gave every pixel one depth: mixed edge pixels and sub-pixel strands
    then had to carry the foreground's depth or stay sharp. With the soft scene that is the matting's job, and
    ``"any"`` maps are a fraction of a pixel fatter than the dev set's (docs/refiner.md, "Labels").
    """
    _check_depth_rule(rule)
    img, _ = raytrace_layers(layers, BlurParams(0.0, 0.0), options=RaytraceOptions(max_spp=1))
    n = layers[0].rgba.shape[0]
    yy, xx = (np.mgrid[0:n, 0:n] + 0.5).astype(np.float32)
    disparity = np.zeros((n, n), np.float32)
    taken = np.zeros((n, n), bool)
    for i, lyr in enumerate(layers):  # nearest first; the last one is the background
        a, b, c = lyr.plane
        d = a * xx + b * yy + c
        alpha = lyr.rgba[..., 3]
        foreground = i < len(layers) - 1 and rule == "any"
        hit = ((alpha > FOREGROUND_COVERAGE) if foreground else (alpha >= 0.5)) & ~taken
        disparity[hit] = d[hit]
        taken |= hit
    return img[..., :3], np.clip(disparity, 0.0, 1.0)


def mean_disparity(layer: Layer) -> float:
    """Alpha-weighted mean disparity of a plane layer: where its content is, not where it is empty."""
    n = layer.rgba.shape[0]
    yy, xx = (np.mgrid[0:n, 0:n] + 0.5).astype(np.float64)
    a, b, c = layer.plane
    w = layer.rgba[..., 3].astype(np.float64)
    d = a * xx + b * yy + c
    return float(np.clip((w * d).sum() / max(w.sum(), 1e-12), 0.0, 1.0))


def generate_one(args: tuple[SynthConfig, int, int, str, bool]) -> str:
    from .datasets import write_blb_scene

    config, seed, index, out, overwrite = args
    layers, desc = make_scene(config, seed, index)
    image, disparity = pinhole_layers(layers, config.depth_rule)
    focus = [mean_disparity(layers[0]), mean_disparity(layers[-1])]
    renders, spp = [], []
    opts = RaytraceOptions(max_spp=config.max_spp)
    for k_index, k in enumerate(config.blur_levels):
        for f_index, d_f in enumerate(focus):
            out_img, st = raytrace_layers(layers, BlurParams(k, d_f), config.aperture, options=opts)
            renders.append({"k_index": k_index, "f_index": f_index, "image": out_img[..., :3]})
            spp.append(st.spp_mean)
    info = {
        "blur_parameters": list(config.blur_levels),
        "focus_disparities": focus,
        "seed": seed,
        "index": index,
        "aperture": asdict(config.aperture),
        "disparity_normalisation": "disparity = 1 / depth (depth.exr), in [0, 1], 1 = nearest",
        "coc_convention": "CoC radius [px] = K * |disparity - focus_disparity|",
        "renderer": "bokehray layered ray tracer",
        "max_spp": config.max_spp,
        "depth_rule": config.depth_rule,
        "mean_spp": float(np.mean(spp)),
        **desc,
    }
    path = write_blb_scene(Path(out) / f"scene_{index:05d}", image, disparity, renders, info, overwrite=overwrite)
    return str(path)


def generate(config: SynthConfig, n: int, out: str | os.PathLike, *, seed: int = 0, workers: int | None = None,
             progress: bool = True, overwrite: bool = False, executor: str | None = "local",
             scheduler: str | None = None) -> list[str]:
    """Generate ``n`` scenes into ``out`` (BLB layout), in parallel on ``executor`` (:mod:`bokehray.executor`).

    Existing scenes are an error unless ``overwrite`` (checked before any rendering). Each scene is written
    atomically by the worker that made it; the first scene that fails stops the run with its error.
    """
    from ..executor import make_executor
    from ..output.atomic import remove_stale_outputs

    if n < 1:
        raise InputError(f"-n: expected at least 1 scene, got {n}")
    if seed < 0:  # NumPy's SeedSequence refuses it inside the first worker, after the folder was made
        raise InputError(f"--seed: expected an integer >= 0, got {seed}")
    if workers is not None and workers < 1:
        raise InputError(f"--workers: expected at least 1, got {workers}")
    existing = [f"scene_{i:05d}" for i in range(n) if (Path(out) / f"scene_{i:05d}").exists()]
    if existing and not overwrite:
        raise InputError(f"{out}: {len(existing)} of the scenes exist already ({existing[0]}, ...); "
                         "choose another folder or pass --overwrite")
    if config.fg_dir:
        _files(config.fg_dir, "foreground")
    if config.bg_dir:
        _files(config.bg_dir, "background")
    Path(out).mkdir(parents=True, exist_ok=True)
    jobs = [(config, seed, i, str(out), overwrite) for i in range(n)]
    from .._quiet import progress_bar

    done: dict[int, str] = {}
    try:
        with make_executor(executor, workers=workers, scheduler=scheduler, tasks=n) as ex, \
                progress_bar(n, "scenes", "scene", enabled=progress, lines=True) as bar:  # no frames in a log
            for o in ex.map(generate_one, jobs):
                if not o.ok:
                    raise InputError(f"scene_{o.index:05d}: {o.error}")
                done[o.index] = o.value
                bar.update()
    finally:  # what workers killed mid-scene left behind (their scenes were rerun)
        remove_stale_outputs(Path(out), [f"scene_{i:05d}" for i in range(n)])
    return [done[i] for i in range(n)]
