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
import os
import shlex
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

import bokehray as br

from ...errors import InputError, OutputError, OutputExistsError
from ...levels import PHOTO_QUALITIES, check_photo_quality

__all__ = [
    "EXPORT_FORMATS",
    "MAX_BODY_BYTES",
    "ProxyLadder",
    "RenderParams",
    "ViewSession",
    "box_factor",
    "box_reduce",
    "encode_jpeg",
    "export_choice",
    "json_integer",
    "json_number",
    "parse_params",
]

MAX_BODY_BYTES = 4096
"""Largest request body the server reads (a parameter set is ~300 bytes)."""

EXPORT_FORMATS = {"png": (8, 16), "jpg": (8,), "tif": (8, 16, 32), "exr": (16, 32)}
"""Export formats (what ``bokehray render`` writes) and their bit depths; EXR 16 is half float."""

FOCUS_CROP_HALF = 160
"""Half the side of the focus crop (:meth:`ViewSession.focus_crop`), in the pixels the screen shows."""

EXPORT_NAME_TRIES = 100
"""Names an export tries when other exports keep taking the next free one first."""

_PARAM_KEYS = {"lens", "amount", "blur", "focus", "focus_at", "aperture", "blades", "rotation", "curvature", "highlight_boost",
               "reconstruct", "quality", "grain"}


def box_factor(h: int, w: int, long_side: int) -> int:
    """The smallest integer ``f`` such that ``max(h, w) / f <= long_side``."""
    return max(1, math.ceil(max(h, w) / max(1, int(long_side))))


def box_reduce(a: np.ndarray, f: int) -> np.ndarray:
    """Mean over ``f x f`` blocks (edge-padded to a multiple of ``f``): shape ``ceil(h/f) x ceil(w/f) [x C]``.
    OpenCV's area resampling, which at a whole factor is the block mean, on all cores; only the ragged last row and
    column of blocks are padded (a 12 MP photo's proxy ladder: 1.6 s as NumPy means over padded copies, 0.1 s)."""
    a = np.asarray(a, np.float32)
    if f == 1:
        return np.ascontiguousarray(a)
    h, w = a.shape[:2]
    hq, wq = h // f, w // f
    out = np.empty((-(-h // f), -(-w // f)) + a.shape[2:], np.float32)
    out[:hq, :wq] = _box_whole(a[: hq * f, : wq * f], f)
    if w > wq * f:  # the last column of blocks, its columns edge-padded
        out[:hq, wq:] = _box_whole(_edge_pad(a[: hq * f, wq * f :], 1, f), f)
    if h > hq * f:  # the last row of blocks
        out[hq:] = _box_whole(_edge_pad(_edge_pad(a[hq * f :], 0, f), 1, f * out.shape[1]), f)
    return out


def _edge_pad(a: np.ndarray, axis: int, n: int) -> np.ndarray:
    """``a`` along ``axis`` to ``n`` entries, its last one repeated."""
    pad = [(0, 0)] * a.ndim
    pad[axis] = (0, n - a.shape[axis])
    return np.pad(a, pad, mode="edge")


def _box_whole(a: np.ndarray, f: int) -> np.ndarray:
    """:func:`box_reduce` of an array whose sides are multiples of ``f`` (a strided view is read in place)."""
    import cv2

    h, w = a.shape[:2]
    if h == 0 or w == 0:
        return np.zeros((h // f, w // f) + a.shape[2:], np.float32)
    if a.strides[-1] != a.itemsize or (a.ndim == 3 and a.strides[1] != a.itemsize * a.shape[2]):
        a = np.ascontiguousarray(a)  # OpenCV takes rows of contiguous pixels
    out = cv2.resize(a, (w // f, h // f), interpolation=cv2.INTER_AREA)
    return out.reshape(out.shape[:2] + a.shape[2:])  # a single channel keeps its axis


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
    half the pixels, ~1.8x cheaper). A render slower than ``budget_s`` steps coarser by as many levels as it
    was over the budget (``ceil(log(t / budget) / log 1.8)``: 0.79 s against 0.19 s is three levels at once,
    so a loaded machine is caught up with in one update); one faster than ``step_up * budget_s`` steps one level
    finer. During a drag the parameters change a little per update, so the last update predicts the next:
    strong blur, bladed apertures and a busy machine settle on a coarser proxy instead of slowing the page down.
    A preview abandoned after it already took longer than the budget is reported too (a slow machine shows
    itself even when every preview is replaced before it ends).
    """

    def __init__(self, levels: int, budget_s: float = 0.19, step_up: float = 0.45) -> None:
        self.levels, self.budget_s, self.step_up = int(levels), float(budget_s), float(step_up)
        self.level = 0

    def report(self, seconds: float) -> int:
        if seconds > self.budget_s and self.level < self.levels - 1:
            ratio = seconds / self.budget_s if self.budget_s > 0 else 1.8
            steps = max(1, math.ceil(math.log(ratio) / math.log(1.8) - 1e-9))
            self.level = min(self.levels - 1, self.level + steps)
        elif seconds < self.step_up * self.budget_s and self.level > 0:
            self.level -= 1
        return self.level


@dataclass(frozen=True)
class RenderParams:
    """A validated parameter set from the page (the same objects, ranges and errors as ``bokehray render``).

    ``amount`` is set when the blur came as an amount (0..100, ``--amount``), else ``k_px`` was given as ``blur``
    (``--blur``); ``focus`` and ``focus_at`` are both None for the default focus (the subject, as ``render``
    chooses it); ``reconstruct`` is highlight reconstruction (``render``'s default for a display-referred photo,
    ``--no-highlight-reconstruction`` off; a ``highlight_boost`` replaces it, as in ``render``); ``grain`` is the
    export's finishing step for a display-referred photo (``render``'s default, ``--no-grain`` off)."""

    k_px: float
    focus: float | None
    focus_at: tuple[int, int] | None
    aperture: str
    blades: int
    rotation: float
    curvature: float
    highlight_boost: float
    quality: str
    blur: br.BlurParams
    lens: br.Aperture
    amount: float | None = None
    reconstruct: bool = False
    thin_lens: br.ThinLens | None = None
    grain: bool = True

    def key(self) -> tuple:
        return (self.blur.k_px, self.blur.focus_disparity, self.lens, self.highlight_boost, self.quality,
                self.reconstructs)

    @property
    def focus_default(self) -> bool:
        return self.focus is None and self.focus_at is None and self.thin_lens is None

    @property
    def reconstructs(self) -> bool:
        """Whether the render reconstructs highlights (as ``render`` decides: not with a boost)."""
        return self.reconstruct and self.highlight_boost == 0


def json_number(v: object, flag: str) -> float:
    """The one check of a JSON number: a finite float (an int too large for a float, a bool, a string: refused)."""
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise InputError(f"{flag}: expected a number, got {v!r}"[:200])
    try:
        f = float(v)
    except OverflowError:
        raise InputError(f"{flag}: expected a number in range, got an integer of {len(str(v))} digits") from None
    if not math.isfinite(f):
        raise InputError(f"{flag}: expected a finite number, got {v!r}")
    return f


def json_integer(v: object, flag: str) -> int:
    if isinstance(v, bool) or not isinstance(v, int):
        raise InputError(f"argument {flag}: invalid int value: {v!r}"[:200])
    if abs(v) > 2**31:
        raise InputError(f"argument {flag}: {len(str(v))}-digit integer out of range")
    return v


def _number(body: dict, name: str, flag: str, default: float) -> float:
    return json_number(body.get(name, default), flag)


def _integer(body: dict, name: str, flag: str, default: int) -> int:
    return json_integer(body.get(name, default), flag)


_LENS_KEYS = {"focal_length", "f_number", "focus_distance", "sensor_width"}


def _physical(spec: object, at: tuple[int, int] | None, disparity: np.ndarray, norm) -> br.ThinLens:
    """A physical lens from ``{"focal_length", "f_number", "focus_distance" | focus_at, "sensor_width"}``, focused as
    ``render`` focuses one (``--focus-at`` through the metric map)."""
    if norm is None:
        raise InputError("a physical lens (--focal-length/--f-number/--focus-distance) needs metric depth, and "
                         "a --disparity map has no scale: give a depth map in metres with --depth, or set the blur "
                         "with --amount/--blur and the focus with --focus/--focus-at")
    if not isinstance(spec, dict) or set(spec) - _LENS_KEYS:
        raise InputError(f"lens: expected {{\"focal_length\", \"f_number\", \"focus_distance\", "
                         f"\"sensor_width\"}}, got {spec!r}"[:200])
    if spec.get("focal_length") is None or spec.get("f_number") is None:
        raise InputError("a physical lens needs both --focal-length and --f-number")
    focal = json_number(spec["focal_length"], "--focal-length")
    n = json_number(spec["f_number"], "--f-number")
    sensor = json_number(spec.get("sensor_width", 36.0), "--sensor-width")
    z = spec.get("focus_distance")
    if z is not None and at is not None:
        raise InputError("--focus-at and --focus-distance contradict each other: give the focus one way")
    if at is not None:
        z = float(norm.depth(br.focus_at(disparity, *at)))
        if not math.isfinite(z):
            raise InputError(f"--focus-at {at[0]},{at[1]}: that point is at infinity (sky); a thin lens focused there "
                             "needs --focus-distance, or click on a surface")
    elif z is None:
        raise InputError("a physical lens needs --focus-distance or --focus-at X,Y")
    else:
        z = json_number(z, "--focus-distance")
    return br.ThinLens(focal, n, z, sensor)


def parse_params(body: object, disparity: np.ndarray, *, subject_d_f: float | None = None,  # noqa: C901
                 reconstruct_default: bool = False, norm=None) -> RenderParams:
    """Validate a JSON parameter set against the full-resolution ``disparity``; raises :class:`InputError`.

    Errors read as the CLI's do, because the same constructors check the same things:
    ``BlurParams`` (K, focus), ``Aperture`` (blades 3..32, curvature 0..1), ``focus_at`` (pixel in the
    image), ``RaytraceOptions`` (rays per pixel); ``--blur`` < 0, ``--amount`` 0..100 and ``--highlight-boost``
    as in ``cmd_render``. What is not given is what ``render`` does: ``--amount 50``, the focus on the subject
    (``subject_d_f`` when the caller has it cached), highlight reconstruction as ``reconstruct_default``.
    """
    if not isinstance(body, dict):
        raise InputError(f"parameters: expected a JSON object, got {type(body).__name__}")
    unknown = sorted(set(body) - _PARAM_KEYS - {"stage", "long_side", "format", "bit_depth"})
    if unknown:
        raise InputError(f"parameters: unknown {', '.join(map(repr, unknown))}"[:300])
    from ...photo.subject import AMOUNT_DEFAULT, k_from_amount, subject_focus

    amount: float | None = None
    if body.get("lens") is not None and any(body.get(k) is not None for k in ("amount", "blur", "focus")):
        raise InputError("give the blur either as --amount/--blur with --focus, or as a physical lens, not both")
    if body.get("blur") is not None and body.get("amount") is not None:
        raise InputError("give the blur either as --amount or as --blur, not both")
    if body.get("blur") is None:  # the CLI's default: --amount 50 of the image diagonal
        amount = AMOUNT_DEFAULT if body.get("amount") is None else json_number(body["amount"], "--amount")
        k = k_from_amount(amount, *disparity.shape)
    else:
        k = _number(body, "blur", "--blur", 0.0)
    if k < 0:
        raise InputError(f"--blur: expected K >= 0, got {k:g}")
    focus_val, at = body.get("focus"), body.get("focus_at")
    if focus_val is not None and at is not None:
        raise InputError("--focus and --focus-at contradict each other: give the focus one way")
    focus: float | None = None
    xy: tuple[int, int] | None = None
    if at is not None:
        if (not isinstance(at, list) or len(at) != 2
                or any(isinstance(v, bool) or not isinstance(v, int) for v in at)):
            raise InputError(f"argument --focus-at: expected X,Y in pixels (e.g. 640,410), got {at!r}"[:200])
        xy = (json_integer(at[0], "--focus-at"), json_integer(at[1], "--focus-at"))
        d_f = br.focus_at(disparity, *xy)
    elif focus_val is not None:
        focus = _number(body, "focus", "--focus", 0.0)
        d_f = focus
    else:  # the CLI's default: focus on the subject
        d_f = subject_focus(disparity).d_f if subject_d_f is None else subject_d_f
    thin = None
    if body.get("lens") is not None:  # render's physical branch: K and d_f from the lens and the metric map
        thin = _physical(body["lens"], xy, disparity, norm)
        pb = thin.blur_params(norm, disparity.shape[1])
        k, d_f, amount = pb.k_px, pb.focus_disparity, None
    blur = br.BlurParams(k, d_f)
    shape = body.get("aperture", "disc")
    if not isinstance(shape, str) or shape not in ("disc", "polygon"):
        raise InputError(f"argument --aperture: invalid choice: {shape!r} (choose from 'disc', 'polygon')"[:200])
    blades = _integer(body, "blades", "--blades", 6)
    rotation = _number(body, "rotation", "--rotation", 0.0)
    curvature = _number(body, "curvature", "--curvature", 0.0)
    lens = br.Aperture() if shape == "disc" else br.Aperture(blades=blades, rotation_deg=rotation, curvature=curvature)
    boost = _number(body, "highlight_boost", "--highlight-boost", 0.0)
    if boost < 0:
        raise InputError(f"highlight_boost: expected a finite value >= 0, got {boost!r}")
    reconstruct = body.get("reconstruct", reconstruct_default)
    if not isinstance(reconstruct, bool):
        raise InputError(f"reconstruct: expected true or false, got {reconstruct!r}"[:200])
    quality = check_photo_quality(body.get("quality", "preview"))
    grain = body.get("grain", True)
    if not isinstance(grain, bool):
        raise InputError(f"grain: expected true or false, got {grain!r}"[:200])
    return RenderParams(k, focus, xy, shape, blades, rotation, curvature, boost, quality, blur, lens,
                        amount, reconstruct, thin, grain)


def _fmt(v: float) -> str:
    """Shortest text that parses back to the same float (so the command line reproduces the render)."""
    return repr(float(v))


def _signed_option(flag: str, v: float) -> list[str]:
    """``flag`` and a value that may be negative: ``--rotation=-1e-05`` joined by ``=``, since argparse takes a
    separate ``-1e-05`` (or ``-1e+16``: not its plain negative-number pattern) for an option."""
    text = _fmt(v)
    return [f"{flag}={text}"] if text.startswith("-") else [flag, text]


def export_choice(body: dict) -> tuple[str, int | None]:
    """The export's format and bit depth in a request body (``format``: PNG by default; ``bit_depth``: None or one
    the format takes), :class:`InputError` for one it does not take."""
    fmt = body.get("format", "png")
    if not isinstance(fmt, str) or fmt not in EXPORT_FORMATS:
        raise InputError(f"export format: expected one of {', '.join(EXPORT_FORMATS)}, got {fmt!r}"[:200])
    bits = body.get("bit_depth")
    if bits is not None and (isinstance(bits, bool) or not isinstance(bits, int) or bits not in EXPORT_FORMATS[fmt]):
        raise InputError(f"argument --bit-depth: {fmt} takes {', '.join(map(str, EXPORT_FORMATS[fmt]))}, "
                         f"got {bits!r}"[:200])
    return fmt, bits


class ViewSession:
    """One photo and its disparity, loaded once, with everything the page needs that does not change.

    Args:
        image: scene-linear H x W x C float32 (C = 1, 3, 4), as read (before highlight reconstruction).
        disparity: H x W in [0, 1] (already resized, if it had to be).
        proxy_long_side: the live preview renders at most this many pixels on the long side (the finest
            proxy; coarser ones take over while updates are slow, see :class:`ProxyLadder`).
        display_long_side: the largest size the sharp version for the screen is rendered at (the page asks
            for the size its canvas shows, at most this; 100 % zoom asks for every pixel). Exports are full size.
        image_path, disparity_arg, depth_path, resize_disparity: what the command line was given, for
            the command shown on the page.
        reconstruct: highlight reconstruction by default (``render``'s default: on for a display-referred file);
            None decides it from ``image_path`` as ``render`` does.
        norm: the depth normalisation of a metric ``--depth`` map (metres on the page).
        export_dir: the only folder exports are written to.
        device: Warp device of every render.
    """

    def __init__(self, image: np.ndarray, disparity: np.ndarray, *, proxy_long_side: int = 640,
                 display_long_side: int = 2048, image_path: str | None = None, disparity_path: str | None = None,
                 depth_model_path: str | None = None,
                 depth_path: str | None = None, resize_disparity: bool = False, export_dir: str | Path = ".",
                 device: str = "cpu", reconstruct: bool | None = None, norm=None) -> None:
        if proxy_long_side < 16:
            raise InputError(f"--proxy-size: expected at least 16 pixels, got {proxy_long_side}")
        if display_long_side < 16:
            raise InputError(f"--display-size: expected at least 16 pixels, got {display_long_side}")
        self.raw_image = np.ascontiguousarray(image, np.float32)
        if self.raw_image.ndim == 2:
            self.raw_image = self.raw_image[..., None]
        self.disparity = np.ascontiguousarray(disparity, np.float32)
        self.d_lo, self.d_hi = float(self.disparity.min()), float(self.disparity.max())  # the map's range, read once
        self.h, self.w = self.raw_image.shape[:2]
        if self.disparity.shape != (self.h, self.w):
            raise InputError(f"disparity: expected shape {(self.h, self.w)} (the image's H x W), got "
                             f"{self.disparity.shape}")
        self.device = device
        self.image_path, self.disparity_path, self.depth_path = image_path, disparity_path, depth_path
        self.depth_model_path = depth_model_path
        self.resize_disparity = resize_disparity
        self.norm = norm
        self.export_dir = Path(export_dir).resolve()
        from ...photo.highlights import is_display_referred
        from ...photo.subject import AMOUNT_DEFAULT, default_focus, k_from_amount

        self.display_referred = bool(image_path) and is_display_referred(image_path)
        self.reconstruct_default = self.display_referred if reconstruct is None else bool(reconstruct)
        # the default focus, as `render` chooses it: the eyes of the nearest face, else the subject
        self.subject = default_focus(self.raw_image, self.disparity)
        self.default_k = k_from_amount(AMOUNT_DEFAULT, self.h, self.w)
        self.proxy_long_side = proxy_long_side
        self.display_factor = box_factor(self.h, self.w, display_long_side)
        self._variants: dict[bool, tuple[np.ndarray, list]] = {}
        self.image, self.proxies = self._variant(self.reconstruct_default)
        self.proxy_factor, self.proxy_image, self.proxy_disparity = self.proxies[0]
        self.ladder = ProxyLadder(len(self.proxies))
        self._cache: dict[str, bytes] = {}
        self._full: tuple[tuple, np.ndarray] | None = None  # the last full-resolution render and its key
        self._screen: tuple[tuple, np.ndarray, np.ndarray] | None = None  # (factor, reconstructs), image, disparity

    def _variant(self, reconstructs: bool) -> tuple[np.ndarray, list]:
        """The image (highlights reconstructed or not) and its proxies: ``f x f`` box means in linear light
        (K scales by 1/f), finest first; see :class:`ProxyLadder`. Built once each, when first needed."""
        if reconstructs not in self._variants:
            image = self.raw_image
            if reconstructs:
                from ...photo.highlights import reconstruct_highlights

                image, _ = reconstruct_highlights(self.raw_image)
                image = np.ascontiguousarray(image, np.float32)
            f0 = box_factor(self.h, self.w, self.proxy_long_side)
            factors = sorted({f0, *(math.ceil(f0 * (4 / 3) ** i) for i in (1, 2, 3, 4))})
            proxies = [(f, box_reduce(image, f), np.clip(box_reduce(self.disparity, f), 0.0, 1.0)) for f in factors]
            self._variants[reconstructs] = (image, proxies)
        return self._variants[reconstructs]

    @classmethod
    def from_files(cls, image_path: str, *, disparity: str | None = None, depth: str | None = None,
                   depth_model: str | None = None, resize_disparity: bool = False, **kw) -> ViewSession:
        """Read the inputs as ``bokehray render`` does (the same readers, depth conventions, checks and messages;
        ``depth_model`` estimates the map with a local checkpoint, as ``--depth-model`` does)."""
        from ..._memory import small_pages
        from ..render_job import read_map

        small_pages()  # as the command line does before it reads (bokehray._memory.small_pages)
        image = br.read_image(image_path)
        d, norm = read_map(image, disparity=disparity, depth=depth, depth_model=depth_model,
                           resize_disparity=resize_disparity, device=kw.get("device", "cpu"))
        return cls(image, d, image_path=image_path, disparity_path=disparity, depth_path=depth,
                   depth_model_path=depth_model, resize_disparity=resize_disparity, norm=norm, **kw)

    def parse(self, body: object) -> RenderParams:
        """:func:`parse_params` with this session's defaults (those of ``render`` on the same inputs)."""
        p = parse_params(body, self.disparity, subject_d_f=self.subject.d_f,
                         reconstruct_default=self.reconstruct_default, norm=self.norm)
        if p.reconstruct and self.image_path and not self.display_referred:  # `render` never reconstructs a linear file
            p = dataclasses.replace(p, reconstruct=False)
        return p

    # --- what does not change -------------------------------------------------------------------------
    def _cached(self, name: str, make) -> bytes:
        if name not in self._cache:
            self._cache[name] = make()
        return self._cache[name]

    def photo_jpeg(self) -> bytes:
        return self._cached("photo", lambda: encode_jpeg(to_srgb8(box_reduce(self.raw_image, self.display_factor))))

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

    def depth_range_m(self) -> tuple[float, float] | None:
        if self.norm is None:
            return None
        return float(self.norm.depth(self.d_hi)), float(self.norm.depth(self.d_lo))

    def info(self) -> dict:
        from ...photo.subject import AMOUNT_DEFAULT

        names = {"image": Path(self.image_path).name if self.image_path else "(array)",
                 "map": Path(self.depth_model_path or self.depth_path or self.disparity_path or "(array)").name,
                 "map_kind": "depth model" if self.depth_model_path else "depth" if self.depth_path else "disparity"}
        s = self.subject
        metric = None
        if self.norm is not None:
            near, far = self.depth_range_m()
            metric = {"z_near_m": self.norm.z_near_m, "z_far_m": self.norm.z_far_m, "nearest_m": near,
                      "farthest_m": far, "subject_m": float(self.norm.depth(s.d_f))}
            # JSON has no infinity (the answer was a 500 on a map with sky): null, which the page reads as Infinity
            metric = {k: float(v) if math.isfinite(v) else None for k, v in metric.items()}
        return {
            "width": self.w, "height": self.h, "files": names,
            "proxy": {"factor": self.proxy_factor, "width": self.proxy_image.shape[1],
                      "height": self.proxy_image.shape[0], "factors": [f for f, _, _ in self.proxies]},
            "display": {"factor": self.display_factor, "width": -(-self.w // self.display_factor),
                        "height": -(-self.h // self.display_factor)},
            "defaults": {"amount": AMOUNT_DEFAULT, "k_px": self.default_k, "focus": s.d_f,
                         "subject": {"x": s.x, "y": s.y, "why": s.describe(), "words": s.words()},
                         "reconstruct": self.reconstruct_default},
            "display_referred": self.display_referred, "metric": metric,
            "max_blur": float(max(8, round(self.w / 8))),
            "qualities": list(PHOTO_QUALITIES), "export_formats": {k: list(v) for k, v in EXPORT_FORMATS.items()},
            "export_dir": str(self.export_dir), "max_body_bytes": MAX_BODY_BYTES,
        }

    # --- renders --------------------------------------------------------------------------------------
    def render_preview(self, p: RenderParams, check=None) -> tuple[bytes, dict]:
        """The live preview: preview level on a proxy with ``K / f``; ``check()`` may raise to abandon it.

        The proxy is the ladder's choice (:class:`ProxyLadder`); an abandoned render moves the ladder only when
        it had already taken longer than the budget.
        """
        level = min(self.ladder.level, len(self.proxies) - 1)
        f, image, disparity = self._variant(p.reconstructs)[1][level]
        blur = br.BlurParams(p.blur.k_px / f, p.blur.focus_disparity)
        progress = (lambda done, total: check(done, total)) if check is not None else None
        t = time.perf_counter()
        try:
            out, stats = br.render_with_stats(image, disparity, blur, p.lens, quality="preview",
                                              device=self.device, highlight_boost=p.highlight_boost,
                                              progress=progress)
        except BaseException:
            if time.perf_counter() - t > self.ladder.budget_s:
                self.ladder.report(time.perf_counter() - t)
            raise
        seconds = time.perf_counter() - t
        self.ladder.report(seconds)
        if check is not None:
            check()
        return encode_jpeg(to_srgb8(out), 88), {"factor": f, "layers": stats.layers, "level": level,
                                                "render_s": seconds}

    def _screen_arrays(self, f: int, reconstructs: bool) -> tuple[np.ndarray, np.ndarray]:
        """The photo and its map reduced by ``f`` for the screen (cached: the sharp version and the focus crop of
        the same size share them; the photo itself at ``f = 1``)."""
        if f == 1:
            return self._variant(reconstructs)[0], self.disparity
        key = (f, reconstructs)
        if self._screen is None or self._screen[0] != key:
            self._screen = None
            image = self._variant(reconstructs)[0]
            self._screen = (key, box_reduce(image, f), np.clip(box_reduce(self.disparity, f), 0.0, 1.0))
        return self._screen[1], self._screen[2]

    def _screen_window(self, f: int, reconstructs: bool, box: tuple[int, int, int, int]) -> tuple[np.ndarray, np.ndarray]:
        """The window ``box`` (y0, y1, x0, x1, screen pixels) of the photo and its map reduced by ``f``: sliced from
        the screen-size arrays where the sharp version has made them, else the window alone reduced (a first click
        does not wait for the whole frame's reduction: 0.6 s at 12 MP beside two busy processes). Block-aligned, so
        the two agree (``tests/cli_io/test_view_focus.py``)."""
        y0, y1, x0, x1 = box
        if f == 1 or (self._screen is not None and self._screen[0] == (f, reconstructs)):
            screen, screen_d = self._screen_arrays(f, reconstructs)
            return np.ascontiguousarray(screen[y0:y1, x0:x1]), np.ascontiguousarray(screen_d[y0:y1, x0:x1])
        image = self._variant(reconstructs)[0]
        rows, cols = slice(y0 * f, y1 * f), slice(x0 * f, x1 * f)
        return box_reduce(image[rows, cols], f), np.clip(box_reduce(self.disparity[rows, cols], f), 0.0, 1.0)

    def focus_point(self, p: RenderParams) -> tuple[int, int]:
        """Where the focus is, in photo pixels: the clicked point, the default focus's point (the eyes, the subject),
        or for a focus set by disparity (the slider, a focus distance) the in-focus pixel nearest the frame's
        centre on the coarsest proxy."""
        if p.focus_at:
            return int(p.focus_at[0]), int(p.focus_at[1])
        if p.focus_default:
            return self.subject.x, self.subject.y
        f, _, d = self.proxies[-1]
        off = np.abs(d - np.float32(p.blur.focus_disparity))
        yy, xx = np.mgrid[: d.shape[0], : d.shape[1]]
        score = off * 1e3 + np.hypot(yy - d.shape[0] / 2, xx - d.shape[1] / 2) / max(d.shape)
        iy, ix = np.unravel_index(int(np.argmin(score)), d.shape)
        return min(self.w - 1, int(ix) * f + f // 2), min(self.h - 1, int(iy) * f + f // 2)

    def focus_crop(self, p: RenderParams, check=None, long_side: int | None = None,
                   half: int = FOCUS_CROP_HALF) -> tuple[bytes, dict]:
        """The focused region at the size the screen shows (the sharp version's reduction), rendered before the
        rest so that the focus can be judged while the whole frame sharpens: a crop of ``2 half`` screen pixels
        around :meth:`focus_point`, rendered on a window reaching the largest CoC beyond it (the light that
        spreads into the crop), on the sharp version's pixel grid. Its ``crop`` (x0, y0, x1, y1, photo pixels)
        says where it goes."""
        p = dataclasses.replace(p, quality="preview")
        f = self.screen_factor(long_side)
        t = time.perf_counter()
        x, y = self.focus_point(p)
        w, h = -(-self.w // f), -(-self.h // f)
        x0 = min(max(0, x // f - half), max(0, w - 2 * half))
        y0 = min(max(0, y // f - half), max(0, h - 2 * half))
        x1, y1 = min(w, x0 + 2 * half), min(h, y0 + 2 * half)
        blur = br.BlurParams(p.blur.k_px / f, p.blur.focus_disparity)
        reach = math.ceil(float(blur.coc_radius(np.array([self.d_lo, self.d_hi])).max())) + 2
        tile = 16  # the window starts on the sharp version's tile grid (LayerOptions.tile_px): the same tiles copied
        wx0, wy0 = max(0, x0 - reach) // tile * tile, max(0, y0 - reach) // tile * tile
        wx1, wy1 = min(w, x1 + reach), min(h, y1 + reach)
        image, disparity = self._screen_window(f, p.reconstructs, (wy0, wy1, wx0, wx1))
        progress = (lambda done, total: check(done, total)) if check is not None else None
        out, _ = br.render_with_stats(image, disparity, blur, p.lens, quality="preview",
                                      device=self.device, highlight_boost=p.highlight_boost, progress=progress)
        if check is not None:
            check()
        crop = out[y0 - wy0 : y1 - wy0, x0 - wx0 : x1 - wx0]
        box = [x0 * f, y0 * f, min(self.w, x1 * f), min(self.h, y1 * f)]
        return encode_jpeg(to_srgb8(crop), 90), {"factor": f, "crop": box, "render_s": time.perf_counter() - t}

    def focus_words(self, p: RenderParams) -> str:
        """The focus said as a photographer would: what it is on (the eyes of the nearest face, the subject, the
        clicked point), how near it lies in the scene (near / middle / far in the map's range), and metres for a
        metric map."""
        if p.focus_at:
            what = "the point you clicked"
        elif p.focus_default:
            what = self.subject.words()
        elif p.thin_lens is not None:
            what = "the focus distance"
        else:
            what = "the focus slider's depth"
        lo, hi = self.d_lo, self.d_hi
        d = p.blur.focus_disparity
        t = (d - lo) / (hi - lo) if hi - lo > 1e-6 else 1.0
        where = "near" if t >= 2 / 3 else "in the middle distance" if t >= 1 / 3 else "far"
        if self.norm is not None:
            z = float(self.norm.depth(d))
            where += f", {z:.3g} m away" if math.isfinite(z) else ", at infinity"
        return f"{what} ({where})"

    def shown_command(self, p: RenderParams, body: dict) -> str:
        """The command shown before any export: :meth:`command` with ``-o OUTPUT.<format>`` and the bit depth
        the page's export choice holds (``format``, ``bit_depth`` in ``body``; PNG by default)."""
        fmt, bits = export_choice(body)
        return self.command(p, f"OUTPUT.{fmt}", bit_depth=bits)

    def warm_up(self) -> float:
        """One preview of the coarsest proxy, thrown away: Warp loads its kernel modules now, not when the page asks
        for its first picture. Returns the seconds it took; the ladder is left alone."""
        t = time.perf_counter()
        p = self.parse({})
        f, image, disparity = self.proxies[-1]
        br.render_with_stats(image, disparity, br.BlurParams(p.blur.k_px / f, p.blur.focus_disparity), p.lens,
                             quality="preview", device=self.device)
        return time.perf_counter() - t

    def screen_factor(self, long_side: int | None) -> int:
        """The reduction of the sharp version for a screen showing ``long_side`` pixels on the photo's long side
        (None: ``--display-size``; at least the photo's size: 1, every pixel)."""
        if long_side is None:
            return self.display_factor
        return max(1, min(box_factor(self.h, self.w, long_side), max(self.h, self.w)))

    def render_full(self, p: RenderParams, check=None) -> np.ndarray:
        """Every pixel at the chosen quality (cached for the export of the same parameters)."""
        key = p.key()
        if self._full is not None and self._full[0] == key:
            return self._full[1]
        progress = (lambda done, total: check(done, total)) if check is not None else None
        if check is not None:
            check()
        image = self._variant(p.reconstructs)[0]
        out, _ = br.render_with_stats(image, self.disparity, p.blur, p.lens, quality=p.quality,
                                      device=self.device, highlight_boost=p.highlight_boost, progress=progress)
        self._full = None  # drop the old one before keeping the new one: one full-size image at a time
        self._full = (key, out)
        return out

    def full_display(self, p: RenderParams, check=None, long_side: int | None = None) -> tuple[bytes, dict]:
        """The sharp version the page shows once the preview of the same state is on screen: every pixel the
        screen shows, at the preview level, rendered at that size (``K / f``: the CoC scaled with it).

        ``long_side`` is what the page's canvas shows (device pixels); at the photo's size or more (100 % zoom)
        this is the full-resolution render, which an export of the same parameters reuses. Always the preview
        level, whatever ``p.quality``: the chosen level is what the export renders.
        """
        p = dataclasses.replace(p, quality="preview")
        f = self.screen_factor(long_side)
        t = time.perf_counter()
        if f == 1:
            out = self.render_full(p, check)
        else:
            image, disparity = self._screen_arrays(f, p.reconstructs)
            progress = (lambda done, total: check(done, total)) if check is not None else None
            out, _ = br.render_with_stats(image, disparity, br.BlurParams(p.blur.k_px / f, p.blur.focus_disparity),
                                          p.lens, quality="preview", device=self.device,
                                          highlight_boost=p.highlight_boost, progress=progress)
        if check is not None:
            check()
        return encode_jpeg(to_srgb8(out), 90), {"factor": f, "render_s": time.perf_counter() - t}

    # --- export ---------------------------------------------------------------------------------------
    def export_path(self, fmt: str) -> Path:
        stem = Path(self.image_path).stem if self.image_path else "render"
        for n in range(1, 100000):
            p = self.export_dir / f"{stem}-bokeh-{n:03d}.{fmt}"
            if not os.path.lexists(p):  # a dangling link takes its name too
                return p
        raise InputError(f"{self.export_dir}: no free export name left")

    def _exif(self) -> bytes | None:
        """The photo's EXIF for a JPEG export, exactly as ``render`` keeps it (orientation reset)."""
        if not self.image_path:
            return None
        from ...formats import FORMATS
        from ...photo.embedded import embedded, exif_for_output

        return exif_for_output(embedded(Path(self.image_path), FORMATS.get(Path(self.image_path).suffix.lower(), "")))

    def _with_grain(self, out: np.ndarray, p: RenderParams, path: Path, bits: int | None) -> np.ndarray:
        """The export's finishing step, as ``render`` does it for a display-referred photo: the photo's grain
        restored where the blur removed it (on a copy: the full render stays cached as rendered)."""
        if not self.display_referred or not p.grain:
            return out
        from ...photo.grain import keep_grain, output_bits

        return keep_grain(out.copy(), self._variant(p.reconstructs)[0], self.disparity, p.blur,
                          dither_bits=output_bits(str(path), bits))

    def export(self, p: RenderParams, fmt: str, bit_depth: int | None, check=None) -> tuple[Path, str]:
        fmt, _ = export_choice({"format": fmt})
        if bit_depth is not None and (isinstance(bit_depth, bool) or not isinstance(bit_depth, int)):
            raise InputError(f"argument --bit-depth: invalid int value: {bit_depth!r}"[:200])
        bits, half = bit_depth, False  # EXR at 16 bits is half float, as `--bit-depth 16` gives
        path = self.export_path(fmt)
        from ...output.write import check_output_path  # the same check as `bokehray render -o`, before rendering
        from ..render_job import JPEG_QUALITY  # render's default: the export is the file the shown command writes

        check_output_path(path, bit_depth=bits, half=half)
        out = self._with_grain(self.render_full(p, check), p, path, bits)
        exif = self._exif()
        tries = iter(range(EXPORT_NAME_TRIES - 1))

        def next_name(_taken: Path) -> Path | None:  # another export (this view's or another process's) took it
            return None if next(tries, None) is None else self.export_path(fmt)

        try:  # encoded once, published under the first name still free
            written = br.write_image(path, out, bit_depth=bits, half=half, quality=JPEG_QUALITY, exif=exif,
                                     exclusive=True, next_name=next_name)
        except OutputExistsError:
            raise OutputError(f"{self.export_dir}: every free export name was taken while writing") from None
        return written, self.command(p, written, bit_depth=bits, half=half)

    def command(self, p: RenderParams, output: str | Path, *, bit_depth: int | None = None,  # noqa: C901
                half: bool = False) -> str:
        """The ``bokehray render`` command line that writes the same image (what is at ``render``'s default is
        left out: the amount 50, the subject focus, highlight reconstruction)."""
        from ...photo.subject import AMOUNT_DEFAULT

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
        args += ["-o", q(str(output))]
        if p.thin_lens is not None:
            lens = p.thin_lens
            args += ["--focal-length", _fmt(lens.focal_length_mm), "--f-number", _fmt(lens.f_number)]
            if p.focus_at is None:
                args += ["--focus-distance", _fmt(lens.focus_distance_m)]
            if lens.sensor_width_mm != 36.0:
                args += ["--sensor-width", _fmt(lens.sensor_width_mm)]
        elif p.amount is None:
            args += ["--blur", _fmt(p.k_px)]
        elif p.amount != AMOUNT_DEFAULT:
            args += ["--amount", _fmt(p.amount)]
        if p.focus_at:
            args += ["--focus-at", f"{p.focus_at[0]},{p.focus_at[1]}"]
        elif p.focus is not None:
            args += ["--focus", _fmt(p.focus)]
        if p.aperture == "polygon":
            args += ["--aperture", "polygon", "--blades", str(p.blades), *_signed_option("--rotation", p.rotation),
                     "--curvature", _fmt(p.curvature)]
        if p.highlight_boost:
            args += ["--highlight-boost", _fmt(p.highlight_boost)]
        elif self.display_referred and not p.reconstruct:
            args.append("--no-highlight-reconstruction")
        if self.display_referred and not p.grain:
            args.append("--no-grain")
        if bit_depth is not None:
            args += ["--bit-depth", str(bit_depth)]
        if half:
            args.append("--half")
        if self.device != "cpu":
            args += ["--device", self.device]
        return " ".join(args)
