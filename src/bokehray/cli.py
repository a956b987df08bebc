"""Command line: ``bokehray render``, ``bokehray demo``.

Every input problem is reported as one line ``bokehray: error: ...`` with exit
code 2 (``--debug`` shows the traceback). Outputs are written atomically, and
only after the render succeeded, so a failed run never leaves a partial file.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ._quiet import init_warp_quietly
from .errors import BokehrayError, InputError

EXIT_INPUT = 2


def _parse_xy(text: str) -> tuple[int, int]:
    try:
        x, y = (int(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected X,Y in pixels (e.g. 640,410), got {text!r}") from None
    return x, y


def _add_lens_args(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("aperture")
    g.add_argument("--aperture", choices=("disc", "polygon"), default="disc", help="aperture shape (default: disc)")
    g.add_argument("--blades", type=int, default=6, help="polygon: number of blades (3..32, default 6)")
    g.add_argument("--rotation", type=float, default=0.0, help="polygon: rotation in degrees")
    g.add_argument("--curvature", type=float, default=0.0,
                   help="polygon: blade curvature, 0 = straight blades .. 1 = circle (default 0)")


def _add_device_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--device", default="cpu", help="Warp device: cpu (default), cuda, cuda:N")
    p.add_argument("--stats", action="store_true", help="print time per stage, tiles skipped, layers, max CoC")
    p.add_argument("--max-layers", type=int, default=None, help="most depth layers of the preview (default 8)")
    p.add_argument("--no-fill", action="store_true", help="do not fill the regions hidden behind nearer layers")
    p.add_argument("--debug", action="store_true", help="show tracebacks")
    p.add_argument("--quiet", action="store_true", help="print nothing but errors")


class _Parser(argparse.ArgumentParser):
    """argparse with the CLI's one-line error format (``bokehray: error: ...``, exit 2)."""

    def error(self, message: str) -> None:  # type: ignore[override]
        self.exit(EXIT_INPUT, f"bokehray: error: {message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    from . import __version__

    parser = _Parser(
        prog="bokehray",
        description="Physics-first lens blur: render a photo as a wide-aperture lens would have taken it.",
    )
    parser.add_argument("--version", action="version", version=f"bokehray {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)

    r = sub.add_parser(
        "render",
        help="render one image with a disparity (or depth) map",
        description="CoC radius in pixels = K * |d - d_f| (d: disparity in [0, 1], 1 = nearest). Give the blur as "
        "--blur K with --focus D_F or --focus-at X,Y, or as a physical lens (--focal-length, --f-number, "
        "--focus-distance, --sensor-width) with a metric --depth map.",
    )
    r.add_argument("image", help="all-in-focus image: PNG/JPEG/TIFF (sRGB, 8/16-bit) or EXR/float TIFF (linear)")
    src = r.add_mutually_exclusive_group(required=True)
    src.add_argument("--disparity", help="disparity map in [0, 1], 1 = nearest: PNG 8/16-bit, EXR, TIFF, NPY")
    src.add_argument("--depth", help="metric depth map in metres: EXR, float TIFF or NPY")
    r.add_argument("-o", "--output", required=True, help="output: .png .jpg .tif .exr")
    b = r.add_argument_group("blur as K and focus disparity")
    b.add_argument("--blur", type=float, help="K: CoC radius in pixels per unit disparity")
    b.add_argument("--focus", type=float, help="focus disparity d_f in [0, 1]")
    b.add_argument("--focus-at", type=_parse_xy, metavar="X,Y",
                   help="focus where this pixel is (median disparity in a 9 x 9 window)")
    lens = r.add_argument_group("blur as a physical thin lens (needs --depth)")
    lens.add_argument("--focal-length", type=float, metavar="MM", help="focal length in millimetres")
    lens.add_argument("--f-number", type=float, metavar="N", help="f-number (aperture diameter = f / N)")
    lens.add_argument("--focus-distance", type=float, metavar="M", help="focus distance in metres")
    lens.add_argument("--sensor-width", type=float, default=36.0, metavar="MM", help="sensor width (default 36)")
    lens.add_argument("--z-near", type=float, help="depth normalisation: nearest depth (default: depth map min)")
    lens.add_argument("--z-far", type=float, help="depth normalisation: farthest depth, inf allowed (default: max)")
    _add_lens_args(r)
    o = r.add_argument_group("input and output")
    o.add_argument("--resize-disparity", action="store_true", help="resize a disparity/depth map of another size")
    o.add_argument("--bit-depth", type=int, choices=(8, 16, 32), help="PNG 8/16, TIFF 16/32 (float)")
    o.add_argument("--half", action="store_true", help="EXR: write half floats")
    o.add_argument("--highlight-boost", type=float, default=0.0,
                   help="re-inflate clipped highlights of 8-bit inputs (0 = off, try 4)")
    o.add_argument("--quality", choices=("preview", "raytrace"), default="preview",
                   help="preview: layered scatter, fast, and the more accurate level for photos; raytrace: the "
                   "same layers ray traced, much slower and on photos measured slightly below the preview "
                   "(docs/raytracer.md; it is the exact renderer of true layer stacks, used by 'synth')")
    o.add_argument("--max-spp", type=int, default=128, help="raytrace: most rays (aperture cells) per pixel (default 128)")
    o.add_argument("--refine", nargs="?", const=True, default=False, metavar="WEIGHTS",
                   help="then run the neural refiner near depth edges (preview quality; needs the 'refiner' extra); "
                   "default: the shipped weights, or WEIGHTS from bokehray train-refiner")
    _add_device_args(r)

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
    sy.add_argument("--workers", type=int, default=None, help="worker processes (default: all cores)")
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
        description="Trains on a BLB-layout folder from `bokehray synth`: classical previews rendered from corrupted "
        "disparity (eroded, dilated, blurred, shifted) against the exact targets. Resumes from OUT/checkpoint.pt. "
        "Writes OUT/refiner.safetensors, refiner.json, loss.csv and loss.png. See docs/refiner.md.",
    )
    t.add_argument("--data", required=True, help="BLB-layout training folder (from bokehray synth)")
    t.add_argument("--out", required=True, help="run folder: checkpoints, loss log and plot, final weights")
    t.add_argument("--steps", type=int, default=2000, help="optimiser steps (default 2000)")
    t.add_argument("--batch", type=int, default=8, help="crops per step (default 8)")
    t.add_argument("--crop", type=int, default=96, help="crop side in pixels, a multiple of 8 (default 96)")
    t.add_argument("--lr", type=float, default=1e-3, help="peak AdamW learning rate (default 1e-3)")
    t.add_argument("--variants", type=int, default=2, help="corrupted-depth renders per pair (default 2)")
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
    return parser


def _aperture(args: argparse.Namespace):
    from .lens import Aperture

    if args.aperture == "disc":
        return Aperture()
    return Aperture(blades=args.blades, rotation_deg=args.rotation, curvature=args.curvature)


def _options(args: argparse.Namespace):
    from ._scatter import PreviewOptions

    kw = {}
    if args.max_layers is not None:
        if args.max_layers < 1:
            raise InputError(f"--max-layers: expected >= 1, got {args.max_layers}")
        kw["max_layers"] = args.max_layers
    if args.no_fill:
        kw["fill"] = False
    return PreviewOptions(**kw)


def _progress_bar(args: argparse.Namespace):
    """A tqdm bar over depth layers, shown on a terminal only."""
    if args.quiet or not sys.stderr.isatty():
        return None, None
    from tqdm import tqdm

    bar = tqdm(total=0, desc="layers", unit="layer", leave=False, file=sys.stderr)

    def update(done: int, total: int) -> None:
        bar.total = total
        bar.n = done
        bar.refresh()

    return bar, update


def _resize(a: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    from skimage.transform import resize

    return resize(a, shape, order=1, mode="edge", anti_aliasing=False, preserve_range=True).astype(np.float32)


def _check_output(path: str, args: argparse.Namespace) -> None:
    from .io import check_output_path

    check_output_path(path, bit_depth=getattr(args, "bit_depth", None), half=getattr(args, "half", False))


def cmd_render(args: argparse.Namespace) -> int:
    from . import io
    from .lens import BlurParams, DepthNormalization, ThinLens, disparity_from_depth
    from .render import focus_at, render_with_stats

    _check_output(args.output, args)
    t0 = time.perf_counter()
    image = io.read_image(args.image)
    h, w = image.shape[:2]

    lens_args = (args.focal_length, args.f_number, args.focus_distance)
    physical = any(v is not None for v in lens_args)
    if physical and args.depth is None:
        raise InputError("a physical lens (--focal-length/--f-number/--focus-distance) needs a metric --depth map")
    if physical and (args.blur is not None or args.focus is not None):
        raise InputError("give the blur either as --blur/--focus or as a physical lens, not both")

    if args.depth is not None:
        depth = io.read_depth(args.depth)
        norm = None
        if args.z_near is not None or args.z_far is not None:
            zn = args.z_near if args.z_near is not None else float(np.min(depth))
            zf = args.z_far if args.z_far is not None else float(np.max(depth))
            norm = DepthNormalization(zn, zf)
        # resize after the conversion: disparity interpolates where depth cannot (inf for sky)
        disparity, norm = disparity_from_depth(depth, norm)
    else:
        disparity, norm = io.read_disparity(args.disparity, check_range=True), None
    if disparity.shape != (h, w):
        source = args.depth or args.disparity
        if not args.resize_disparity:
            raise InputError(f"{source}: map is {disparity.shape[1]}x{disparity.shape[0]}, image is {w}x{h}; "
                             "pass --resize-disparity to resize it")
        disparity = _resize(disparity, (h, w))

    if physical:
        if args.focal_length is None or args.f_number is None:
            raise InputError("a physical lens needs both --focal-length and --f-number")
        focus_m = args.focus_distance
        if args.focus_at is not None:
            x, y = args.focus_at
            focus_m = float(norm.depth(focus_at(disparity, x, y)))
            if not np.isfinite(focus_m):
                raise InputError(f"--focus-at {x},{y}: that point is at infinity (sky); a thin lens focused there "
                                 "needs --focus-distance, or click on a surface")
        if focus_m is None:
            raise InputError("a physical lens needs --focus-distance or --focus-at X,Y")
        lens = ThinLens(args.focal_length, args.f_number, focus_m, args.sensor_width)
        blur = lens.blur_params(norm, w)
    else:
        if args.blur is None:
            raise InputError("give the blur strength: --blur K (or a physical lens with --depth)")
        if args.blur < 0:
            raise InputError(f"--blur: expected K >= 0, got {args.blur:g}")
        if (args.focus is None) == (args.focus_at is None):
            raise InputError("give the focus as exactly one of --focus D_F or --focus-at X,Y")
        d_f = args.focus if args.focus is not None else focus_at(disparity, *args.focus_at)
        blur = BlurParams(args.blur, d_f)
    t_read = time.perf_counter() - t0

    bar, update = _progress_bar(args)
    try:
        from .raytrace import RaytraceOptions

        rt_opts = RaytraceOptions(max_spp=args.max_spp)  # validated whatever the quality
        out, stats = render_with_stats(image, disparity, blur, _aperture(args), quality=args.quality,
                                       device=args.device, options=_options(args), raytrace_options=rt_opts,
                                       highlight_boost=args.highlight_boost, progress=update, refine=args.refine)
    finally:
        if bar is not None:
            bar.close()
    t1 = time.perf_counter()
    path = io.write_image(args.output, out, bit_depth=args.bit_depth, half=args.half)
    t_write = time.perf_counter() - t1
    if not args.quiet:
        max_coc = float(blur.coc_radius(disparity).max())
        refined = (f", refined {stats.refine['tiles_refined']}/{stats.refine['tiles_total']} tiles"
                   if stats.refine else "")
        print(f"wrote {path}  (K = {blur.k_px:.3f} px, d_f = {blur.focus_disparity:.4f}, "
              f"max CoC {max_coc:.1f} px, {stats.stage_seconds.get('total', 0.0):.2f} s{refined})")
    if args.stats:
        info = stats.as_dict()
        info["stage_seconds"] = {"read": round(t_read, 4), **info["stage_seconds"], "write": round(t_write, 4)}
        info["blur"] = {"K_px": blur.k_px, "focus_disparity": blur.focus_disparity}
        print(json.dumps(info, indent=2))
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    from . import io
    from .demo import build_demo_scene, contact_sheet
    from .lens import BlurParams
    from .render import render_with_stats

    w, h = args.size
    out_dir = Path(args.output)
    scene = build_demo_scene(width=w, height=h)
    aperture = _aperture(args)
    opts = _options(args)
    written: list[tuple[str, Path]] = []

    def save(name: str, img: np.ndarray, what: str) -> None:
        written.append((what, io.write_image(out_dir / name, img)))

    save("input.png", scene.image, "all-in-focus input (sRGB preview)")
    written.append(("all-in-focus input (linear EXR)", io.write_image(out_dir / "input.exr", scene.image)))
    written.append(("disparity (16-bit PNG, 1 = nearest)", io.write_disparity(out_dir / "disparity.png",
                                                                            scene.disparity)))
    all_stats = []
    renders = {}
    for label, d_f in (("near", scene.focus_near), ("far", scene.focus_far)):
        out, stats = render_with_stats(scene.image, scene.disparity, BlurParams(scene.k_px, d_f), aperture,
                                       device=args.device, options=opts)
        renders[label] = out
        all_stats.append((label, stats))
        save(f"render_focus_{label}.png", out, f"focused {label} (d_f = {d_f:.3f}, K = {scene.k_px:.2f})")
        written.append((f"focused {label} (linear EXR)", io.write_image(out_dir / f"render_focus_{label}.exr", out)))

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
                                       device=args.device, options=opts)
        tiles.append(out)
        labels.append(f"focus d_f = {d_f:.2f}")
    sheet = contact_sheet(tiles, labels, columns=4)
    sheet_path = out_dir / "focal_stack.png"
    from .io import srgb_to_linear

    written.append(("focal-stack contact sheet", io.write_image(sheet_path, srgb_to_linear(sheet / 255.0))))
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
    from .synth import SynthConfig, generate

    try:
        levels = tuple(float(v) for v in args.blur_levels.split(","))
    except ValueError:
        raise InputError(f"--blur-levels: expected comma-separated numbers, got {args.blur_levels!r}") from None
    config = SynthConfig(size=args.size, blur_levels=levels, aperture=_aperture(args), max_spp=args.max_spp,
                         fg_dir=args.fg, bg_dir=args.bg)
    paths = generate(config, args.n, args.output, seed=args.seed, workers=args.workers, progress=not args.quiet,
                     overwrite=args.overwrite)
    if not args.quiet:
        print(f"wrote {len(paths)} scenes to {args.output}")
    return 0


def _refiner_module(name: str):
    """Import a module of the optional torch refiner, or say which install step is missing."""
    import importlib

    try:
        return importlib.import_module(f"bokehray_refiner.{name}")
    except ImportError as e:
        raise InputError(f"the neural refiner needs its extra: pip install 'bokehray[refiner]' ({e})") from None


def cmd_train_refiner(args: argparse.Namespace) -> int:
    train = _refiner_module("train")
    if args.threads is not None:
        if args.threads < 1:
            raise InputError(f"--threads: expected >= 1, got {args.threads}")
        import torch

        torch.set_num_threads(args.threads)
    try:
        cfg = train.TrainConfig(
            data=args.data, out=args.out, steps=args.steps, batch=args.batch, crop=args.crop, lr=args.lr,
            variants=args.variants, limit=args.limit, seed=args.seed, edge_weight=args.edge_weight,
            adv_weight=args.adv_weight, lpips_model=args.lpips_model, lpips_weight=args.lpips_weight,
            checkpoint_every=args.checkpoint_every, device=args.device)
        weights = train.train(cfg, resume=not args.no_resume, progress=not args.quiet, stop_at=args.stop_at)
    except ValueError as e:
        raise InputError(str(e)) from None
    if not args.quiet:
        print(f"wrote {weights}")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    init_warp_quietly(args.debug)
    try:
        if args.command == "render":
            return cmd_render(args)
        if args.command == "synth":
            return cmd_synth(args)
        if args.command == "train-refiner":
            return cmd_train_refiner(args)
        if args.command == "bench":
            from .bench.cli import cmd_bench

            return cmd_bench(args)
        return cmd_demo(args)
    except BokehrayError as e:
        if args.debug:
            raise
        print(f"bokehray: error: {e}", file=sys.stderr)
        return EXIT_INPUT
    except OSError as e:  # the disk, not the input: e.g. an output folder that cannot be created
        if args.debug:
            raise
        print(f"bokehray: error: {e}", file=sys.stderr)
        return EXIT_INPUT
    except KeyboardInterrupt:
        print("bokehray: interrupted; no output was written", file=sys.stderr)
        return 130
    except BrokenPipeError:  # stdout closed early (e.g. piped into head): the work is done
        sys.stdout = None
        return 0


if __name__ == "__main__":
    sys.exit(main())
