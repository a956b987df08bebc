"""One photo rendered as ``bokehray render IMAGE ... -o OUTPUT`` does it: check the flags, read the photo and its map
(orientation, colour profile, depth conventions, a local depth model), choose the blur and focus when not given,
reconstruct clipped highlights, render, write. The CLI's single-file path and every batch task
(``bokehray.app.batch``) run :func:`render_one`, so a batch output is the single-file output.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import threading
import time
from pathlib import Path

import numpy as np

from .._memory import small_pages
from .._quiet import init_warp_quietly
from ..errors import InputError
from ..photo.subject import AMOUNT_DEFAULT, AMOUNT_K_FRACTION
from ..stats import Clock
from ..validate import number_text

__all__ = ["aperture_of", "check_render_flags", "layer_options_of", "read_map", "render_one", "start_warp"]


JPEG_QUALITY = 95
"""The quality of a JPEG output without ``--jpeg-quality``."""


RENDER_MODULES = ("warp", "bokehray.pipeline", "bokehray.ramps", "bokehray.strands", "bokehray.matting",
                  "bokehray.levels.preview")
"""What a preview render imports on its way (Warp, about 0.4 s of Python; the kernels' modules, whose kernels are
parsed as they load): :func:`prefetch_imports` loads them while the photo is read."""


def prefetch_imports(modules: tuple[str, ...] = RENDER_MODULES) -> threading.Thread:
    """Import ``modules`` on a daemon thread, started now; join it before the first of them is needed. The photo's
    reading, its map's and the colour conversion run in C with the GIL released (Pillow's decoders and littleCMS,
    NumPy's loops), so the imports' Python runs beside them on the other core instead of after them. Importing is
    all it does (``wp.init`` stays with :func:`start_warp`, which may silence the native stderr); a module that
    fails to import here is left to the import that needs it, which raises as before."""
    import importlib

    def run() -> None:
        for name in modules:
            try:
                importlib.import_module(name)
            except Exception:  # noqa: BLE001 - the import that needs it raises it, with its own context
                return

    thread = threading.Thread(target=run, name="bokehray-imports", daemon=True)
    thread.start()
    return thread


def start_warp(args: argparse.Namespace) -> None:
    """Initialise Warp (a slow import, then its module cache) only once a command is about to compute, so that
    ``--help`` and argument errors return at once."""
    init_warp_quietly(getattr(args, "debug", False))


def aperture_of(args: argparse.Namespace):
    from ..lens import Aperture

    shape = {"--blades": args.blades, "--rotation": args.rotation, "--curvature": args.curvature}
    if args.aperture == "disc":
        given = [flag for flag, value in shape.items() if value is not None]
        if given:
            raise InputError(f"{'/'.join(given)} shape{'s' if len(given) == 1 else ''} a polygonal aperture; "
                             "add --aperture polygon (the default aperture is a disc)")
        return Aperture()
    return Aperture(blades=6 if args.blades is None else args.blades,
                    rotation_deg=0.0 if args.rotation is None else args.rotation,
                    curvature=0.0 if args.curvature is None else args.curvature)


def layer_options_of(args: argparse.Namespace):
    from ..options import LayerOptions

    kw = {}
    if args.max_layers is not None:
        if args.max_layers < 1:
            raise InputError(f"--max-layers: expected >= 1, got {args.max_layers}")
        kw["max_layers"] = args.max_layers
    if args.no_fill:
        kw["fill"] = False
    if args.thin_depth:
        kw["thin_depth"] = True
    return LayerOptions(**kw)


def _check_refiner_model(args: argparse.Namespace) -> None:
    """``--refiner-model DIR`` implies ``--refine``; it replaces the shipped networks, so it takes no --refine
    WEIGHTS and no --refine-everywhere; DIR must be a folder."""
    model = getattr(args, "refiner_model", None)
    if model is None:
        return
    if args.refine not in (False, True):
        raise InputError(f"--refiner-model {model} replaces the shipped networks; it takes no --refine WEIGHTS "
                         f"({args.refine})")
    if getattr(args, "refine_everywhere", False):
        raise InputError("--refine-everywhere tunes the shipped networks; --refiner-model replaces them")
    if not Path(model).is_dir():
        raise InputError(f"--refiner-model {model}: not a folder (a one-step model is a diffusers-layout folder)")
    args.refine = True


def refine_options_of(args: argparse.Namespace):
    """``--refine-everywhere``: refine also a map the depth fix finds right, and run the edge network wherever it is
    found wrong (``RefineOptions(min_fixed_share=0, edge_min_disagreement=0)``); ``--refiner-model DIR``: the
    one-step model in DIR instead (``RefineOptions(model=DIR)``); None: the refiner's defaults."""
    kw = {}
    if getattr(args, "refine_everywhere", False):
        kw |= {"min_fixed_share": 0.0, "edge_min_disagreement": 0.0}
    if getattr(args, "refiner_model", None) is not None:
        kw["model"] = args.refiner_model
    if not kw:
        return None
    from ..levels.refine import refine_options

    return refine_options(**kw)


class _Progress:
    """One bar over the stages of a render (read, depth estimation, render with its layers, write), on a
    terminal only; each stage owns a share of the bar in proportion to its usual cost."""

    def __init__(self, args: argparse.Namespace, stages: dict[str, float]) -> None:
        self.bar = None
        total = sum(stages.values())
        self.start, at = {}, 0.0
        for name, weight in stages.items():
            self.start[name] = (100.0 * at / total, 100.0 * weight / total)
            at += weight
        if args.quiet or not sys.stderr.isatty():
            return
        from tqdm import tqdm

        self.bar = tqdm(total=100, desc="read", leave=False, file=sys.stderr,
                        bar_format="{desc:<7} {percentage:3.0f}%|{bar}| {elapsed}")

    def stage(self, name: str):
        """Enter stage ``name``; returns ``update(fraction)`` for progress within it."""
        base, share = self.start[name]

        def update(fraction: float) -> None:
            if self.bar is not None:
                self.bar.n = min(100.0, base + share * max(0.0, min(1.0, fraction)))
                self.bar.refresh()

        if self.bar is not None:
            self.bar.set_description_str(name)
        update(0.0)
        return update

    def layers(self):
        """The render stage's ``progress(done, total)`` callback (layers of either level)."""
        update = self.stage("render")
        return lambda done, total: update(done / total if total else 1.0)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def _resize(a: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    from skimage.transform import resize

    return resize(a, shape, order=1, mode="edge", anti_aliasing=False, preserve_range=True).astype(np.float32)


def _check_output(path: str, args: argparse.Namespace) -> None:
    from ..output.write import CLI_NAMES, check_output_path

    check_output_path(path, bit_depth=getattr(args, "bit_depth", None), half=getattr(args, "half", False),
                      names=CLI_NAMES)
    out = Path(path)
    for what, source in (("photo", args.image), ("map", getattr(args, "disparity", None) or
                                                  getattr(args, "depth", None))):
        # the render would replace the very file it reads (a batch with -o its own folder and --overwrite, too)
        if source is not None and out.is_file() and Path(source).is_file() and out.samefile(source):
            raise InputError(f"{path}: is the {what} being rendered ({source}), and writing the render there would "
                             "replace it; choose another output name (or folder)")


def _say(args: argparse.Namespace, text: str) -> None:
    if not args.quiet:
        print(text)


def _metres(norm, d_f: float) -> str:
    """`` (2.35 m away)`` for metric depth, else nothing."""
    if norm is None:
        return ""
    z = float(norm.depth(d_f))
    return f" ({z:.3g} m away)" if math.isfinite(z) else " (at infinity)"


def _warn(args: argparse.Namespace, text: str) -> None:
    if not args.quiet:
        print(f"bokehray: warning: {text}", file=sys.stderr)


def check_render_flags(args: argparse.Namespace) -> bool:  # noqa: C901
    """Contradictions between flags, found before any file is read (and before Warp starts). Returns whether
    the blur is a physical lens."""
    from ..levels import check_photo_quality

    check_photo_quality(args.quality)
    physical = any(v is not None for v in (args.focal_length, args.f_number, args.focus_distance))
    given_focus = [name for name, v in (("--focus", args.focus), ("--focus-at", args.focus_at),
                                        ("--focus-distance", args.focus_distance)) if v is not None]
    if len(given_focus) > 1:
        raise InputError(f"{' and '.join(given_focus)} contradict each other: give the focus one way")
    if physical and args.depth is None:
        how = " (--normalize/--invert describe a relative map)" if args.normalize or args.invert else ""
        raise InputError("a physical lens (--focal-length/--f-number/--focus-distance) needs metric depth, and "
                         f"a --disparity map{how} has no scale: give a depth map in metres with --depth (an integer "
                         "map with --depth-scale, e.g. 0.001 for millimetres), or set the blur with --amount/--blur "
                         "and the focus with --focus/--focus-at")
    if physical and (args.blur is not None or args.amount is not None or args.focus is not None):
        raise InputError("give the blur either as --amount/--blur with --focus, or as a physical lens, not both")
    if physical and (args.focal_length is None or args.f_number is None):
        raise InputError("a physical lens needs both --focal-length and --f-number")
    if args.depth_model is not None and (args.normalize or args.invert):
        raise InputError("--normalize and --invert describe a --disparity map; a --depth-model's output is "
                         "normalised with its known polarity")
    if args.save_depth and args.depth_model is None:
        raise InputError("--save-depth writes the map a --depth-model estimated; it needs --depth-model")
    if args.depth is not None and (args.normalize or args.invert):
        raise InputError("--normalize and --invert describe a relative --disparity map; a --depth map is metric "
                         "(near = small), and is converted to disparity with the thin-lens normalisation")
    if args.sensor_width is not None and not physical:
        raise InputError("--sensor-width sizes the sensor of a physical lens; it needs --focal-length and --f-number "
                         "(with --depth)")
    if args.depth_scale is not None and args.depth is None:
        raise InputError("--depth-scale converts the codes of an integer --depth map to metres; it needs --depth")
    _check_refiner_model(args)
    if getattr(args, "refine_everywhere", False) and not args.refine:
        raise InputError("--refine-everywhere changes what --refine does; it needs --refine")
    if args.blur is not None and args.blur < 0:
        raise InputError(f"--blur: expected K >= 0, got {number_text(args.blur)}")
    if args.z_near is not None or args.z_far is not None:
        if args.depth is None:
            raise InputError("--z-near/--z-far normalise a metric --depth map; they need --depth")
    if args.jpeg_quality is not None and not 1 <= args.jpeg_quality <= 100:
        raise InputError(f"--jpeg-quality: expected 1..100, got {args.jpeg_quality}")
    if args.amount is not None:
        from ..photo.subject import k_from_amount

        k_from_amount(args.amount, 1, 1)  # the range check
    aperture_of(args)  # polygon flags without --aperture polygon, refused before any work
    return physical


def _disparity_path(output: str) -> Path:
    out = Path(output)
    return out.with_name(f"{out.stem}-disparity.png")


def _read_map(args: argparse.Namespace, h: int, w: int, image: np.ndarray | None = None, stage=None):  # noqa: C901
    """The disparity map by the conventions the flags state; ``(d, DepthNormalization or None)``."""
    from ..lens import DepthNormalization, check_focus_in_range, disparity_from_depth
    from ..output.write import write_disparity
    from ..photo.depth import looks_reversed, missing_depth_share, normalize_relative, read_depth
    from ..photo.read import read_disparity

    norm = None
    if args.depth_model is not None:
        from ..photo.depth_model import estimate_disparity

        t = time.perf_counter()
        disparity, info = estimate_disparity(image, args.depth_model, device=args.device,
                                             progress=stage)
        _say(args, f"depth: estimated by the {info['model']} model in {args.depth_model} at "
             f"{info['input_size'][1]}x{info['input_size'][0]} ({info['what']}) in {time.perf_counter() - t:.1f} s")
        if args.save_depth:
            saved = write_disparity(_disparity_path(args.output), disparity)
            _say(args, f"depth: saved to {saved} (reuse it with --disparity {saved})")
        return np.ascontiguousarray(disparity, np.float32), None
    if args.depth is not None:
        depth = read_depth(args.depth, scale=args.depth_scale)
        if args.z_near is not None or args.z_far is not None:
            finite = depth[np.isfinite(depth) & (depth > 0)]
            zn = args.z_near if args.z_near is not None else float(finite.min()) if finite.size else 1.0
            zf = args.z_far if args.z_far is not None else float(finite.max()) if finite.size else np.inf
            norm = DepthNormalization(zn, zf)
        # resize after the conversion: disparity interpolates where depth cannot (inf for sky)
        disparity, norm = disparity_from_depth(depth, norm, source=args.depth, names=("--z-near", "--z-far"))
        if getattr(args, "focus_distance", None) is not None:  # refused before any line is printed
            check_focus_in_range(args.focus_distance, norm, "--focus-distance", ("--z-near", "--z-far"))
        finite = depth[np.isfinite(depth) & (depth > 0)]
        if finite.size:
            _say(args, f"depth: read {args.depth}: {float(finite.min()):.3g} .. {float(finite.max()):.3g} m (nearest .. "
                 f"farthest; disparity 1 at {norm.z_near_m:.3g} m, 0 at {norm.z_far_m:.3g} m)")
        missing = missing_depth_share(depth)
        if missing > 0:
            _say(args, f"depth: {missing:.1%} of {args.depth} is 0, negative or infinite (no depth): taken as "
                 "infinitely far (sky)")
        source = args.depth
    else:
        source = args.disparity
        raw = read_disparity(source)
        if args.normalize:
            disparity, (lo, hi, how) = normalize_relative(raw, invert=args.invert, source=source, with_bounds=True)
            _say(args, f"disparity: {source} normalised from [{lo:.4g}, {hi:.4g}] ({how}) "
                 f"to [0, 1]{', inverted' if args.invert else ''}")
        else:
            if raw.size and (raw.min() < 0.0 or raw.max() > 1.0):
                raise InputError(f"{source}: expected disparity in [0, 1] (1 = nearest), got values in "
                                 f"[{float(raw.min()):.4g}, {float(raw.max()):.4g}]: pass --normalize for a relative "
                                 "map of any range (add --invert if near is dark), or give metric depth with --depth")
            disparity = 1.0 - raw if args.invert else raw
        # said beside the choices it explains (the blur from an amount, the subject); a render with --blur and
        # --focus prints nothing before its output, as before
        chooses = getattr(args, "blur", None) is None or (getattr(args, "focus", None) is None
                                                          and getattr(args, "focus_at", None) is None)
        if disparity.size and chooses:
            _say(args, f"depth: read disparity {source}: {float(disparity.min()):.3f} .. {float(disparity.max()):.3f} "
                 "(0 = far, 1 = near; relative, no metres)")
        reverse, why = looks_reversed(disparity)
        if reverse:
            fix = "drop --invert" if args.invert else "pass --invert"
            _warn(args, f"{source}: the map looks reversed ({why}); if near is dark in it, {fix}")
    _say_embedded(args, source)
    if disparity.shape != (h, w):
        mh, mw = disparity.shape
        _check_map_size(args, source, (mh, mw), (h, w))
        disparity = _resize(disparity, (h, w))
    return np.ascontiguousarray(disparity, np.float32), norm


def read_map(image: np.ndarray, *, disparity: str | None = None, depth: str | None = None,
             depth_model: str | None = None, resize_disparity: bool = False, device: str = "cpu"):
    """The disparity map of ``image`` exactly as ``bokehray render`` reads it with these flags (and the defaults of
    the others): ``(d, DepthNormalization or None)``. Used by ``bokehray view``."""
    if sum(v is not None for v in (disparity, depth, depth_model)) != 1:
        raise InputError("give exactly one of --disparity D, --depth D or --depth-model DIR")
    args = argparse.Namespace(image=None, disparity=disparity, depth=depth, depth_model=depth_model, depth_scale=None,
                              normalize=False, invert=False, z_near=None, z_far=None, resize_disparity=resize_disparity,
                              save_depth=False, output="", device=device, quiet=True)
    return _read_map(args, image.shape[0], image.shape[1], image)


def _say_embedded(args: argparse.Namespace, path: str):
    """What the reader did with the file's orientation and colour profile, said in one line."""
    from ..formats import FORMATS
    from ..photo.embedded import embedded, orientation_words

    meta = embedded(Path(path), FORMATS.get(Path(path).suffix.lower(), ""))
    done = []
    if meta.orientation != 1:
        done.append(f"EXIF orientation {meta.orientation} applied ({orientation_words(meta.orientation)})")
    if not meta.is_srgb:
        done.append(f"colour profile '{meta.icc_name}' converted to sRGB")
    if done:
        _say(args, f"{'image' if path == args.image else 'map'}: {'; '.join(done)}")
    return meta


def _turned_by_exif(path: str) -> int | None:
    """The EXIF orientation (5 to 8) that turns the photo a quarter as it is read, else None."""
    from ..formats import FORMATS
    from ..photo.embedded import embedded

    orientation = embedded(Path(path), FORMATS.get(Path(path).suffix.lower(), "")).orientation
    return orientation if orientation in (5, 6, 7, 8) else None


def _check_map_size(args: argparse.Namespace, source: str, map_hw: tuple[int, int], hw: tuple[int, int]) -> None:
    """A map of another size than the photo (as read: EXIF orientation applied) is resized only when asked, and
    only at the same aspect ratio; a map in the stored orientation of a photo its EXIF turns a quarter is named as
    that, since resizing cannot fix it."""
    from ..photo.embedded import orientation_words

    (mh, mw), (h, w) = map_hw, hw
    sizes = f"{source}: map is {mw}x{mh}, image is {w}x{h}"
    image = getattr(args, "image", None)  # bokehray view reads a map without the photo's path
    turned = _turned_by_exif(image) if image is not None and (mh, mw) != (h, w) else None
    if turned is not None and abs(math.log((mw / mh) / (h / w))) <= 0.02:
        raise InputError(f"{sizes} as displayed: the image's EXIF orientation {turned} "
                         f"({orientation_words(turned)}) is applied when it is read, and the map matches the image "
                         "as stored, unturned; turn the map the same way (or save the photo without its EXIF "
                         "orientation)")
    if not args.resize_disparity:
        raise InputError(f"{sizes}; pass --resize-disparity to resize it")
    if abs(math.log((mw / mh) / (w / h))) > 0.02:
        raise InputError(f"{sizes}: a different aspect ratio, so resizing would stretch it")


def _check_sizes_from_headers(args: argparse.Namespace) -> None:
    """Refuse an image and map of different sizes from their headers, before decoding either (a 64 MP PNG takes
    seconds to decode); the readers still check each file in full afterwards."""
    from ..photo.read import read_size

    source = args.depth or args.disparity
    if args.resize_disparity or source is None:
        return
    (h, w), (mh, mw) = read_size(args.image), read_size(source)
    if (mh, mw) != (h, w):
        _check_map_size(args, source, (mh, mw), (h, w))


def render_one(args: argparse.Namespace) -> dict:
    """One photo, as ``bokehray render IMAGE ... -o OUTPUT`` does it; every batch task runs this too (with
    ``quiet``), so a batch output is the single-file output. Returns what was done (output, pixels, K, d_f, how
    the focus was chosen, the amount when the blur came from one, the focus distance in metres for metric depth)."""
    physical = check_render_flags(args)  # before any import that takes time
    _check_output(args.output, args)
    _check_sizes_from_headers(args)
    bar = _Progress(args, {"read": 5, **({"depth": 30} if args.depth_model else {}), "render": 60, "write": 5})
    try:
        return _render(args, physical, bar)
    finally:
        bar.close()


def focus_words(focus) -> str:
    """How a default focus was chosen, as a batch line and ``render_one``'s result say it."""
    from ..photo.faces import EyesFocus

    if isinstance(focus, EyesFocus):
        return f"{focus.words()} at ({focus.x}, {focus.y})"
    return f"the subject around pixel ({focus.x}, {focus.y})"


def _plan_grain(args: argparse.Namespace, image: np.ndarray, disparity: np.ndarray, blur):
    """The grain to restore after the render (a display-referred photo without ``--no-grain``), else None."""
    from ..photo.highlights import is_display_referred

    if getattr(args, "no_grain", False) or not is_display_referred(args.image):
        return None
    from ..photo.grain import plan_grain

    return plan_grain(image, blur.coc_radius(disparity))


def max_coc_px(blur, disparity: np.ndarray) -> float:
    """``blur.coc_radius(disparity).max()`` from the map's nearest and farthest values alone: the float32
    ``K (d - d_f)`` is monotonic in ``d`` (each rounding is), so its magnitude peaks at an end of the range (no
    frame-sized CoC, 48 MB at 12 MP, twice over). 0 for an empty map."""
    if not disparity.size:
        return 0.0
    return float(blur.coc_radius(np.array([disparity.min(), disparity.max()])).max())


def _alpha_for_output(args: argparse.Namespace, image: np.ndarray) -> np.ndarray:
    """A photo with alpha rendered into a JPEG, which stores none: an alpha of 1 everywhere (an RGBA PNG saved
    opaque) says nothing, so it is dropped; real transparency is refused now, not after the render."""
    from ..formats import FORMATS

    if image.shape[2] != 4 or FORMATS.get(Path(args.output).suffix.lower()) != "JPEG":
        return image
    if (image[..., 3] == 1.0).all():
        return np.ascontiguousarray(image[..., :3])
    raise InputError(f"{args.image}: has transparent pixels (alpha below 1), which a JPEG output ({args.output}) "
                     "cannot store; write .png, .tif or .exr, or flatten the photo first")


_STARTED = {"counted": False}


def _process_age() -> float:
    """Seconds since this process started, from the kernel's clock ticks since boot (``/proc``: 10 ms steps; a
    process's creation time in epoch seconds is off by up to the boot time's whole second); 0 where ``/proc`` is
    not there."""
    try:
        with open("/proc/self/stat") as f:
            start_ticks = int(f.read().rsplit(")", 1)[1].split()[19])  # field 22, after the command's name
        with open("/proc/uptime") as f:
            uptime = float(f.read().split()[0])
        return max(0.0, uptime - start_ticks / os.sysconf("SC_CLK_TCK"))
    except (OSError, ValueError, IndexError):
        return 0.0


def command_clock() -> Clock:
    """The clock of one render command. The first render of a process starts it at the process's start, so the
    interpreter's start-up and the imports are its "start" stage; a batch worker's later renders start it now."""
    now = time.perf_counter()
    if _STARTED["counted"]:
        return Clock(now)
    _STARTED["counted"] = True
    clock = Clock(now - _process_age())
    clock.lap("start")
    return clock


def _render(args: argparse.Namespace, physical: bool, bar: _Progress) -> dict:  # noqa: C901
    from ..lens import BlurParams, ThinLens
    from ..output.write import write_image
    from ..photo.embedded import exif_for_output
    from ..photo.highlights import is_display_referred, reconstruct_highlights
    from ..photo.read import read_image
    from ..photo.subject import default_focus, k_from_amount
    from ..validate import check_radiance

    clock = command_clock()
    small_pages()  # NumPy's large arrays on 4 KB pages from the reading on (_memory.small_pages: less CPU here)
    imports = prefetch_imports()
    bar.stage("read")
    image = _alpha_for_output(args, read_image(args.image))
    check_radiance(image, str(args.image))  # the limit every level has, with the file named
    h, w = image.shape[:2]
    meta = _say_embedded(args, args.image)
    clock.lap("read")
    disparity, norm = _read_map(args, h, w, image, bar.stage("depth") if args.depth_model else None)
    clock.lap("depth")

    amount = None
    if physical:
        focus_how = "--focus-at" if args.focus_at is not None else "--focus-distance"
        focus_m = args.focus_distance
        if args.focus_at is not None:
            from ..pipeline import focus_at

            x, y = args.focus_at
            focus_m = float(norm.depth(focus_at(disparity, x, y)))
            if not np.isfinite(focus_m):
                raise InputError(f"--focus-at {x},{y}: that point is at infinity (sky); a thin lens focused there "
                                 "needs --focus-distance, or click on a surface")
        if focus_m is None:
            raise InputError("a physical lens needs --focus-distance or --focus-at X,Y")
        sensor = {} if args.sensor_width is None else {"sensor_width_mm": args.sensor_width}  # else ThinLens's
        lens = ThinLens(args.focal_length, args.f_number, focus_m, **sensor)
        blur = lens.blur_params(norm, w)
        _say(args, f"focus: at {focus_m:.3g} m ({'--focus-at' if args.focus_at is not None else '--focus-distance'}); "
             f"{args.focal_length:g} mm f/{args.f_number:g}")
    else:
        if args.blur is not None:
            k = args.blur
        else:  # the amount
            amount = AMOUNT_DEFAULT if args.amount is None else args.amount + 0.0  # -0 said as 0
            k = k_from_amount(amount, h, w)
            _say(args, f"blur: --amount {amount:g} -> K = {k:.1f} px ({amount / 100 * AMOUNT_K_FRACTION:.1%} of the "
                 f"{math.hypot(h, w):.0f}-px diagonal){'' if args.amount is not None else ' (the default)'}")
        if args.focus is not None:
            d_f, focus_how = args.focus, "--focus"
            if norm is not None:  # where that is, in metres
                _say(args, f"focus: d_f = {d_f:.4g} (--focus){_metres(norm, d_f)}")
        elif args.focus_at is not None:
            from ..pipeline import focus_at

            d_f, focus_how = focus_at(disparity, *args.focus_at), "--focus-at"
            if norm is not None:
                _say(args, f"focus: d_f = {d_f:.4g} at pixel ({args.focus_at[0]}, {args.focus_at[1]}) "
                     f"(--focus-at){_metres(norm, d_f)}")
        else:
            subject = default_focus(image, disparity)  # the eyes of the nearest face, else the subject
            d_f, focus_how = subject.d_f, focus_words(subject)
            _say(args, f"focus: {subject.describe()}{_metres(norm, d_f)}; --focus-at X,Y to choose")
        blur = BlurParams(k, d_f)
    clock.lap("focus")
    if is_display_referred(args.image) and not args.no_highlight_reconstruction and args.highlight_boost == 0:
        image, found = reconstruct_highlights(image, overwrite=True)  # the photo as read is ours: no copy
        if found:
            _say(args, f"highlights: {found} clipped highlight{'s' * (found > 1)} reconstructed (display-referred "
                 "input; --no-highlight-reconstruction keeps them clipped)")
        clock.lap("highlights")
    grain = _plan_grain(args, image, disparity, blur)
    if grain is not None:
        clock.lap("grain")

    imports.join()
    start_warp(args)
    from ..options import PreviewOptions
    from ..pipeline import Handover, render_handed_over

    clock.lap("warp start")
    max_coc = max_coc_px(blur, disparity)  # said after the render
    # a batch's worker processes share the machine's cores (``threads``; the output does not depend on it)
    level_options = PreviewOptions(threads=getattr(args, "threads", None))
    # the render owns the photo and its map from here: it frees them once the scene is split (240 MB at 12 MP)
    inputs = Handover(image, disparity)
    del image, disparity
    out, stats = render_handed_over(inputs, blur, aperture_of(args), quality=args.quality,
                                    device=args.device, options=level_options,
                                    layers=layer_options_of(args), highlight_boost=args.highlight_boost,
                                    progress=bar.layers(), refine=args.refine,
                                    refine_options=refine_options_of(args))
    clock.lap_as(stats.stage_seconds, "render (other)")
    if grain is not None:
        from ..photo.grain import output_bits, restore_grain

        out = restore_grain(out, grain.grain, grain.removed, dither_bits=output_bits(args.output, args.bit_depth))
        clock.lap("grain")
    bar.stage("write")
    quality = JPEG_QUALITY if args.jpeg_quality is None else args.jpeg_quality
    path = write_image(args.output, out, bit_depth=args.bit_depth, half=args.half, quality=quality,
                       exif=exif_for_output(meta))  # JPEG keeps the photo's EXIF, orientation reset
    clock.lap("write")
    stats.stage_seconds = {**clock.laps, "total": clock.total()}  # the whole command, start-up to the file
    if grain is not None:  # said once the file is written, as a render with --blur and --focus says nothing before
        _say(args, f"grain: {grain.describe()} (--no-grain keeps the blur clean)")
    if not args.quiet:
        refined = (f", refined {stats.refine['tiles_refined']}/{stats.refine['tiles_total']} tiles"
                   if stats.refine else "")
        print(f"wrote {path}  (K = {blur.k_px:.3f} px, d_f = {blur.focus_disparity:.4f}, "
              f"max CoC {max_coc:.1f} px, {stats.stage_seconds['total']:.2f} s{refined})")
    if args.stats:
        info = stats.as_dict()
        info["blur"] = {"K_px": blur.k_px, "focus_disparity": blur.focus_disparity}
        print(json.dumps(info, indent=2))
    return {"output": str(path), "pixels": h * w, "seconds": stats.stage_seconds["total"], "k_px": blur.k_px,
            "focus_disparity": blur.focus_disparity, "focus": focus_how, "amount": amount,
            "focus_m": None if norm is None else float(norm.depth(blur.focus_disparity))}
