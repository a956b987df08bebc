"""Benchmark datasets: BokehMe's Blur Lens Benchmark (BLB) layout and EBB!-style photo pairs.

BLB layout (also what our synthetic generator writes)::

    root/<scene>/image.exr          all-in-focus, linear RGB
    root/<scene>/depth.exr          1 / disparity (depth >= 1; +Inf for d = 0)
    root/<scene>/bokeh_<k>_<f>.exr  render for blur level k and focus index f (0-based)
    root/<scene>/info.json          {"blur_parameters": [K, ...], "focus_distances": [z_f, ...], ...}

so ``K * (1/depth - 1/z_f)`` is the signed CoC radius in pixels. Unknown info fields and
extra files (PNG previews, ...) are ignored. Datasets are lazy: ``__init__`` reads only
directory listings and ``info.json``; pixels are read in ``__getitem__``.
"""

from __future__ import annotations

import copy
import json
import math
import os
import re
import shutil
import tempfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError, OutputError
from ..output.write import write_disparity, write_image
from ..photo.depth import read_depth
from ..photo.read import read_disparity, read_image
from ..validate import check_disparity, check_image

__all__ = ["FAR_DEPTH", "BLBDataset", "EBBDataset", "Sample", "natural_key", "perturb_disparity", "write_blb_scene"]

FAR_DEPTH = 1e9
"""Finite depth / focus distance written for disparity 0 (OpenEXR and JSON hold no +Inf here)."""

_BOKEH = re.compile(r"^bokeh_(\d+)_(\d+)\.exr$")
_IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".exr")
_DISPARITY_EXTS = (".png", ".tif", ".tiff", ".exr", ".npy")


@dataclass(frozen=True, eq=False)
class Sample:
    """One benchmark item. ``eq=False``: samples hold arrays, so they compare by identity."""

    name: str  #: e.g. ``"scene_0003/bokeh_2_1"`` or the EBB file stem
    image: np.ndarray  #: H x W x 3 linear float32, all-in-focus
    disparity: np.ndarray  #: H x W float32 in [0, 1], 1 = nearest
    target: np.ndarray | None  #: H x W x 3 linear float32 wide-aperture image, None if absent
    k_px: float | None  #: blur parameter K when known (BLB), else None
    focus_disparity: float | None  #: d_f when known (BLB), else None
    meta: dict  #: the scene's info.json (BLB) or {}, plus ``"paths"`` of the source files


def natural_key(name: str) -> list[Any]:
    """Sort key ordering embedded numbers numerically ("2" before "10")."""
    return [(0, int(t), "") if t.isdigit() else (1, 0, t) for t in re.split(r"(\d+)", name) if t]


def _rgb(a: np.ndarray, path: Path, shape: tuple[int, ...] | None = None) -> np.ndarray:
    a = a[..., :3]  # an alpha channel, if any, is dropped
    if shape is not None and a.shape[:2] != shape[:2]:
        got = f"got {a.shape[1]} x {a.shape[0]}"
        raise InputError(f"{path}: expected {shape[1]} x {shape[0]} pixels like the input, {got}")
    return a


def _floats(info: Mapping[str, Any], key: str, where: str) -> list[float]:
    vals = info.get(key)
    if not isinstance(vals, (list, tuple)) or not vals or any(isinstance(v, (bool, str)) for v in vals):
        raise InputError(f"{where}: expected {key!r} as a non-empty list of numbers, got {vals!r}")
    try:
        return [float(v) for v in vals]
    except (TypeError, ValueError):
        raise InputError(f"{where}: expected {key!r} as a list of numbers, got {vals!r}") from None


def _json_default(o: Any) -> Any:
    if isinstance(o, (np.generic, np.ndarray)):
        return o.tolist()
    raise TypeError(f"{type(o).__name__} is not JSON serialisable")


# --------------------------------------------------------------------------- writer


def write_blb_scene(
    folder: str | os.PathLike[str],
    image: np.ndarray,
    disparity: np.ndarray,
    renders: Sequence[Mapping[str, Any]],
    info: Mapping[str, Any],
    *,
    previews: bool = True,
    overwrite: bool = False,
) -> Path:
    """Write one BLB scene atomically: all files appear at once or none do.

    Writes ``image.exr`` and ``bokeh_<k>_<f>.exr`` (float32), ``depth.exr`` = 1 / disparity
    (float32; disparity 0 is written as :data:`FAR_DEPTH` = 1e9, not +Inf), ``info.json`` (a copy
    of ``info`` with ``focus_distances`` = 1 / ``focus_disparities`` added, d_f = 0 written as 1e9,
    replacing any given value) and, if ``previews``, 8-bit sRGB ``image.png``/``bokeh_<k>_<f>.png``
    and a 16-bit ``disparity.png``. Everything goes to a hidden temporary sibling folder that is
    renamed onto ``folder`` at the end; on any error it is removed and ``folder`` is untouched.

    Args:
        folder: Scene folder to create (parents are created).
        image: H x W x 3 finite linear float all-in-focus image.
        disparity: H x W finite disparity in [0, 1].
        renders: Dicts ``{"k_index": int, "f_index": int, "image": H x W x 3 float}``.
        info: JSON-serialisable mapping with ``blur_parameters`` (K >= 0 per level) and
            ``focus_disparities`` (d_f in [0, 1] per focus index); other fields are kept.
        previews: Also write the PNG previews.
        overwrite: Replace an existing non-empty ``folder``.

    Returns:
        The scene folder.

    Raises:
        InputError: Bad shape, dtype, NaN/Inf, range, index, duplicate render, non-JSON info,
            or ``folder`` exists (not empty) without ``overwrite``.
    """
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise InputError(f"{folder}: expected a scene folder, got an existing file")
    if folder.is_dir() and any(folder.iterdir()) and not overwrite:
        raise InputError(f"{folder}: folder already exists and is not empty; pass overwrite=True to replace it")
    img = _check_image(image, "image")
    h, w = img.shape[:2]
    d = np.asarray(disparity)
    if d.shape != (h, w) or d.dtype.kind not in "fiu":
        raise InputError(f"disparity: expected a real {h} x {w} (H x W) array like the image, got shape {d.shape}")
    d = check_disparity(d, (h, w))
    ks, dfs, text = _checked_info(info)
    outs = _checked_renders(renders, len(ks), len(dfs), (h, w))

    folder.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=folder.parent, prefix=f".{folder.name}.tmp-{os.getpid()}-"))
    try:
        _write_scene_files(tmp, img, d, outs, text, previews)
        _swap_in(tmp, folder)
    except OutputError as e:  # name the scene's folder, not the hidden one it is written in (removed below)
        shutil.rmtree(tmp, ignore_errors=True)
        raise OutputError(str(e).replace(str(tmp), str(folder))) from None
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return folder


def _checked_info(info: Any) -> tuple[list[float], list[float], str]:
    """``info``'s blur levels and focus disparities, checked, and its JSON with ``focus_distances`` added."""
    if not isinstance(info, Mapping):
        raise InputError(f"info: expected a dict, got {type(info).__name__}")
    ks = _floats(info, "blur_parameters", "info")
    dfs = _floats(info, "focus_disparities", "info")
    if not all(math.isfinite(k) and k >= 0.0 for k in ks):
        raise InputError(f"info: expected finite blur_parameters K >= 0, got {ks}")
    if not all(0.0 <= f <= 1.0 for f in dfs):
        raise InputError(f"info: expected focus_disparities in [0, 1], got {dfs}")
    meta = {**info, "focus_distances": [1.0 / f if f > 0 else FAR_DEPTH for f in dfs]}
    try:
        text = json.dumps(meta, indent=2, allow_nan=False, default=_json_default)
    except (TypeError, ValueError) as exc:
        raise InputError(f"info: expected JSON-serialisable finite values, got an error: {exc}") from None
    return ks, dfs, text


def _checked_renders(renders: Sequence[Mapping[str, Any]], n_k: int, n_f: int,
                     hw: tuple[int, int]) -> dict[tuple[int, int], np.ndarray]:
    """The renders by (k_index, f_index), each index, duplicate and image checked."""
    outs: dict[tuple[int, int], np.ndarray] = {}
    for i, r in enumerate(renders):
        if not isinstance(r, Mapping):
            raise InputError(f"renders[{i}]: expected a dict with k_index, f_index and image, got {type(r).__name__}")
        k, f = r.get("k_index"), r.get("f_index")
        if not all(isinstance(v, (int, np.integer)) and not isinstance(v, bool) for v in (k, f)):
            raise InputError(f"renders[{i}]: expected integer k_index and f_index, got {k!r}, {f!r}")
        if not (0 <= k < n_k and 0 <= f < n_f):
            raise InputError(f"renders[{i}]: k_index {k} / f_index {f} out of range for {n_k} blur levels "
                             f"and {n_f} focus disparities")  # fmt: skip
        if (int(k), int(f)) in outs:
            raise InputError(f"renders[{i}]: duplicate render for k_index {k}, f_index {f}")
        outs[int(k), int(f)] = _check_image(r.get("image"), f"renders[{i}] image", hw)
    return outs


def _write_scene_files(tmp: Path, img: np.ndarray, d: np.ndarray, outs: dict[tuple[int, int], np.ndarray],
                       text: str, previews: bool) -> None:
    """Every file of the scene into the temporary folder ``tmp`` (made readable as a folder mkdir would make)."""
    umask = os.umask(0o022)
    os.umask(umask)
    os.chmod(tmp, 0o777 & ~umask)  # mkdtemp makes 0700
    write_image(tmp / "image.exr", img)
    with np.errstate(divide="ignore"):
        write_image(tmp / "depth.exr", np.where(d > 0, 1.0 / d.astype(np.float64), FAR_DEPTH).astype(np.float32))
    if previews:
        write_image(tmp / "image.png", img)
        write_disparity(tmp / "disparity.png", d)
    for (k, f), out in sorted(outs.items()):
        write_image(tmp / f"bokeh_{k}_{f}.exr", out)
        if previews:
            write_image(tmp / f"bokeh_{k}_{f}.png", out)
    (tmp / "info.json").write_text(text + "\n")


def _check_image(a: Any, what: str, hw: tuple[int, int] | None = None) -> np.ndarray:
    if a is None:
        raise InputError(f"{what}: expected an H x W x 3 array, got None")
    img = check_image(a, what, channels=(3,))
    if hw is not None and img.shape[:2] != hw:
        raise InputError(f"{what}: expected a {hw[0]} x {hw[1]} x 3 array like the image, got shape {img.shape}")
    return img


def _swap_in(tmp: Path, folder: Path) -> None:
    """Rename ``tmp`` onto ``folder``; an existing folder is moved aside first and restored on failure."""
    if not folder.exists():
        os.replace(tmp, folder)
        return
    old = folder.parent / f".{folder.name}.old-{tmp.name.rsplit('-', 1)[-1]}"
    os.replace(folder, old)
    try:
        os.replace(tmp, folder)
    except BaseException:
        os.replace(old, folder)
        raise
    shutil.rmtree(old, ignore_errors=True)


# --------------------------------------------------------------------------- readers


class BLBDataset(Sequence[Sample]):
    """One :class:`Sample` per ``(scene, k, f)`` bokeh file present, scenes in natural name order.

    ``disparity = 1 / depth`` clipped to [0, 1] (depth +Inf gives 0), ``K = blur_parameters[k]``,
    ``d_f = 1 / focus_distances[f]`` (clipped to [0, 1] within 1e-6). Hidden folders (names
    starting with ``.``, e.g. an unfinished :func:`write_blb_scene`) are skipped.

    Args:
        root: Folder holding one sub-folder per scene.
        level: Keep only blur level ``k == level`` (the BokehMe paper evaluates level 5).
        focus: Keep only focus index ``f == focus``.

    Raises:
        InputError: ``root`` missing or holds no scene; an unreadable ``info.json`` or one
            without valid ``blur_parameters``/``focus_distances``; a bokeh index out of range;
            no bokeh file matches ``level``/``focus``.
    """

    def __init__(self, root: str | os.PathLike[str], *, level: int | None = None, focus: int | None = None):
        self.root = _folder(root, "BLB root")
        scenes = sorted((p for p in self.root.iterdir() if p.is_dir() and not p.name.startswith(".")
                         and (p / "info.json").is_file()), key=lambda p: natural_key(p.name))  # fmt: skip
        if not scenes:
            raise InputError(f"no BLB scenes under {self.root}: expected <root>/<scene>/info.json")
        self._items: list[tuple[Path, int, int, dict, float, float]] = []
        for scene in scenes:
            info = _read_info(scene / "info.json")
            ks = _floats(info, "blur_parameters", str(scene / "info.json"))
            zs = _floats(info, "focus_distances", str(scene / "info.json"))
            if not all(math.isfinite(k) and k >= 0.0 for k in ks):
                raise InputError(f"{scene / 'info.json'}: expected finite blur_parameters K >= 0, got {ks}")
            if not all(z > 0 for z in zs) or any(1.0 / z > 1.0 + 1e-6 for z in zs):
                raise InputError(f"{scene / 'info.json'}: expected focus_distances >= 1 (disparity <= 1), got {zs}")
            found = sorted((int(m[1]), int(m[2])) for p in scene.iterdir() if (m := _BOKEH.match(p.name)))
            for k, f in found:
                if k >= len(ks) or f >= len(zs):
                    raise InputError(f"{scene}/bokeh_{k}_{f}.exr: index out of range for {len(ks)} blur_parameters "
                                     f"and {len(zs)} focus_distances in info.json")  # fmt: skip
                if (level is None or k == level) and (focus is None or f == focus):
                    self._items.append((scene, k, f, info, ks[k], min(1.0, 1.0 / zs[f])))
        if not self._items:
            raise InputError(f"no bokeh_<k>_<f>.exr files under {self.root} (level={level}, focus={focus})")

    def __len__(self) -> int:
        return len(self._items)

    def __getitem__(self, i: int) -> Sample:  # type: ignore[override]
        scene, k, f, info, k_px, d_f = self._items[_index(i, len(self))]
        paths = {"image": scene / "image.exr", "depth": scene / "depth.exr", "target": scene / f"bokeh_{k}_{f}.exr"}
        image = _rgb(read_image(paths["image"]), paths["image"])
        depth = read_depth(paths["depth"]).astype(np.float32)  # EXR floats: exact in float32
        if depth.shape != image.shape[:2]:
            raise InputError(f"{paths['depth']}: expected {image.shape[1]} x {image.shape[0]} pixels like image.exr, "
                             f"got {depth.shape[1]} x {depth.shape[0]}")  # fmt: skip
        if (depth <= 0).any():
            raise InputError(f"{paths['depth']}: expected depth > 0 (disparity = 1 / depth), got min {depth.min():g}")
        disparity = np.clip(1.0 / depth, 0.0, 1.0).astype(np.float32)
        target = _rgb(read_image(paths["target"]), paths["target"], image.shape)
        meta = copy.deepcopy(info) | {"paths": {n: str(p) for n, p in paths.items()}}
        return Sample(f"{scene.name}/bokeh_{k}_{f}", image, disparity, target, k_px, d_f, meta)


class EBBDataset(Sequence[Sample]):
    """EBB!/Val294-style real photo pairs: files paired by stem across three sub-folders.

    Inputs and targets may be any image format :func:`~bokehray.photo.read.read_image` reads; disparity
    maps PNG/TIFF/EXR/NPY (values must lie in [0, 1]). Stems are ordered naturally ("2" before
    "10"); stems present only in the target or disparity folder are ignored. ``k_px`` and
    ``focus_disparity`` are None (the benchmark searches them); ``meta`` holds the source paths.

    Raises:
        InputError: A folder is missing, holds no input, has two files with one stem, or an input
            stem lacks a target or disparity (first 5 listed); in ``__getitem__``, a disparity
            or target of another size than the input, or disparity outside [0, 1].
    """

    def __init__(self, root: str | os.PathLike[str], *, input_dir: str = "input", target_dir: str = "target",
                 disparity_dir: str = "disparity"):  # fmt: skip
        self.root = _folder(root, "EBB root")
        inputs = _by_stem(_folder(self.root / input_dir, "EBB input folder"), _IMAGE_EXTS)
        if not inputs:
            raise InputError(f"{self.root / input_dir}: expected input images ({', '.join(_IMAGE_EXTS)}), found none")
        targets = _by_stem(_folder(self.root / target_dir, "EBB target folder"), _IMAGE_EXTS)
        disps = _by_stem(_folder(self.root / disparity_dir, "EBB disparity folder"), _DISPARITY_EXTS)
        for what, found, sub in (("target", targets, target_dir), ("disparity", disps, disparity_dir)):
            missing = sorted(set(inputs) - set(found), key=natural_key)
            if missing:
                more = f" and {len(missing) - 5} more" if len(missing) > 5 else ""
                raise InputError(f"{self.root / sub}: expected a {what} for every input, missing stems "
                                 f"{', '.join(missing[:5])}{more}")  # fmt: skip
        self._items = [(s, inputs[s], targets[s], disps[s]) for s in sorted(inputs, key=natural_key)]

    def __len__(self) -> int:
        return len(self._items)

    def __getitem__(self, i: int) -> Sample:  # type: ignore[override]
        stem, p_in, p_tgt, p_d = self._items[_index(i, len(self))]
        image = _rgb(read_image(p_in), p_in)
        target = _rgb(read_image(p_tgt), p_tgt, image.shape)
        d = read_disparity(p_d)
        if d.shape != image.shape[:2]:
            raise InputError(f"{p_d}: expected {image.shape[1]} x {image.shape[0]} pixels like {p_in.name}, "
                             f"got {d.shape[1]} x {d.shape[0]} (the loader does not resize)")  # fmt: skip
        if d.min() < 0.0 or d.max() > 1.0:
            raise InputError(f"{p_d}: expected disparity in [0, 1], got range [{d.min():g}, {d.max():g}]")
        meta = {"paths": {"image": str(p_in), "target": str(p_tgt), "disparity": str(p_d)}}
        return Sample(stem, image, d, target, None, None, meta)


def _folder(path: str | os.PathLike[str], what: str) -> Path:
    p = Path(path)
    if not p.exists():
        raise InputError(f"{p}: {what} does not exist")
    if not p.is_dir():
        raise InputError(f"{p}: expected {what} to be a directory, got a file")
    return p


def _read_info(path: Path) -> dict:
    try:
        info = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise InputError(f"{path}: cannot read info.json: {exc}") from None
    if not isinstance(info, dict):
        raise InputError(f"{path}: expected a JSON object, got {type(info).__name__}")
    return info


def _by_stem(folder: Path, exts: tuple[str, ...]) -> dict[str, Path]:
    out: dict[str, Path] = {}
    for p in sorted(folder.iterdir()):
        if p.is_file() and p.suffix.lower() in exts and not p.name.startswith("."):
            if p.stem in out:
                raise InputError(f"{folder}: two files for stem {p.stem!r}: {out[p.stem].name} and {p.name}")
            out[p.stem] = p
    return out


def _index(i: int, n: int) -> int:
    if not isinstance(i, (int, np.integer)) or isinstance(i, bool):
        raise TypeError(f"dataset indices must be integers, got {type(i).__name__}")
    if not -n <= i < n:
        raise IndexError(f"index {i} out of range for {n} samples")
    return int(i) % n


def perturb_disparity(disparity: np.ndarray, radius: int) -> np.ndarray:
    """Grey erosion (``radius < 0``) or dilation (``> 0``) with a disc of ``|radius|`` px (paper fig. 7)."""
    from scipy import ndimage

    r = abs(int(radius))
    if r == 0:
        return disparity.copy()
    yy, xx = np.mgrid[-r:r + 1, -r:r + 1]
    disc = (xx * xx + yy * yy) <= r * r
    op = ndimage.grey_dilation if radius > 0 else ndimage.grey_erosion
    return op(disparity, footprint=disc, mode="nearest").astype(np.float32)
