"""Command line: ``bokehray render``, ``synth``, ``demo``, ``train-refiner`` and ``bench``.

Every input problem is reported as one line ``bokehray: error: ...`` with exit
code 2 (``--debug`` shows the traceback). Outputs are written atomically, and
only after the render succeeded, so a failed run never leaves a partial file.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import re
import signal
import sys
import threading
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .._quiet import collect_warnings, command_stderr
from ..errors import EXIT_INTERRUPTED, BokehrayError, InputError, Terminated
from ..formats import FORMATS
from ..photo.subject import AMOUNT_DEFAULT, AMOUNT_K_FRACTION
from .render_job import aperture_of, layer_options_of, render_one, start_warp

if TYPE_CHECKING:
    from .demo import DemoScene

EXIT_INPUT = 2


def _on_sigterm(signum: int, frame) -> None:
    signal.signal(signum, signal.SIG_DFL)  # a second one during the clean-up ends the process
    raise Terminated(signum)


@contextlib.contextmanager
def _sigterm_raises() -> Iterator[None]:
    """Within the block, SIGTERM and SIGHUP (the terminal closed) raise :class:`Terminated` (main thread only; the
    previous handlers are restored). A SIGHUP that is ignored (``nohup``) stays ignored: the render outlives the
    terminal, as asked."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {}
    for sig in (signal.SIGTERM, signal.SIGHUP):
        if sig != signal.SIGHUP or signal.getsignal(sig) is not signal.SIG_IGN:
            previous[sig] = signal.signal(sig, _on_sigterm)
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def _parse_xy(text: str) -> tuple[int, int]:
    try:
        x, y = (int(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected X,Y in pixels (e.g. 640,410), got {text!r}") from None
    return x, y


def _add_lens_args(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("aperture")
    g.add_argument("--aperture", choices=("disc", "polygon"), default="disc", help="aperture shape (default: disc)")
    g.add_argument("--blades", type=int, default=None, help="polygon: number of blades (3..32, default 6)")
    g.add_argument("--rotation", type=float, default=None, help="polygon: rotation in degrees (default 0)")
    g.add_argument("--curvature", type=float, default=None,
                   help="polygon: blade curvature, 0 = straight blades .. 1 = circle (default 0)")


def _add_device_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--device", default="cpu", help="Warp device: cpu (default), cuda, cuda:N")
    p.add_argument("--stats", action="store_true", help="print time per stage, tiles skipped, layers, max CoC")
    p.add_argument("--max-layers", type=int, default=None, help="most depth layers of the preview (default 8)")
    p.add_argument("--no-fill", action="store_true", help="do not fill the regions hidden behind nearer layers")
    p.add_argument("--thin-depth", action="store_true",
                   help="give wires, twigs and strokes a soft map flattened their depth back from the photo (about "
                        "0.04 CPU-s a megapixel; docs/soft-scene.md)")
    p.add_argument("--debug", action="store_true", help="show tracebacks")
    p.add_argument("--quiet", action="store_true", help="print nothing but errors")


class _Parser(argparse.ArgumentParser):
    """argparse with the CLI's one-line error format (``bokehray: error: ...``, exit 2).

    Values that start with a minus sign and look like numbers or number pairs (``-0.5``,
    ``-1,0``) are values, not options: ``--focus-at -1,0`` reaches the option's own check
    (out of the image) instead of "expected one argument".
    """

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self._negative_number_matcher = re.compile(r"^-\d+$|^-\d*\.\d+$|^-\d+(,-?\d+)+$")

    argv: Sequence[str] = ()  # the command line being parsed (set by :func:`main`), for the hint below

    def error(self, message: str) -> None:  # type: ignore[override]
        self.exit(EXIT_INPUT, f"bokehray: error: {message}{_swallowed_hint(message, _Parser.argv)} "
                              f"(see {self.prog} --help)\n")


def _swallowed_hint(message: str, argv: Sequence[str]) -> str:
    """``--refine`` takes an optional WEIGHTS value: ``--refine photo.png`` at the end of the options takes the photo
    as the weights, and argparse then says only that the image is missing."""
    if "required: image" not in message:
        return ""
    argv = list(argv)
    for i, tok in enumerate(argv[:-1]):
        if tok == "--refine" and not argv[i + 1].startswith("-"):
            return f"; --refine took {argv[i + 1]} as its WEIGHTS: give the photo before --refine"
    return ""


def build_parser() -> argparse.ArgumentParser:
    from .. import __version__
    from .batch import add_batch_args, parse_sweep

    parser = _Parser(
        prog="bokehray",
        description="Physics-first lens blur: render a photo as a wide-aperture lens would have taken it.",
    )
    parser.add_argument("--version", action="version", version=f"bokehray {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)

    r = sub.add_parser(
        "render",
        help="render one image with a disparity (or depth) map",
        description="CoC radius in pixels = K * |d - d_f| (d: disparity in [0, 1], 1 = nearest). With only an image "
        "and a map it picks the blur (--amount 50) and focuses on the eyes of the nearest face, or without a face on "
        "the subject (the nearest depth region, split at the troughs of the map's histogram, holding 3% of the "
        "centre-weighted frame) and says so, with the depth range "
        "it read. Or give --amount/--blur K with --focus D_F or --focus-at X,Y, or a "
        "physical lens (--focal-length, --f-number, --focus-distance, --sensor-width) with a metric --depth map. "
        "docs/usage.md walks through it.",
    )
    r.add_argument("image", help="all-in-focus image: PNG/JPEG/TIFF (sRGB, 8/16-bit) or EXR/float TIFF (linear)")
    src = r.add_mutually_exclusive_group(required=True)
    src.add_argument("--disparity", help="disparity map in [0, 1], 1 = nearest (PNG 8/16-bit, EXR, TIFF, NPY); "
                     "any other range with --normalize")
    src.add_argument("--depth", help="metric depth map in metres: EXR, float TIFF or NPY; integer PNG/TIFF/NPY "
                     "codes with --depth-scale. Depth <= 0 or inf = no depth: infinitely far (sky)")
    src.add_argument("--depth-model", metavar="DIR",
                     help="no map: estimate one with a local Depth Anything (V1/V2) or DPT checkpoint folder "
                     "(transformers layout; never downloads; needs the 'depth' extra)")
    r.add_argument("-o", "--output", required=True, help="output: .png .jpg .tif .exr")
    dm = r.add_argument_group("depth conventions")
    dm.add_argument("--save-depth", action="store_true",
                    help="with --depth-model: also write the estimated disparity beside the output "
                    "(OUTPUT-disparity.png, 16-bit; reuse it with --disparity)")
    dm.add_argument("--normalize", action="store_true",
                    help="the --disparity map is relative (any range, e.g. a depth model's inverse depth): map its "
                    "0.5th..99.5th percentiles to 0..1")
    dm.add_argument("--invert", action="store_true", help="the --disparity map is near-is-dark: use 1 - d")
    dm.add_argument("--depth-scale", type=float, metavar="M", help="metres per code of an integer --depth map "
                    "(0.001 for a 16-bit millimetre PNG); multiplies a float map")
    b = r.add_argument_group("blur and focus")
    blur = b.add_mutually_exclusive_group()
    blur.add_argument("--amount", type=float, metavar="0..100",
                      help=f"blur strength independent of resolution: K = amount/100 x "
                      f"{AMOUNT_K_FRACTION:.0%} of the image diagonal (default {AMOUNT_DEFAULT:g})".replace("%", "%%"))
    blur.add_argument("--blur", type=parse_sweep, metavar="K", help="K: CoC radius in pixels per unit disparity")
    b.add_argument("--focus", type=parse_sweep, metavar="D_F", help="focus disparity d_f in [0, 1]; a list or START:STOP:COUNT renders a focal sweep")
    b.add_argument("--focus-at", type=_parse_xy, metavar="X,Y",
                   help="focus where this pixel is (median disparity in a 9 x 9 window)")
    lens = r.add_argument_group("blur as a physical thin lens (needs a metric --depth map)")
    lens.add_argument("--focal-length", type=float, metavar="MM", help="focal length in millimetres")
    lens.add_argument("--f-number", type=float, metavar="N", help="f-number (aperture diameter = f / N)")
    lens.add_argument("--focus-distance", type=float, metavar="M", help="focus distance in metres")
    lens.add_argument("--sensor-width", type=float, default=None, metavar="MM",
                      help="sensor width of the physical lens (default 36)")
    lens.add_argument("--z-near", type=float, help="depth normalisation: nearest depth (default: depth map min)")
    lens.add_argument("--z-far", type=float, help="depth normalisation: farthest depth, inf allowed (default: max)")
    _add_lens_args(r)
    o = r.add_argument_group("input and output")
    o.add_argument("--resize-disparity", action="store_true", help="resize a disparity/depth map of another size "
                   "(same aspect ratio)")
    o.add_argument("--bit-depth", type=int, choices=(8, 16, 32), help="PNG 8/16, TIFF 16/32 (float)")
    o.add_argument("--half", action="store_true", help="EXR: write half floats")
    o.add_argument("--jpeg-quality", type=int, default=None, metavar="Q",
                   help="quality of a JPEG output 1..100 (default 95)")
    o.add_argument("--no-highlight-reconstruction", action="store_true",
                   help="keep the clipped highlights of a PNG/JPEG/integer TIFF as they are (by default they are "
                   "re-inflated so that lamps give bright bokeh; never done for EXR/float TIFF)")
    o.add_argument("--no-grain", action="store_true",
                   help="keep the blur clean: by default a PNG/JPEG/integer TIFF photo's grain, measured where it is "
                   "flat and in focus, is restored where the blur removed it, and an 8-bit output is dithered "
                   "(seeded: the same command writes the same file; never for EXR/float TIFF)")
    o.add_argument("--highlight-boost", type=float, default=0.0,
                   help="instead of the reconstruction: the older uniform boost of every pixel near 1.0 "
                   "(1 + S t^2; 0 = off)")
    from ..levels import LEVELS, PHOTO_QUALITIES

    o.add_argument("--quality", default="preview", metavar="{" + ",".join(PHOTO_QUALITIES) + "}",
                   help="; ".join(f"{name}: {LEVELS[name].summary}" for name in PHOTO_QUALITIES)
                   + " (the ray tracer renders layer stacks: bokehray synth)")
    o.add_argument("--refine", nargs="?", const=True, default=False, metavar="WEIGHTS",
                   help="then run the neural refiner near depth edges (preview quality; needs the 'refiner' extra); "
                   "default: the shipped weights, or WEIGHTS from bokehray train-refiner")
    o.add_argument("--refiner-model", metavar="DIR", default=None,
                   help="instead of the shipped networks, a one-step diffusion checkpoint with PISA attention from "
                   "the local folder DIR (diffusers layout: unet/ vae/ scheduler/ and text encoders or "
                   "prompt_embeds.safetensors) renders the frame, on --device; implies --refine; nothing is "
                   "downloaded (docs/refiner.md)")
    o.add_argument("--refine-everywhere", action="store_true",
                   help="with --refine: also where the depth fix finds the map right (it moved under 1%% of the edge "
                   "band), which --refine leaves as rendered, and the edge network wherever the map is found wrong; "
                   "for a painted or estimated map that misses what the colour does not show, such as hair. On a "
                   "right map it costs about 3 dB (docs/refiner.md)")
    _add_device_args(r)
    add_batch_args(r)  # folders, globs, manifests, sweeps: bokehray.app.batch

    sy = sub.add_parser(
        "synth",
        help="generate synthetic paired data (BLB layout) with the layered ray tracer",
        description="RGBA foregrounds over all-in-focus backgrounds at random scale, placement, tilt and depth; "
        "exact thin-lens targets for every blur level and for focus on the foreground and on the background.",
    )
    sy.add_argument("-n", type=int, default=10, help="number of scenes (default 10)")
    sy.add_argument("-o", "--output", required=True, help="output folder (BLB layout)")
    sy.add_argument("--seed", type=int, default=0, help="seed: scene i depends only on (seed, i)")
    sy.add_argument("--fg", help="folder of RGBA foregrounds (PNG with alpha); default: built-in procedural ones")
    sy.add_argument("--bg", help="folder of background photos; default: photos bundled with scikit-image")
    sy.add_argument("--size", type=int, default=512, help="image side in pixels (default 512)")
    sy.add_argument("--blur-levels", default="10,20,30", help="K values, comma separated (default 10,20,30)")
    sy.add_argument("--max-spp", type=int, default=64, help="most rays (aperture cells) per pixel (default 64)")
    sy.add_argument("--depth-rule", choices=("any", "half"), default="any",
                    help="which pixels a foreground labels in the map: any coverage (default) or at least half "
                    "(a point-sampled sensor's rule, the dev set's and the soft scene's)")
    sy.add_argument("--kinds", metavar="KIND=W,...",
                    help="built-in foregrounds drawn with these relative weights, e.g. strands=3,fur=2,cutout=1 "
                    "(kinds: cutout, strands, foliage, mesh, lights, fur, whiskers, softcut; default: the first "
                    "five, uniformly)")
    from ..executor import add_executor_args

    add_executor_args(sy)
    sy.add_argument("--overwrite", action="store_true", help="replace scenes that exist already")
    _add_lens_args(sy)
    sy.add_argument("--debug", action="store_true", help="show tracebacks")
    sy.add_argument("--quiet", action="store_true", help="no progress bar")

    d = sub.add_parser("demo", help="render the built-in demo scene (no download) and a focal-stack contact sheet")
    d.add_argument("-o", "--output", default="bokehray-demo", help="output folder (default ./bokehray-demo)")
    d.add_argument("--size", type=_parse_xy, default=(1152, 768), metavar="W,H", help="image size (default 1152,768)")
    _add_lens_args(d)
    _add_device_args(d)

    t = sub.add_parser(
        "train-refiner",
        help="train the small one-step refiner on synthetic pairs (needs the 'refiner' extra)",
        description="Trains on a BLB-layout folder from `bokehray synth`: the classical level rendered, as `render "
        "--refine` does, after the depth fix on corrupted disparity (an estimator's map, locally misplaced edges, "
        "missing thin structures, eroded, dilated, exact) against the exact targets. Resumes from "
        "OUT/checkpoint.pt; the rendered inputs are kept in OUT/bank.npz. Writes OUT/refiner.safetensors, "
        "refiner.json, loss.csv and loss.png. See docs/refiner.md.",
    )
    t.add_argument("--data", required=True, help="BLB-layout training folder (from bokehray synth)")
    t.add_argument("--out", required=True, help="run folder: checkpoints, loss log and plot, final weights")
    t.add_argument("--steps", type=int, default=2000, help="optimiser steps (default 2000)")
    t.add_argument("--batch", type=int, default=8, help="crops per step (default 8)")
    t.add_argument("--crop", type=int, default=96, help="crop side in pixels, a multiple of 8 (default 96)")
    t.add_argument("--lr", type=float, default=1e-3, help="peak AdamW learning rate (default 1e-3)")
    t.add_argument("--variants", type=int, default=2, help="corrupted-depth renders per pair (default 2)")
    t.add_argument("--corruptions", metavar="KIND=SHARE,...",
                   help="shares of the corruptions (kinds: none, erode, dilate, blur, shift, estimator, local, "
                   "missing; unnamed kinds get 0; default: docs/refiner.md)")
    t.add_argument("--edge-share", type=float, default=0.8,
                   help="share of crops centred on the edge band, where the loss counts (default 0.8)")
    t.add_argument("--behind-gate", action="store_true",
                   help="count the loss only where the confidence gate lets the network's output through at "
                   "inference (weighted by it); by default over the whole edge band (measured: docs/refiner.md)")
    t.add_argument("--exact-weight", type=float, default=1.0,
                   help="weight of the loss on inputs rendered on the exact map, where any change is harm (default 1)")
    t.add_argument("--limit", type=int, help="use only the first N pairs")
    t.add_argument("--seed", type=int, default=0, help="seed of the model, the corruptions and the batches")
    t.add_argument("--edge-weight", type=float, default=0.5, help="weight of the multi-scale edge loss (eq. 9)")
    t.add_argument("--adv-weight", type=float, default=0.0, help="weight of the adversarial term (default off)")
    t.add_argument("--lpips-model", help="local TorchScript LPIPS model (never downloaded)")
    t.add_argument("--lpips-weight", type=float, default=0.0, help="weight of the LPIPS term (needs --lpips-model)")
    t.add_argument("--checkpoint-every", type=int, default=100, help="steps between checkpoints (default 100)")
    t.add_argument("--stop-at", type=int, help="stop at this step and export its weights (the schedule stays that "
                   "of --steps); resuming a run that is past it exports that checkpoint")
    t.add_argument("--no-resume", action="store_true", help="start over even if OUT/checkpoint.pt exists")
    t.add_argument("--device", default="auto", help="torch device: auto (cuda if present), cpu, cuda:0")
    t.add_argument("--threads", type=int, help="torch CPU threads (default: torch's choice; on a busy machine 1 is "
                   "several times faster than oversubscribed cores)")
    t.add_argument("--debug", action="store_true", help="show tracebacks")
    t.add_argument("--quiet", action="store_true", help="no progress bar")

    from .bench.cli import add_parser as add_bench_parser  # bokehray bench: docs/benchmarks.md

    add_bench_parser(sub)
    from .view.cli import add_parser as add_view_parser  # bokehray view: docs/view.md

    add_view_parser(sub)
    return parser


_A_BATCH = "a batch (a folder, a glob or a manifest of photos, or a focal sweep)"
_A_SWEEP = "a focal sweep (--focus or --blur with a list A,B,C or a range START:STOP:COUNT)"
_BATCH_ONLY = (  # (dest, what it does); given on a single render they would change nothing
    ("workers", f"--workers sets the number of processes of {_A_BATCH}"),
    ("executor", f"--executor chooses where the renders of {_A_BATCH} run"),
    ("scheduler", f"--scheduler names the Dask scheduler of {_A_BATCH}"),
    ("map_suffix", "--map-suffix pairs the photos of a batch (a folder or a glob of photos) with their maps by name"),
    ("overwrite", f"--overwrite renders again the outputs that {_A_BATCH} would skip as done"),
    ("gif_width", f"--gif-width sets the width of the animated preview of {_A_SWEEP}"),
    ("fps", f"--fps sets the frame rate of the animated preview of {_A_SWEEP}"),
    ("gif_labels", f"--gif-labels draws each frame's focus in the animated preview of {_A_SWEEP}"),
)
"""The options of many renders that ``bokehray render`` with one photo and one focus refuses, as it refuses other
flags that would change nothing (docs/robustness.md)."""


def _check_single_render(args: argparse.Namespace) -> None:
    """Flags of a batch, a sweep or another output format, given to a single render: refused before any work."""
    for dest, what in _BATCH_ONLY:
        value = getattr(args, dest)
        if value is not None and value is not False:  # given (0 too: 0 == False)
            replaces = ", which replaces its -o file whether it exists or not" if dest == "overwrite" else ""
            raise InputError(f"{what}; this is a single render (one photo, one focus){replaces}: leave "
                             f"--{dest.replace('_', '-')} out")
    fmt = args.output_format  # a batch's option; one render's format is its -o name's (FORMATS: .jpeg is jpg)
    if fmt is not None and FORMATS.get(Path(args.output).suffix.lower()) != FORMATS["." + fmt]:
        raise InputError(f"--output-format {args.output_format} sets the format of a batch's outputs; one render is "
                         f"written in the format its -o name says ({args.output}): name it .{args.output_format}")
    if args.jpeg_quality is not None and FORMATS.get(Path(args.output).suffix.lower()) != "JPEG":
        raise InputError(f"--jpeg-quality sets the quality of a JPEG output; {args.output} is not one (name it .jpg, "
                         "or leave --jpeg-quality out)")


def cmd_render(args: argparse.Namespace) -> int:
    from .batch import is_batch, run_batch

    if is_batch(args):  # folders, globs, manifests or a focal sweep (docs/scale.md)
        return run_batch(args)
    _check_single_render(args)
    render_one(args)
    return 0


def _demo_files(args: argparse.Namespace, scene: DemoScene, out_dir: Path,
                keep: Callable[[str, Path], None]) -> list[tuple[str, object]]:
    """Render and write the demo's files into ``out_dir``, each given to ``keep(what, path)``; the render stats."""
    from ..lens import BlurParams
    from ..output.write import write_disparity, write_image
    from ..pipeline import render_with_stats
    from .demo import contact_sheet

    aperture = aperture_of(args)
    opts = layer_options_of(args)

    def save(name: str, img: np.ndarray, what: str) -> None:
        keep(what, write_image(out_dir / name, img))

    save("input.png", scene.image, "all-in-focus input (sRGB preview)")
    keep("all-in-focus input (linear EXR)", write_image(out_dir / "input.exr", scene.image))
    keep("disparity (16-bit PNG, 1 = nearest)", write_disparity(out_dir / "disparity.png", scene.disparity))
    all_stats = []
    renders = {}
    for label, d_f in (("near", scene.focus_near), ("far", scene.focus_far)):
        out, stats = render_with_stats(scene.image, scene.disparity, BlurParams(scene.k_px, d_f), aperture,
                                       device=args.device, layers=opts)
        renders[label] = out
        all_stats.append((label, stats))
        save(f"render_focus_{label}.png", out, f"focused {label} (d_f = {d_f:.3f}, K = {scene.k_px:.2f})")
        keep(f"focused {label} (linear EXR)", write_image(out_dir / f"render_focus_{label}.exr", out))

    stack_d = np.linspace(scene.focus_far, scene.focus_near, 6)
    tiles, labels = [scene.image], ["all in focus"]
    disp_vis = np.repeat(scene.disparity[..., None], 3, axis=2) ** 2.2  # shown as grey, brighter = nearer
    tiles.append(disp_vis.astype(np.float32))
    labels.append("disparity (white = near)")
    for i, d_f in enumerate(stack_d):
        if i in (0, len(stack_d) - 1):  # the far and near ends are the renders written above
            out = renders["far" if i == 0 else "near"]
        else:
            out, _ = render_with_stats(scene.image, scene.disparity, BlurParams(scene.k_px, float(d_f)), aperture,
                                       device=args.device, layers=opts)
        tiles.append(out)
        labels.append(f"focus d_f = {d_f:.2f}")
    sheet = contact_sheet(tiles, labels, columns=4)
    sheet_path = out_dir / "focal_stack.png"
    from ..colour import srgb_to_linear

    keep("focal-stack contact sheet", write_image(sheet_path, srgb_to_linear(sheet / 255.0)))
    return all_stats


def cmd_demo(args: argparse.Namespace) -> int:
    from ..output.atomic import remove_made_folder_on_failure
    from .demo import build_demo_scene

    start_warp(args)
    w, h = args.size
    out_dir = Path(args.output)
    scene = build_demo_scene(width=w, height=h)
    written: list[tuple[str, Path]] = []
    # a failure (a full disk, Ctrl-C) removes the folder the demo made, with what it wrote there
    with remove_made_folder_on_failure(out_dir) as files:

        def keep(what: str, path: Path) -> None:
            files.append(path)
            written.append((what, path))

        all_stats = _demo_files(args, scene, out_dir, keep)
    if not args.quiet:
        print(scene.description)
        for what, path in written:
            print(f"  {what:<42} {path}")
        for label, st in all_stats:
            print(f"  render focus {label}: {st.stage_seconds['total']:.2f} s, {st.layers} layers, "
                  f"{st.tiles_copied}/{st.tiles_total} tiles copied, max CoC {st.max_coc_px:.1f} px")
    if args.stats:
        print(json.dumps({label: st.as_dict() for label, st in all_stats}, indent=2))
    return 0


def cmd_synth(args: argparse.Namespace) -> int:
    from ..data.synth import SynthConfig, generate
    from ..executor import check_executor_args

    check_executor_args(args.executor, workers=args.workers, scheduler=args.scheduler)  # before the folder is made
    try:
        levels = tuple(float(v) for v in args.blur_levels.split(","))
    except ValueError:
        raise InputError(f"--blur-levels: expected comma-separated numbers, got {args.blur_levels!r}") from None
    kinds = tuple(_name_values(args.kinds, "--kinds", "KIND=WEIGHT")) if args.kinds else None
    config = SynthConfig(size=args.size, blur_levels=levels, aperture=aperture_of(args), max_spp=args.max_spp,
                         fg_dir=args.fg, bg_dir=args.bg, kinds=kinds, depth_rule=args.depth_rule)
    start_warp(args)
    paths = generate(config, args.n, args.output, seed=args.seed, workers=args.workers, progress=not args.quiet,
                     overwrite=args.overwrite, executor=args.executor, scheduler=args.scheduler)
    if not args.quiet:
        print(f"wrote {len(paths)} scenes to {args.output}")
    return 0


def _name_values(text: str, option: str, form: str) -> list[tuple[str, float]]:
    """``"a=1,b=2.5"`` -> ``[("a", 1.0), ("b", 2.5)]``, or one line naming ``option`` and the expected form."""
    try:
        return [(k.strip(), float(v)) for k, v in (item.split("=") for item in text.split(","))]
    except ValueError:
        raise InputError(f"{option}: expected {form} pairs separated by commas, got {text!r}") from None


def _refiner_module(name: str):
    """Import a module of the optional torch refiner, or say which install step is missing."""
    import importlib

    try:
        return importlib.import_module(f"bokehray_refiner.{name}")
    except ImportError as e:
        raise InputError(f"the neural refiner needs its extra: pip install 'bokehray[refiner]' ({e})") from None


def _check_train_args(args: argparse.Namespace) -> None:
    """The counts, the crop and the training folder, each named with its flag and value, before the run folder
    (--out) is made: a refused run leaves nothing behind."""
    from ..data.datasets import BLBDataset

    for flag, value in (("--steps", args.steps), ("--batch", args.batch), ("--checkpoint-every", args.checkpoint_every),
                        ("--variants", args.variants)):
        if value < 1:
            raise InputError(f"{flag}: expected >= 1, got {value}")
    factor = _refiner_module("model").RefinerConfig().latent_factor
    if args.crop < factor or args.crop % factor:
        raise InputError(f"--crop: expected a positive multiple of {factor} (the refiner's latent grid), got "
                         f"{args.crop}")
    try:
        BLBDataset(args.data)
    except InputError as e:
        raise InputError(f"--data {args.data}: expected a BLB-layout training folder (from bokehray synth): {e}") from None


def cmd_train_refiner(args: argparse.Namespace) -> int:
    train = _refiner_module("training.residual")
    _check_train_args(args)
    start_warp(args)
    if args.threads is not None:
        if args.threads < 1:
            raise InputError(f"--threads: expected >= 1, got {args.threads}")
        import torch

        torch.set_num_threads(args.threads)
    extra = {}
    if args.corruptions:
        CORRUPTIONS = _refiner_module("training.data").CORRUPTIONS
        shares = dict(_name_values(args.corruptions, "--corruptions", "KIND=SHARE"))
        unknown = sorted(set(shares) - set(CORRUPTIONS))
        total = sum(shares.values())
        if unknown or not total > 0 or min(shares.values()) < 0:
            raise InputError(f"--corruptions: expected shares >= 0 of {CORRUPTIONS} with a positive sum, got "
                             f"{args.corruptions!r}")
        extra["corruption_probs"] = [shares.get(k, 0.0) / total for k in CORRUPTIONS]
    if not 0.0 <= args.edge_share <= 1.0:
        raise InputError(f"--edge-share: expected a share in [0, 1], got {args.edge_share}")
    try:
        cfg = train.TrainConfig(
            data=args.data, out=args.out, steps=args.steps, batch=args.batch, crop=args.crop, lr=args.lr,
            edge_share=args.edge_share, behind_gate=args.behind_gate, exact_weight=args.exact_weight, **extra,
            variants=args.variants, limit=args.limit, seed=args.seed, edge_weight=args.edge_weight,
            adv_weight=args.adv_weight, lpips_model=args.lpips_model, lpips_weight=args.lpips_weight,
            checkpoint_every=args.checkpoint_every, device=args.device)
        # tqdm's frames only on a terminal: in a log they are carriage-return noise (the loss log is the record)
        weights = train.train(cfg, resume=not args.no_resume, progress=not args.quiet and sys.stderr.isatty(),
                              stop_at=args.stop_at)
    except ValueError as e:
        raise InputError(str(e)) from None
    if not args.quiet:
        print(f"wrote {weights}")
    return 0


def _run(args: argparse.Namespace) -> int:
    if args.command == "render":
        return cmd_render(args)
    if args.command == "synth":
        return cmd_synth(args)
    if args.command == "train-refiner":
        return cmd_train_refiner(args)
    if args.command == "bench":
        from .bench.cli import cmd_bench

        return cmd_bench(args)
    if args.command == "view":
        from .view.cli import cmd_view

        return cmd_view(args)
    return cmd_demo(args)


def _os_error_line(e: OSError) -> str:
    """An OSError as one line that names the file (``[Errno 28] No space left on device`` names none)."""
    if e.filename is not None and e.strerror:
        other = f" -> {e.filename2}" if e.filename2 is not None else ""
        return f"{e.filename}{other}: {e.strerror}"
    return str(e)


def _exit_now(code: int) -> None:
    """End the process at once: the outputs are complete or absent (atomic writes), temporaries are removed."""
    import os

    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


def main(argv: Sequence[str] | None = None) -> int:  # noqa: C901
    with _sigterm_raises():
        try:
            parser = build_parser()
            _Parser.argv = sys.argv[1:] if argv is None else list(argv)
            args = parser.parse_args(argv)
        except KeyboardInterrupt as e:  # before any work: nothing to clean up
            return e.exit_code if isinstance(e, Terminated) else EXIT_INTERRUPTED
        debug = getattr(args, "debug", False)
        code, message = None, None
        # native libraries' lines (libpng, Warp, workers) go nowhere, bokehray's own reach the terminal
        with command_stderr(debug), collect_warnings(debug) as warned:
            try:
                code = _run(args)  # each command starts Warp when it computes (_start_warp): --help stays fast
            except BokehrayError as e:
                if debug:
                    raise
                message = str(e)
            except BrokenPipeError:  # stdout closed early (e.g. piped into head): the work is done
                sys.stdout = None
                return 0
            except OSError as e:  # the disk, not the input: e.g. an output folder that cannot be created
                if debug:
                    raise
                message = _os_error_line(e)
            except KeyboardInterrupt as e:
                # atomic writes removed their temporary file on the way out: nothing partial is left
                what = e.said if isinstance(e, Terminated) else "interrupted"
                with contextlib.suppress(OSError):  # after SIGHUP the terminal may be gone
                    print(f"bokehray: {what}; no partial output was left", file=sys.stderr)
                code = e.exit_code if isinstance(e, Terminated) else EXIT_INTERRUPTED
                if argv is None:  # the command itself (not a caller's main([...])): do not wait at exit for a
                    _exit_now(code)  # worker thread still inside a native launch (up to seconds on a 12 MP layer)
                return code
        if message is not None:  # one line; warnings raised on the way to the error are dropped (--debug shows them)
            print(f"bokehray: error: {message}", file=sys.stderr)
            return EXIT_INPUT
        if not getattr(args, "quiet", False):
            for w in warned:
                print(f"bokehray: warning: {w.message} ({Path(w.filename).name}:{w.lineno})", file=sys.stderr)
        return code


def run() -> None:
    """The ``bokehray`` command: :func:`main`, then the exit handlers, and the process ends without the
    interpreter's teardown (unloading Warp's native libraries alone took 0.17-0.25 s a command on the 2-core
    machine, after every file was written: a cost on no clock)."""
    import atexit

    code = main()
    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(OSError, ValueError, AttributeError):  # closed, or None after a broken pipe
            stream.flush()
    os._exit(code)


if __name__ == "__main__":
    run()
