"""The state behind ``bokehray view``: the photo, its disparity, the proxies, parameter validation.

Only the public API of :mod:`bokehray` is used here. Everything that does not
change between updates is computed once, when the session opens: the
reduced-resolution proxy of the image and disparity (a box mean over ``f x f``
pixels, in linear light), the sRGB display of the photo, the depth view and
the packed 16-bit disparity the page uses to draw the in-focus region.
"""

from __future__ import annotations

import dataclasses
import io
import math
import shlex
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

import bokehray as br

from ...errors import InputError

__all__ = ["EXPORT_FORMATS", "MAX_BODY_BYTES", "ProxyLadder", "RenderParams", "ViewSession", "box_factor", "box_reduce",
           "encode_jpeg", "parse_params"]

MAX_BODY_BYTES = 4096
"""Largest request body the server reads (a parameter set is ~300 bytes)."""

EXPORT_FORMATS = {"png": (8, 16), "jpg": (8,), "tif": (8, 16, 32), "exr": (16, 32)}
"""Export formats (what ``bokehray render`` writes) and their bit depths; EXR 16 is half float."""

_PARAM_KEYS = {"blur", "focus", "focus_at", "aperture", "blades", "rotation", "curvature", "highlight_boost",
               "quality", "max_spp"}


def box_factor(h: int, w: int, long_side: int) -> int:
    """The smallest integer ``f`` such that ``max(h, w) / f <= long_side``."""
    return max(1, math.ceil(max(h, w) / max(1, int(long_side))))


def box_reduce(a: np.ndarray, f: int) -> np.ndarray:
    """Mean over ``f x f`` blocks (edge-padded to a multiple of ``f``): shape ``ceil(h/f) x ceil(w/f) [x C]``."""
    if f == 1:
        return np.ascontiguousarray(a, np.float32)
    h, w = a.shape[:2]
    ph, pw = -h % f, -w % f
    pad = ((0, ph), (0, pw)) + ((0, 0),) * (a.ndim - 2)
    a = np.pad(a, pad, mode="edge") if ph or pw else a
    shape = (a.shape[0] // f, f, a.shape[1] // f, f) + a.shape[2:]
    return np.ascontiguousarray(a.reshape(shape).mean(axis=(1, 3), dtype=np.float32), np.float32)


# sRGB encoding through a 16-bit table: a lookup per pixel instead of a power law
_LIN = np.linspace(0.0, 1.0, 65536, dtype=np.float64)
_SRGB8 = np.round(255.0 * np.where(_LIN <= 0.0031308, 12.92 * _LIN, 1.055 * _LIN ** (1 / 2.4) - 0.055)).astype(np.uint8)


def to_srgb8(linear: np.ndarray) -> np.ndarray:
    """Scene-linear float (H x W x C, C in 1, 3, 4) to 8-bit sRGB RGB (alpha dropped, grey repeated)."""
    a = linear if linear.ndim == 3 else linear[..., None]
    a = a[..., :3] if a.shape[2] >= 3 else np.repeat(a[..., :1], 3, axis=2)
    idx = (np.clip(a, 0.0, 1.0) * 65535.0 + 0.5).astype(np.uint16)
    return _SRGB8[idx]


def encode_jpeg(rgb8: np.ndarray, quality: int = 90) -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(rgb8, "RGB").save(buf, "JPEG", quality=quality)
    return buf.getvalue()


def encode_png(arr: np.ndarray, mode: str) -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(arr, mode).save(buf, "PNG", compress_level=1)
    return buf.getvalue()


class ProxyLadder:
    """Which proxy the next live update renders at: a feedback rule on the last update's render time.

    Level 0 is the finest proxy (``--proxy-size``); each next level has about 3/4 of the long side (just over
    half the pixels). A render slower than ``budget_s`` steps one level coarser; one faster than
    ``step_up * budget_s`` steps one level finer (a level costs ~1.8x the next, so the finer one is expected
    inside the budget). During a drag the parameters change a little per update, so the last update predicts
    the next: strong blur and bladed apertures, which cost more per pixel, settle on a coarser proxy instead
    of slowing the page down.
    """

    def __init__(self, levels: int, budget_s: float = 0.19, step_up: float = 0.45) -> None:
        self.levels, self.budget_s, self.step_up = int(levels), float(budget_s), float(step_up)
        self.level = 0

    def report(self, seconds: float) -> int:
        if seconds > self.budget_s and self.level < self.levels - 1:
            self.level += 1
        elif seconds < self.step_up * self.budget_s and self.level > 0:
            self.level -= 1
        return self.level


@dataclass(frozen=True)
class RenderParams:
    """A validated parameter set from the page (the same objects, ranges and errors as ``bokehray render``)."""

    k_px: float
    focus: float | None
    focus_at: tuple[int, int] | None
    aperture: str
    blades: int
    rotation: float
    curvature: float
    highlight_boost: float
    quality: str
    max_spp: int
    blur: br.BlurParams
    lens: br.Aperture

    def key(self) -> tuple:
        return (self.blur.k_px, self.blur.focus_disparity, self.lens, self.highlight_boost, self.quality,
                self.max_spp)


def _number(body: dict, name: str, flag: str, default: float) -> float:
    v = body.get(name, default)
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise InputError(f"{flag}: expected a number, got {v!r}")
    v = float(v)
    if not math.isfinite(v):
        raise InputError(f"{flag}: expected a finite number, got {v!r}")
    return v


def _integer(body: dict, name: str, flag: str, default: int) -> int:
    v = body.get(name, default)
    if isinstance(v, bool) or not isinstance(v, int):
        raise InputError(f"argument {flag}: invalid int value: {v!r}")
    return v


def parse_params(body: object, disparity: np.ndarray) -> RenderParams:
    """Validate a JSON parameter set against the full-resolution ``disparity``; raises :class:`InputError`.

    Errors read as the CLI's do, because the same constructors check the same things:
    ``BlurParams`` (K, focus), ``Aperture`` (blades 3..32, curvature 0..1), ``focus_at`` (pixel in the
    image), ``RaytraceOptions`` (rays per pixel); ``--blur`` < 0 and ``--highlight-boost`` as in
    ``cmd_render``.
    """
    if not isinstance(body, dict):
        raise InputError(f"parameters: expected a JSON object, got {type(body).__name__}")
    unknown = sorted(set(body) - _PARAM_KEYS - {"stage"})
    if unknown:
        raise InputError(f"parameters: unknown {', '.join(map(repr, unknown))}")
    from ...photo.subject import AMOUNT_DEFAULT, k_from_amount, subject_focus

    if body.get("blur") is None:  # the CLI's default: --amount 50 of the image diagonal
        k = k_from_amount(AMOUNT_DEFAULT, *disparity.shape)
    else:
        k = _number(body, "blur", "--blur", 0.0)
    if k < 0:
        raise InputError(f"--blur: expected K >= 0, got {k:g}")
    focus_val, at = body.get("focus"), body.get("focus_at")
    if focus_val is not None and at is not None:
        raise InputError("--focus and --focus-at contradict each other: give the focus one way")
    focus: float | None = None
    xy: tuple[int, int] | None = None
    if focus_val is None and at is None:  # the CLI's default: focus on the subject
        focus_val = subject_focus(disparity).d_f
        body = {**body, "focus": focus_val}
    if at is not None:
        if (not isinstance(at, list) or len(at) != 2
                or any(isinstance(v, bool) or not isinstance(v, int) for v in at)):
            raise InputError(f"argument --focus-at: expected X,Y in pixels (e.g. 640,410), got {at!r}")
        xy = (at[0], at[1])
        d_f = br.focus_at(disparity, *xy)
    else:
        focus = _number(body, "focus", "--focus", 0.0)
        d_f = focus
    blur = br.BlurParams(k, d_f)
    shape = body.get("aperture", "disc")
    if shape not in ("disc", "polygon"):
        raise InputError(f"argument --aperture: invalid choice: {shape!r} (choose from 'disc', 'polygon')")
    blades = _integer(body, "blades", "--blades", 6)
    rotation = _number(body, "rotation", "--rotation", 0.0)
    curvature = _number(body, "curvature", "--curvature", 0.0)
    lens = br.Aperture() if shape == "disc" else br.Aperture(blades=blades, rotation_deg=rotation, curvature=curvature)
    boost = _number(body, "highlight_boost", "--highlight-boost", 0.0)
    if boost < 0:
        raise InputError(f"highlight_boost: expected a finite value >= 0, got {boost!r}")
    quality = body.get("quality", "preview")
    if quality not in br.QUALITIES:
        raise InputError(f"argument --quality: invalid choice: {quality!r} (choose from "
                         f"{', '.join(map(repr, br.QUALITIES))})")
    max_spp = _integer(body, "max_spp", "--max-spp", 128)
    br.RaytraceOptions(max_spp=max_spp)  # validated whatever the quality, as the CLI does
    return RenderParams(k, focus, xy, shape, blades, rotation, curvature, boost, quality, max_spp, blur, lens)


def _fmt(v: float) -> str:
    """Shortest text that parses back to the same float (so the command line reproduces the render)."""
    return repr(float(v))


class ViewSession:
    """One photo and its disparity, loaded once, with everything the page needs that does not change.

    Args:
        image: scene-linear H x W x C float32 (C = 1, 3, 4).
        disparity: H x W in [0, 1] (already resized, if it had to be).
        proxy_long_side: the live preview renders at most this many pixels on the long side (the finest
            proxy; coarser ones take over while updates are slow, see :class:`ProxyLadder`).
        display_long_side: the refined full-resolution render is sent to the page reduced to this size
            (the export writes every pixel).
        image_path, disparity_arg, depth_path, resize_disparity: what the command line was given, for
            the command shown on the page.
        export_dir: the only folder exports are written to.
        device: Warp device of every render.
    """

    def __init__(self, image: np.ndarray, disparity: np.ndarray, *, proxy_long_side: int = 640,
                 display_long_side: int = 2048, image_path: str | None = None, disparity_path: str | None = None,
                 depth_model_path: str | None = None,
                 depth_path: str | None = None, resize_disparity: bool = False, export_dir: str | Path = ".",
                 device: str = "cpu") -> None:
        if proxy_long_side < 16:
            raise InputError(f"--proxy-size: expected at least 16 pixels, got {proxy_long_side}")
        if display_long_side < 16:
            raise InputError(f"--display-size: expected at least 16 pixels, got {display_long_side}")
        self.image = np.ascontiguousarray(image, np.float32)
        if self.image.ndim == 2:
            self.image = self.image[..., None]
        self.disparity = np.ascontiguousarray(disparity, np.float32)
        self.h, self.w = self.image.shape[:2]
        if self.disparity.shape != (self.h, self.w):
            raise InputError(f"disparity: expected shape {(self.h, self.w)} (the image's H x W), got "
                             f"{self.disparity.shape}")
        self.device = device
        self.image_path, self.disparity_path, self.depth_path = image_path, disparity_path, depth_path
        self.depth_model_path = depth_model_path
        self.resize_disparity = resize_disparity
        self.export_dir = Path(export_dir).resolve()
        # the proxies: f x f box means in linear light (K scales by 1/f), finest first; see ProxyLadder
        f0 = box_factor(self.h, self.w, proxy_long_side)
        factors = sorted({f0, *(math.ceil(f0 * (4 / 3) ** i) for i in (1, 2, 3, 4))})
        self.proxies = [(f, box_reduce(self.image, f), np.clip(box_reduce(self.disparity, f), 0.0, 1.0))
                        for f in factors]
        self.proxy_factor, self.proxy_image, self.proxy_disparity = self.proxies[0]
        self.ladder = ProxyLadder(len(self.proxies))
        self.display_factor = box_factor(self.h, self.w, display_long_side)
        self._cache: dict[str, bytes] = {}
        self._full: tuple[tuple, np.ndarray] | None = None  # the last full-resolution render and its key

    @classmethod
    def from_files(cls, image_path: str, *, disparity: str | None = None, depth: str | None = None,
                   depth_model: str | None = None, resize_disparity: bool = False, **kw) -> ViewSession:
        """Read the inputs as ``bokehray render`` does (the same readers, depth conventions, checks and messages;
        ``depth_model`` estimates the map with a local checkpoint, as ``--depth-model`` does)."""
        from ..render_job import read_map

        image = br.read_image(image_path)
        d, _ = read_map(image, disparity=disparity, depth=depth, depth_model=depth_model,
                        resize_disparity=resize_disparity, device=kw.get("device", "cpu"))
        return cls(image, d, image_path=image_path, disparity_path=disparity, depth_path=depth,
                   depth_model_path=depth_model, resize_disparity=resize_disparity, **kw)

    # --- what does not change -------------------------------------------------------------------------
    def _cached(self, name: str, make) -> bytes:
        if name not in self._cache:
            self._cache[name] = make()
        return self._cache[name]

    def photo_jpeg(self) -> bytes:
        return self._cached("photo", lambda: encode_jpeg(to_srgb8(box_reduce(self.image, self.display_factor))))

    def depth_png(self) -> bytes:
        """The disparity as grey (white = near), at display size."""
        def make() -> bytes:
            d = box_reduce(self.disparity, self.display_factor)
            return encode_png((np.clip(d, 0, 1) * 255 + 0.5).astype(np.uint8), "L")
        return self._cached("depth", make)

    def disparity16_png(self) -> bytes:
        """The disparity at display size as 16 bits packed in R (high byte) and G (low byte), B = 0.

        The page reads it back with a canvas to draw the in-focus region without a round trip.
        """
        def make() -> bytes:
            q = (np.clip(box_reduce(self.disparity, self.display_factor), 0, 1) * 65535 + 0.5).astype(np.uint16)
            rgb = np.stack([(q >> 8).astype(np.uint8), (q & 255).astype(np.uint8), np.zeros_like(q, np.uint8)], 2)
            return encode_png(rgb, "RGB")
        return self._cached("disp16", make)

    def info(self) -> dict:
        names = {"image": Path(self.image_path).name if self.image_path else "(array)",
                 "map": Path(self.depth_model_path or self.depth_path or self.disparity_path or "(array)").name,
                 "map_kind": "depth model" if self.depth_model_path else "depth" if self.depth_path else "disparity"}
        return {
            "width": self.w, "height": self.h, "files": names,
            "proxy": {"factor": self.proxy_factor, "width": self.proxy_image.shape[1],
                      "height": self.proxy_image.shape[0], "factors": [f for f, _, _ in self.proxies]},
            "display": {"factor": self.display_factor, "width": -(-self.w // self.display_factor),
                        "height": -(-self.h // self.display_factor)},
            "default_blur": float(max(1, round(self.w / 50))), "max_blur": float(max(8, round(self.w / 8))),
            "qualities": list(br.QUALITIES), "export_formats": {k: list(v) for k, v in EXPORT_FORMATS.items()},
            "export_dir": str(self.export_dir), "max_body_bytes": MAX_BODY_BYTES,
        }

    # --- renders --------------------------------------------------------------------------------------
    def render_preview(self, p: RenderParams, check=None) -> tuple[bytes, dict]:
        """The live preview: preview level on a proxy with ``K / f``; ``check()`` may raise to abandon it.

        The proxy is the ladder's choice (:class:`ProxyLadder`); an abandoned render does not move the ladder.
        """
        level = self.ladder.level
        f, image, disparity = self.proxies[level]
        blur = br.BlurParams(p.blur.k_px / f, p.blur.focus_disparity)
        progress = (lambda done, total: check()) if check is not None else None
        t = time.perf_counter()
        out, stats = br.render_with_stats(image, disparity, blur, p.lens, quality="preview",
                                          device=self.device, highlight_boost=p.highlight_boost, progress=progress)
        self.ladder.report(time.perf_counter() - t)
        if check is not None:
            check()
        return encode_jpeg(to_srgb8(out), 88), {"factor": f, "layers": stats.layers, "level": level}

    def render_full(self, p: RenderParams, check=None) -> np.ndarray:
        """Every pixel at the chosen quality (cached for the export of the same parameters)."""
        key = p.key()
        if self._full is not None and self._full[0] == key:
            return self._full[1]
        progress = (lambda done, total: check()) if check is not None else None
        if check is not None:
            check()
        out, _ = br.render_with_stats(self.image, self.disparity, p.blur, p.lens, quality=p.quality,
                                      device=self.device, highlight_boost=p.highlight_boost, progress=progress,
                                      options=br.RaytraceOptions(max_spp=p.max_spp) if p.quality == "raytrace"
                                      else None)
        self._full = None  # drop the old one before keeping the new one: one full-size image at a time
        self._full = (key, out)
        return out

    def full_display(self, p: RenderParams, check=None) -> tuple[bytes, dict]:
        """The refinement the page shows when the input rests: every pixel at the preview level, reduced for display.

        Always the preview level, whatever ``p.quality``: the ray tracer has no progress hook in the public
        API, so a ray-traced refinement could not be abandoned when the user drags again (it would hold every
        preview back for its whole run). The chosen level is what the export renders.
        """
        p = dataclasses.replace(p, quality="preview")
        out = self.render_full(p, check)
        if check is not None:
            check()
        f = self.display_factor
        return encode_jpeg(to_srgb8(box_reduce(out, f)), 90), {"factor": f}

    # --- export ---------------------------------------------------------------------------------------
    def export_path(self, fmt: str) -> Path:
        stem = Path(self.image_path).stem if self.image_path else "render"
        for n in range(1, 100000):
            p = self.export_dir / f"{stem}-bokeh-{n:03d}.{fmt}"
            if not p.exists():
                return p
        raise InputError(f"{self.export_dir}: no free export name left")

    def export(self, p: RenderParams, fmt: str, bit_depth: int | None, check=None) -> tuple[Path, str]:
        if fmt not in EXPORT_FORMATS:
            raise InputError(f"export format: expected one of {', '.join(EXPORT_FORMATS)}, got {fmt!r}")
        if bit_depth is not None and (isinstance(bit_depth, bool) or not isinstance(bit_depth, int)):
            raise InputError(f"argument --bit-depth: invalid int value: {bit_depth!r}")
        bits, half = bit_depth, False  # EXR at 16 bits is half float, as `--bit-depth 16` gives
        path = self.export_path(fmt)
        from ...output.write import check_output_path  # the same check as `bokehray render -o`, before rendering

        check_output_path(path, bit_depth=bits, half=half)
        out = self.render_full(p, check)
        written = br.write_image(path, out, bit_depth=bits, half=half)
        return written, self.command(p, written, bit_depth=bits, half=half)

    def command(self, p: RenderParams, output: str | Path, *, bit_depth: int | None = None,
                half: bool = False) -> str:
        """The ``bokehray render`` command line that writes the same image."""
        from ...photo.highlights import is_display_referred

        q = shlex.quote
        img = str(Path(self.image_path).resolve()) if self.image_path else "IMAGE"
        args = ["bokehray", "render", q(img)]
        if self.depth_model_path:
            args += ["--depth-model", q(str(Path(self.depth_model_path).resolve()))]
        elif self.depth_path:
            args += ["--depth", q(str(Path(self.depth_path).resolve()))]
        else:
            args += ["--disparity", q(str(Path(self.disparity_path).resolve()) if self.disparity_path else "D")]
        if self.resize_disparity:
            args.append("--resize-disparity")
        args += ["-o", q(str(output)), "--blur", _fmt(p.k_px)]
        args += ["--focus-at", f"{p.focus_at[0]},{p.focus_at[1]}"] if p.focus_at else ["--focus", _fmt(p.focus)]
        if p.aperture == "polygon":
            args += ["--aperture", "polygon", "--blades", str(p.blades), "--rotation", _fmt(p.rotation),
                     "--curvature", _fmt(p.curvature)]
        if p.highlight_boost:
            args += ["--highlight-boost", _fmt(p.highlight_boost)]
        elif self.image_path and is_display_referred(self.image_path):
            # the page shows a display-referred photo's highlights as they are (its boost control instead)
            args.append("--no-highlight-reconstruction")
        if p.quality != "preview":
            args += ["--quality", p.quality, "--max-spp", str(p.max_spp)]
        if bit_depth is not None:
            args += ["--bit-depth", str(bit_depth)]
        if half:
            args.append("--half")
        if self.device != "cpu":
            args += ["--device", self.device]
        return " ".join(args)
