"""``bokehray render`` on many inputs: folders, globs, manifests, focal sweeps (docs/scale.md).

The command line names the photos with the positional argument (a file, a folder or a glob) and their maps with
``--disparity`` or ``--depth`` (a file, a folder, a glob or a manifest CSV). A photo finds its map by one rule:

* **same stem**: ``shoot/IMG_01.jpg`` pairs with ``maps/IMG_01.png`` (any map extension: PNG, TIFF, EXR, NPY);
* **a suffix** (``--map-suffix _disp``): ``IMG_01.jpg`` pairs with ``IMG_01_disp.png``, the maps may then lie in
  the photos' folder (files whose stem ends with the suffix are maps, not photos);
* **a manifest CSV** (``--disparity pairs.csv``): a header with ``image`` and ``disparity`` (or ``depth``, or
  ``map``) columns; ``image`` is a photo's path (relative to the CSV's folder, like the map's) or just its file
  name. Rows for photos that are not among the inputs are ignored.

Each photo gives one output ``OUT/<stem>.<ext>`` (``--output-format``, default: the photo's own format); with a
sweep (``--focus 0.1:0.9:9`` or ``--blur 4,8,16``) each photo gives a focal stack ``OUT/<stem>_focus_0.100.<ext>``
... and an animated ``OUT/<stem>_focus_sweep.gif`` (Pillow). Renders are tasks ``(input paths, settings)`` on an
executor (:mod:`bokehray.executor`), written atomically by their worker. A rerun skips the outputs that exist: a
file there is complete (atomic writes) and was made with the same settings (``OUT/bokehray-batch.json`` holds
them; other settings or foreign files are refused unless ``--overwrite``). A photo that fails is reported in the
summary at the end and never stops the batch; the command then exits with 2.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import glob
import hashlib
import json
import math
import os
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

from ..errors import EXIT_INTERRUPTED, InputError, Terminated
from ..validate import number_text

__all__ = ["Pair", "RenderSettings", "RenderTask", "add_batch_args", "find_pairs", "frame_labels", "is_batch",
           "parse_sweep", "render_file", "run_batch", "sweep_values"]

IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".exr")
MAP_EXTS = (".png", ".tif", ".tiff", ".exr", ".npy")
OUTPUT_FORMATS = ("png", "jpg", "tif", "exr")
STATE_FILE = "bokehray-batch.json"
MAX_SWEEP = 1000
GIF_WIDTH = 640
"""Width of a sweep's animated preview without ``--gif-width``."""
FPS = 6.0
"""Frame rate of a sweep's animated preview without ``--fps``."""


# --------------------------------------------------------------------------- the command line


def parse_sweep(text: str) -> float | tuple[float, ...]:
    """``0.5`` -> 0.5; ``0.2,0.4,0.6`` -> a list (2 values or more: no empty item, so ``0.5,`` is no one-frame sweep);
    ``START:STOP:COUNT`` -> COUNT values from START to STOP (finite ends). ``-0`` is read as 0 (``+ 0.0``): a negative
    zero would print as ``-0.000`` in every line and JSON after it."""
    try:
        if ":" in text:
            values = _sweep_range(text)
        elif "," in text:
            items = text.split(",")
            if any(not v.strip() for v in items):
                raise argparse.ArgumentTypeError(f"a list A,B,C has an empty value in {text!r}")
            values = tuple(float(v) for v in items)
            if len(values) > MAX_SWEEP:
                raise argparse.ArgumentTypeError(f"a list takes at most {MAX_SWEEP} values, got {len(values)}")
        else:
            return float(text) + 0.0
        return tuple(v + 0.0 for v in values)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, a list A,B,C or a range START:STOP:COUNT, "
                                         f"got {text!r}") from None


def _sweep_range(text: str) -> tuple[float, ...]:
    parts = text.split(":")
    if len(parts) != 3:
        raise ValueError
    start, stop, count = float(parts[0]), float(parts[1]), int(parts[2])
    if not (math.isfinite(start) and math.isfinite(stop)):
        raise argparse.ArgumentTypeError(f"a range needs finite ends, got {text!r}")
    if not 2 <= count <= MAX_SWEEP:
        raise argparse.ArgumentTypeError(f"a range needs 2..{MAX_SWEEP} values, got {count} in {text!r}")
    return tuple(start + (stop - start) * i / (count - 1) for i in range(count))


def add_batch_args(r: argparse.ArgumentParser) -> None:
    """The batch options of ``bokehray render`` (called from :func:`bokehray.app.cli.build_parser`)."""
    from ..executor import add_executor_args

    g = r.add_argument_group(
        "many inputs (docs/scale.md)",
        "IMAGE may be a folder or a glob ('shoot/*.jpg'), --disparity/--depth a folder, a glob or a manifest CSV "
        "(columns image,disparity); -o is then a folder. --focus/--blur also take a list (0.2,0.4) or a range "
        "(START:STOP:COUNT): a focal stack and an animated GIF per image.")
    # the batch's options default to None (resolved in run_batch): a single render refuses them when given
    g.add_argument("--map-suffix", default=None, metavar="SUFFIX",
                   help="a map's stem is the image's stem plus SUFFIX (e.g. _disp; default: the same stem)")
    g.add_argument("--output-format", choices=OUTPUT_FORMATS, help="format of the outputs (default: the input's)")
    g.add_argument("--overwrite", action="store_true",
                   help="render everything again (default: skip outputs that exist, made with the same settings)")
    g.add_argument("--gif-width", type=int, default=None,
                   help=f"width of the animated sweep preview (default {GIF_WIDTH})")
    g.add_argument("--fps", type=float, default=None, help=f"frames per second of the sweep preview (default {FPS:g})")
    g.add_argument("--gif-labels", action="store_const", const=True, default=None,
                   help="draw each frame's focus (or blur) small in the corner of the sweep's animated preview")
    add_executor_args(r, workers_help="worker processes (default: all cores, at most one per render)")


def _is_glob(text: str) -> bool:
    return any(c in text for c in "*?[")


def is_batch(args: argparse.Namespace) -> bool:
    """Whether ``bokehray render`` was given many inputs or a sweep (else: the single-file path)."""
    maps = args.disparity or args.depth
    # a single photo with a folder as its map stays on the single-file path (which names the folder as the error)
    return (Path(args.image).is_dir() or (_is_glob(args.image) and not Path(args.image).exists())
            or isinstance(args.focus, tuple) or isinstance(args.blur, tuple)
            or (maps is not None and (maps.lower().endswith(".csv") or (_is_glob(maps) and not Path(maps).exists()))))


# --------------------------------------------------------------------------- pairing


@dataclass(frozen=True)
class Pair:
    """A photo and its map (``map`` None: no map found, ``problem`` says why)."""

    image: Path
    map: Path | None
    problem: str | None = None


def natural_key(p: Path) -> list:
    from ..data.datasets import natural_key as key

    return key(str(p))


def _listing(spec: str, exts: tuple[str, ...], what: str) -> tuple[list[Path], Path | None]:
    """Files named by a folder, a glob or one file; and the folder they are relative to."""
    p = Path(spec)
    if p.is_dir():
        # not only regular files: a FIFO, a dangling link or a link loop named as a photo is listed, to be reported
        # as a failure (not_a_file), not dropped silently
        files = [f for f in p.iterdir() if not f.is_dir() and not f.name.startswith(".") and f.suffix.lower() in exts]
        return sorted(files, key=natural_key), p
    if p.is_file():
        return [p], p.parent
    if _is_glob(spec):
        files = [Path(f) for f in glob.glob(spec, recursive=True)]
        files = [f for f in files if not f.is_dir() and f.suffix.lower() in exts]
        return sorted(files, key=natural_key), None
    raise InputError(f"{spec}: no such {what} file or folder")


def _real(f: Path) -> Path:
    """``f`` resolved; a link loop (which ``resolve`` refuses) as it is named."""
    try:
        return f.resolve()
    except (OSError, RuntimeError):
        return f.absolute()


def not_a_file(f: Path) -> str | None:
    """Why ``f`` cannot be read as a photo's file (a dangling symbolic link, a link loop, a named pipe, a socket, a
    device), or None for a regular file."""
    import errno
    import stat

    try:
        mode = os.stat(f).st_mode
    except OSError as e:
        if e.errno == errno.ELOOP:
            return "a loop of symbolic links"
        if e.errno == errno.ENOENT and os.path.islink(f):
            return f"a dangling symbolic link (to {os.readlink(f)})"
        return f"cannot be read ({e.strerror or e})"
    if stat.S_ISREG(mode):
        return None
    kind = "a named pipe (FIFO)" if stat.S_ISFIFO(mode) else "a socket" if stat.S_ISSOCK(mode) else "a device"
    return f"expected a regular file, got {kind}"


def _manifest(path: Path, kind: str) -> dict[str, Path]:
    rows: list[tuple[int, list[str]]] = []
    try:
        with open(path, newline="", encoding="utf-8-sig") as fh:
            reader = csv.reader(fh)
            header = [h.strip().lower() for h in next(reader, [])]
            for fields in reader:
                if any(f.strip() for f in fields):  # blank lines are no rows
                    rows.append((reader.line_num, fields))
    except (OSError, UnicodeDecodeError, csv.Error) as e:
        raise InputError(f"{path}: cannot read the manifest CSV ({e})") from None
    if not rows:
        raise InputError(f"{path}: the manifest CSV has no rows (expected a header image,{kind} and one row a pair)")
    col = next((c for c in (kind, "map") if c in header), None)
    if "image" not in header or col is None:
        raise InputError(f"{path}: the manifest CSV needs the columns image and {kind} (or map), got "
                         f"{', '.join(header)}")
    out: dict[str, Path] = {}
    for n, fields in rows:
        if len(fields) > len(header):
            raise InputError(f"{path}: line {n}: expected at most {len(header)} fields (the header's "
                             f"{','.join(header)}), got {len(fields)}; quote a path that holds a comma")
        row = dict(zip(header, (f.strip() for f in fields)))
        if not row.get("image") or not row.get(col):
            raise InputError(f"{path}: line {n}: expected an image and a {kind} path")
        if "\0" in row["image"] + row[col]:  # no file system takes it: os calls raised "embedded null byte"
            raise InputError(f"{path}: line {n}: a path holds a NUL byte")
        m = Path(row[col])
        out[row["image"]] = m if m.is_absolute() else path.parent / m
    return out


def _check_one_map_file(images: str, mp: Path, files: list[Path], kind: str, suffix: str) -> None:
    """One map file for a folder or glob of photos pairs with the photo of its name at most: refused up front (the
    others would each fail in the summary, after the output folder was made)."""
    if Path(images).is_file() or not mp.is_file():
        return
    others = [f for f in files if f.stem + suffix != mp.stem]
    if others:
        raise InputError(f"--{kind} {mp}: one map file for the {len(files)} photos of {images}; give a folder or a "
                         f"glob of maps named after the photos (or a manifest CSV of pairs), or render one photo "
                         f"with it")


def find_pairs(images: str, maps: str, *, kind: str = "disparity", suffix: str = "") -> list[Pair]:
    """The photos named by ``images`` and their maps from ``maps`` (module docstring: the pairing rule). A photo that
    is no regular file is a pair without a map, its problem said (:func:`not_a_file`): the batch lists it as failed."""
    pairs = _pair(images, maps, kind=kind, suffix=suffix)
    return [Pair(p.image, None, why) if (why := not_a_file(p.image)) else p for p in pairs]


def _pair(images: str, maps: str, *, kind: str, suffix: str) -> list[Pair]:  # noqa: C901
    mp = Path(maps)
    if mp.suffix.lower() == ".csv" and mp.is_file():
        table = _manifest(mp, kind)
        files, root = _listing(images, IMAGE_EXTS, "image")
        pairs = []
        by_path = {_real(mp.parent / k): m for k, m in table.items()}
        for f in files:
            keys = [f.name] + ([str(f.relative_to(root))] if root is not None else [])
            m = by_path.get(_real(f)) or next((table[k] for k in keys if k in table), None)
            pairs.append(Pair(f, m) if m is not None else Pair(f, None, f"no {kind} map listed in {mp}"))
        return pairs
    if mp.suffix.lower() == ".csv":
        raise InputError(f"{maps}: no such manifest CSV")
    map_files, _ = _listing(maps, MAP_EXTS, kind)
    by_stem: dict[str, list[Path]] = {}
    for m in map_files:
        by_stem.setdefault(m.stem, []).append(m)
    files, _ = _listing(images, IMAGE_EXTS, "image")
    map_set = {_real(m) for m in map_files}
    if suffix:
        files = [f for f in files if not f.stem.endswith(suffix)]
    elif Path(images).is_file() and mp.is_file():
        return [Pair(Path(images), mp)]
    else:
        shared = [f for f in files if _real(f) in map_set]
        if shared:
            raise InputError(f"{maps}: the maps are among the images ({shared[0]}); name them with a suffix and "
                             "pass --map-suffix (e.g. IMG_01.jpg and IMG_01_disp.png with --map-suffix _disp)")
    _check_one_map_file(images, mp, files, kind, suffix)
    pairs = []
    for f in files:
        cands = [m for m in by_stem.get(f.stem + suffix, []) if _real(m) != _real(f)]
        if len(cands) == 1:
            pairs.append(Pair(f, cands[0]))
        elif not cands:
            pairs.append(Pair(f, None, f"no {kind} map named {f.stem + suffix}.* in {maps}"))
        else:
            pairs.append(Pair(f, None, f"{len(cands)} {kind} maps match: " + ", ".join(c.name for c in cands)))
    return pairs


# --------------------------------------------------------------------------- one render (a task)


_NOT_SETTINGS = frozenset({
    "command", "image", "disparity", "depth", "output",  # the task's own paths
    "map_suffix", "output_format", "overwrite", "gif_width", "fps", "gif_labels", "executor", "workers", "scheduler",
    "quiet", "debug", "stats",  # how a process talks, not what it renders
})


@dataclass(frozen=True)
class RenderSettings:
    """Everything a render depends on besides its input paths: the single-file ``bokehray render`` arguments,
    as (name, value) pairs, so a batch task renders exactly what the single-file command does with them."""

    kind: str = "disparity"  # or "depth" (metric, metres)
    args: tuple[tuple[str, object], ...] = ()
    threads: int | None = None  # preview CPU threads per render (None: all cores); the output does not depend on it

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> RenderSettings:
        kept = {k: v for k, v in vars(args).items() if k not in _NOT_SETTINGS}
        return cls("depth" if args.depth is not None else "disparity", tuple(sorted(kept.items())))

    def get(self, name: str):
        return dict(self.args)[name]

    def with_values(self, **values) -> RenderSettings:
        """The same settings with some arguments replaced (a sweep's frame)."""
        d = dict(self.args)
        d.update(values)
        return replace(self, args=tuple(sorted(d.items())))

    def namespace(self, image: str, map_path: str, output: str) -> argparse.Namespace:
        ns = argparse.Namespace(**dict(self.args), image=image, output=output, quiet=True, stats=False, debug=False,
                                threads=self.threads)
        ns.disparity, ns.depth = (None, map_path) if self.kind == "depth" else (map_path, None)
        return ns

    def fingerprint(self) -> str:
        """What makes two renders of the same inputs the same (the device and threads are not part of it)."""
        d = {k: v for k, v in self.args if k != "device"}
        d["kind"] = self.kind
        return hashlib.sha256(json.dumps(d, sort_keys=True, default=str).encode()).hexdigest()[:16]


@dataclass(frozen=True)
class RenderTask:
    image: str
    map: str
    output: str
    settings: RenderSettings = field(default_factory=RenderSettings)


def render_file(task: RenderTask) -> dict:
    """Render one photo to ``task.output`` (written atomically) with the single-file render of the CLI; a pure
    function of the inputs and settings."""
    from .render_job import render_one

    return render_one(task.settings.namespace(task.image, task.map, task.output))


# --------------------------------------------------------------------------- the batch


def sweep_values(args: argparse.Namespace) -> tuple[str | None, tuple[float, ...]]:
    """The swept parameter (``focus``, ``blur`` or None) and its values."""
    f, b = isinstance(args.focus, tuple), isinstance(args.blur, tuple)
    if f and b:
        raise InputError("sweep one of --focus or --blur, not both")
    if not (f or b):
        return None, ()
    name = "focus" if f else "blur"
    values = args.focus if f else args.blur  # parse_sweep read -0 as 0: one name, one render
    if len(set(values)) != len(values):
        raise InputError(f"--{name}: the values repeat ({', '.join(map(number_text, values))})"[:300])
    # every value is checked as a single one is, before any frame is written (not frame by frame, half a stack later)
    from ..lens import MAX_K_PX

    for i, v in enumerate(values):
        if name == "focus" and not 0.0 <= v <= 1.0:
            raise InputError(f"--focus: expected every value of the sweep in [0, 1] (1 = nearest), got {number_text(v)} "
                             f"(value {i + 1} of {len(values)})")
        if name == "blur" and not 0.0 <= v <= MAX_K_PX:
            raise InputError(f"--blur: expected every value of the sweep as K in [0, {MAX_K_PX:g}], got {number_text(v)} "
                             f"(value {i + 1} of {len(values)})")
    return name, values


def _settings(args: argparse.Namespace) -> RenderSettings:
    if args.max_layers is not None and args.max_layers < 1:
        raise InputError(f"--max-layers: expected >= 1, got {args.max_layers}")
    if args.depth_model:
        raise InputError("--depth-model: one photo at a time (render each, or save their maps with --save-depth "
                         "and batch with --disparity)")
    return RenderSettings.from_args(args)


FRAME_DECIMALS = {"focus": 3, "blur": 0}
"""The fewest decimals in a sweep frame's name (``p_focus_0.100.png``, ``p_blur_4.png``)."""
_MOST_DECIMALS = 20


def _shown_decimals(v: float) -> int:
    """The decimals ``%g`` shows of ``v`` (six significant digits, ``2.5`` -> 1, ``24`` -> 0, ``1e-05`` -> 5)."""
    from decimal import Decimal

    return max(0, -Decimal(f"{v:.6g}").normalize().as_tuple().exponent)


def frame_labels(name: str, values: Sequence[float]) -> list[str]:
    """The value part of each frame's name: one rule for every sweep, distinct for distinct values.

    Every value of a sweep is written with the same number of decimals: the fewest that are at least
    ``FRAME_DECIMALS[name]``, show each value as ``%g`` does (six significant digits) and give each value its own
    name (``0.1,0.1004`` -> ``0.1000``, ``0.1004``); blur values then drop trailing zeros (``4``, ``2.5``,
    ``24.0000001``). Values that ``_MOST_DECIMALS`` decimals cannot tell apart are refused: two frames never share
    a file, whatever order the workers finish in.
    """
    first = max([FRAME_DECIMALS[name], *(_shown_decimals(v) for v in values)])
    for decimals in range(min(first, _MOST_DECIMALS), _MOST_DECIMALS + 1):
        labels = [f"{v:.{decimals}f}" for v in values]
        if name == "blur" and decimals:
            labels = [t.rstrip("0").rstrip(".") for t in labels]
        if len(set(labels)) == len(labels):
            return labels
    i = next(i for i, t in enumerate(labels) if labels.count(t) > 1)
    j = labels.index(labels[i], i + 1)
    raise InputError(f"--{name}: the values {values[i]!r} and {values[j]!r} of the sweep are too close to tell "
                     f"apart in the frames' file names (they differ after {_MOST_DECIMALS} decimals)")


def frame_caption(name: str, label: str, done: dict | None = None) -> str:
    """What a sweep frame shows in its corner with ``--gif-labels``: ``focus 0.600`` (``, 2.4 m`` for metric depth,
    when the render said it) or ``blur K 12 px``."""
    if name == "blur":
        return f"blur K {label} px"
    metres = done.get("focus_m") if done else None
    return f"focus {label}" + (f", {metres:.3g} m" if metres is not None and math.isfinite(metres) else "")


def _captions(name: str, frames: list[Path], frame_label: dict[str, str], results: dict) -> list[str]:
    """The captions of a sweep's frames: with metres only when every frame was rendered in this run (a resumed run
    skips the frames already written, whose distances it does not know: one GIF must not mix the two)."""
    done = [results.get(str(f)) for f in frames]
    every = all(d is not None for d in done)
    return [frame_caption(name, frame_label[str(f)], d if every else None) for f, d in zip(frames, done)]


def _caption(im, text: str):
    """``text`` drawn small (Pillow's built-in bitmap font) on a dark box in the frame's top-left corner."""
    from PIL import ImageDraw, ImageFont

    draw = ImageDraw.Draw(im)
    font = ImageFont.load_default()
    x0, y0, x1, y1 = draw.textbbox((4, 3), text, font=font)
    draw.rectangle((x0 - 3, y0 - 2, x1 + 3, y1 + 2), fill=(0, 0, 0))
    draw.text((4, 3), text, fill=(255, 255, 255), font=font)
    return im


def _gif(frames: Sequence[Path], path: Path, width: int, fps: float, captions: Sequence[str] | None = None) -> Path:
    """An animated preview of a focal stack (8-bit sRGB, ``width`` px wide; each frame's caption drawn small in
    its corner when ``captions`` are given), written atomically."""
    import numpy as np
    from PIL import Image

    from ..colour import linear_to_srgb
    from ..output.atomic import atomic_write
    from ..photo.read import read_image

    images = []
    for f in frames:
        rgb = np.clip(linear_to_srgb(np.clip(read_image(f)[..., :3], 0.0, 1.0)), 0.0, 1.0)
        im = Image.fromarray(np.round(rgb * 255.0).astype(np.uint8))
        if im.width > width:
            im = im.resize((width, max(1, round(im.height * width / im.width))), Image.Resampling.LANCZOS)
        if captions is not None:
            im = _caption(im, captions[len(images)])
        images.append(im)
    duration = max(20, round(1000.0 / fps))

    def encode(tmp: str) -> None:
        images[0].save(tmp, format="GIF", save_all=True, append_images=images[1:], duration=duration, loop=0)

    return atomic_write(path, encode)


def _stamp(path: str) -> tuple[int, int] | None:
    """The file's identity now (inode, mtime in ns), or None: an atomic write replaces both."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    return st.st_ino, st.st_mtime_ns


def photo_line(image: str, done: dict) -> str:
    """One batch line per photo: the file, the focus (disparity, how chosen, metres) and the blur (amount, K)."""
    metres = "" if done.get("focus_m") is None else f", {done['focus_m']:.3g} m"
    blur = (f"amount {done['amount']:g} (K = {done['k_px']:.1f} px)" if done.get("amount") is not None
            else f"K = {done['k_px']:.1f} px")
    return (f"{Path(image).name} -> {Path(done['output']).name}: focus d_f = {done['focus_disparity']:.3f} "
            f"({done.get('focus', '?')}{metres}), {blur}")


def _state(out: Path, fingerprint: str, outputs: Sequence[str], overwrite: bool) -> None:
    """Refuse to skip outputs made with other settings (or not by a batch); then record this batch's settings."""
    from ..output.atomic import atomic_write

    state = out / STATE_FILE
    existing = [o for o in outputs if (out / o).exists()]
    if existing and not overwrite:
        try:
            old = json.loads(state.read_text()).get("settings")
        except (OSError, ValueError, AttributeError):
            old = None
        if old is None:
            raise InputError(f"{out / existing[0]}: exists and was not written by a bokehray batch; pass "
                             "--overwrite to replace it, or choose another output folder")
        if old != fingerprint:
            raise InputError(f"{out}: holds {len(existing)} renders made with other settings ({existing[0]}, ...); "
                             "pass --overwrite to render them again, or choose another output folder")
    text = json.dumps({"settings": fingerprint, "outputs": len(outputs)}, indent=2) + "\n"
    atomic_write(state, lambda tmp: Path(tmp).write_text(text))


RENDER_BASE_BYTES = 300 << 20
"""A render process's memory before its photo: Python, NumPy, Warp, OpenCV (``benchmarks/results/memory--*.json``:
the preview's peak at 1.5, 6 and 12 MP lies on ``300 MB + 94 B/px``)."""

RENDER_BYTES_PER_PX = 110
"""A ``bokehray render``'s peak per pixel of its photo beyond :data:`RENDER_BASE_BYTES`: the preview's 94 B/px plus
decoding, highlights and grain (measured: 1.64 GB peak RSS for a 12 MP JPEG at the defaults)."""

MEMORY_SHARE = 0.8
"""The share of the available memory a batch's workers may plan to hold together."""


def render_peak_bytes(pixels: int) -> int:
    """The peak memory of one render of a photo of ``pixels`` pixels (the model above)."""
    return RENDER_BASE_BYTES + RENDER_BYTES_PER_PX * int(pixels)


def fit_workers(requested: int, pixels: int, available: int) -> int:
    """As many of the ``requested`` workers as can each render a photo of ``pixels`` pixels at once within
    ``MEMORY_SHARE`` of the ``available`` memory (at least one)."""
    return max(1, min(requested, int(MEMORY_SHARE * available) // render_peak_bytes(pixels)))


def _workers_for(args: argparse.Namespace, todo: Sequence[RenderTask]) -> int | None:
    """``--workers`` (None: the executor's default), lowered so that the local workers fit the memory available
    now, from the largest photo's header; said on stderr when lowered."""
    if args.executor == "dask" or not todo:
        return args.workers
    from .._memory import available_bytes
    from ..photo.read import read_size

    largest = 0
    for image in {t.image for t in todo}:
        with contextlib.suppress(InputError):  # an unreadable photo fails as its render, reported there
            h, w = read_size(image)
            largest = max(largest, h * w)
    requested = min(args.workers or os.cpu_count() or 1, len(todo))
    available = available_bytes()
    n = fit_workers(requested, largest, available)
    if n < requested and not args.quiet:
        print(f"workers: {n} instead of {requested}, to fit the memory available ({available / 2**30:.1f} GB; a "
              f"{largest / 1e6:.1f} MP render peaks at about {render_peak_bytes(largest) / 2**30:.1f} GB)",
              file=sys.stderr)
    return n if n < requested else args.workers


def run_batch(args: argparse.Namespace) -> int:  # noqa: C901
    """``bokehray render`` with many inputs or a sweep: plan, skip what is done, run, summarise."""
    from .._quiet import progress_bar
    from ..executor import check_executor_args, make_executor
    from ..output.atomic import remove_stale_outputs

    # the batch's own options, None when not given (a single render refuses them given: cli._check_single_render)
    suffix = args.map_suffix or ""
    gif_width = GIF_WIDTH if args.gif_width is None else args.gif_width
    fps = FPS if args.fps is None else args.fps
    check_executor_args(args.executor, workers=args.workers, scheduler=args.scheduler)  # before any file is made
    if "/" in suffix:
        raise InputError(f"--map-suffix: expected a file-name suffix, got {suffix!r}")
    if gif_width < 8:
        raise InputError(f"--gif-width: expected at least 8 px, got {gif_width}")
    if not 0.1 <= fps <= 50:
        raise InputError(f"--fps: expected 0.1..50, got {fps:g}")
    if args.stats:
        raise InputError("--stats: single-file renders only (a batch prints its throughput at the end)")
    name, values = sweep_values(args)
    # the flags' contradictions and values, as a single render checks them: once, before the folder is made (not
    # once per render in the summary); a swept value is checked by sweep_values, its first one stands for it here
    from .render_job import check_render_flags

    check_render_flags(argparse.Namespace(**{**vars(args), **({name: values[0]} if name else {})}))
    labels = frame_labels(name, values) if name is not None else []
    settings = _settings(args)
    out = Path(args.output)
    if out.exists() and not out.is_dir():
        raise InputError(f"{out}: many outputs go into a folder, got an existing file")
    if out.suffix.lower() in (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".exr") and not out.exists():
        raise InputError(f"{out}: many outputs go into a folder, got a file name; give a folder with -o")
    pairs = find_pairs(args.image, args.disparity or args.depth, kind=settings.kind, suffix=suffix)
    if not pairs:
        raise InputError(f"{args.image}: no images found ({', '.join(IMAGE_EXTS)})")
    ext = "." + args.output_format if args.output_format else None

    failures: list[tuple[str, str]] = []
    tasks: list[RenderTask] = []
    stacks: dict[Path, list[Path]] = {}  # gif -> frames
    frame_label: dict[str, str] = {}  # frame -> its value as named
    seen: dict[str, Path] = {}
    for pair in pairs:
        if pair.map is None:
            failures.append((str(pair.image), pair.problem or "no map"))
            continue
        suffix = ext or (".jpg" if pair.image.suffix.lower() == ".jpeg" else pair.image.suffix.lower())
        suffix = ".tif" if suffix == ".tiff" else suffix
        stem = pair.image.stem
        if stem in seen:
            failures.append((str(pair.image), f"its output name is that of {seen[stem]}; rename one of them"))
            continue
        seen[stem] = pair.image
        if name is None:
            tasks.append(RenderTask(str(pair.image), str(pair.map), str(out / f"{stem}{suffix}"), settings))
            continue
        frames = []
        for v, label in zip(values, labels):
            frame = out / f"{stem}_{name}_{label}{suffix}"
            frames.append(frame)
            frame_label[str(frame)] = label
            tasks.append(RenderTask(str(pair.image), str(pair.map), str(frame), settings.with_values(**{name: v})))
        stacks[out / f"{stem}_{name}_sweep.gif"] = frames
    from ..output.write import CLI_NAMES, check_output_path

    for t in {Path(t.output).suffix: t for t in tasks}.values():  # one output of each format
        check_output_path(t.output, bit_depth=settings.get("bit_depth"), half=settings.get("half"), names=CLI_NAMES)
    out.mkdir(parents=True, exist_ok=True)
    names = [Path(t.output).name for t in tasks] + [g.name for g in stacks]
    _state(out, settings.fingerprint(), names, args.overwrite)
    todo = [t for t in tasks if args.overwrite or not Path(t.output).exists()]
    skipped = len(tasks) - len(todo)
    quiet = args.quiet
    done_pixels, t0 = 0, time.perf_counter()
    failed_outputs: set[str] = set()
    before = {t.output: _stamp(t.output) for t in todo}  # what is there now (with --overwrite: the old renders)
    results: dict[str, dict] = {}  # output -> what its render said (the GIF's captions take the metres from it)
    try:
        if todo:
            with make_executor(args.executor, workers=_workers_for(args, todo), scheduler=args.scheduler,
                               tasks=len(todo)) as ex:
                if ex.workers > 1 and not args.scheduler:  # the workers share this machine's cores
                    share = max(1, (os.cpu_count() or 1) // ex.workers)
                    todo = [replace(t, settings=replace(t.settings, threads=share)) for t in todo]
                if not quiet:
                    print(f"rendering {len(todo)} of {len(tasks)} outputs on {ex.describe()}"
                          + (f" ({skipped} done already)" if skipped else ""), file=sys.stderr)
                # a bar on a terminal only: in a log, the photo lines below say the progress
                with progress_bar(len(todo), "render", "img", enabled=not quiet) as bar:
                    for o in ex.map(render_file, todo):
                        if o.ok:
                            done_pixels += o.value["pixels"]
                            results[todo[o.index].output] = o.value
                            if not quiet:  # what each photo got: its focus and blur, one line
                                bar.write(photo_line(todo[o.index].image, o.value), file=sys.stdout)
                        else:
                            failures.append((todo[o.index].image, o.error))
                            failed_outputs.add(todo[o.index].output)
                        bar.update()
    except KeyboardInterrupt as e:
        # counted on disk once the executor has closed: the renders in flight when the signal came finished
        # (atomically) while it shut down, and they are done as much as those whose outcome was seen
        complete = sum(1 for t in todo if _stamp(t.output) not in (None, before[t.output]))
        what, code = (e.said, e.exit_code) if isinstance(e, Terminated) else ("interrupted", EXIT_INTERRUPTED)
        with contextlib.suppress(OSError):  # after SIGHUP the terminal may be gone
            print(f"bokehray: {what} after {complete} of {len(todo)} renders; they are complete in {out}, "
                  "run the same command again to render the rest", file=sys.stderr)
        return code
    finally:
        remove_stale_outputs(out, names)
    wall = time.perf_counter() - t0
    gifs = 0
    for gif, frames in stacks.items():
        if any(str(f) in failed_outputs for f in frames):
            continue
        if args.overwrite or args.gif_labels or not gif.exists() or any(f.stat().st_mtime > gif.stat().st_mtime for f in frames):
            try:
                captions = _captions(name, frames, frame_label, results) if args.gif_labels else None
                _gif(frames, gif, gif_width, fps, captions)
                gifs += 1
            except Exception as e:  # noqa: BLE001 - a preview that fails is reported like a render
                failures.append((str(gif), f"{type(e).__name__}: {e}".splitlines()[0]))
    rendered = len(todo) - len(failed_outputs)
    if not quiet:
        rate = f", {done_pixels / 1e6 / wall:.2f} MP/s" if rendered and wall > 0 else ""
        print(f"{rendered} rendered, {skipped} skipped (complete), {len(failures)} failed"
              + (f", {gifs} sweep previews" if stacks else "") + f" -> {out} ({wall:.1f} s{rate})")
    if failures:
        print(f"bokehray: {len(failures)} input{'s' if len(failures) != 1 else ''} failed:", file=sys.stderr)
        for path, why in failures:
            print(f"  {path}: {why}", file=sys.stderr)
        return 2
    return 0
