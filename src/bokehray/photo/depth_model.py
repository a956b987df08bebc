"""A disparity map for a photo that has none: a monocular depth model from a local checkpoint folder.

Reads the Hugging Face ``transformers`` layouts of **Depth Anything (V1/V2)** (``model_type`` ``depth_anything``)
and **DPT** (``dpt``, e.g. DPT-Hybrid/MiDaS) from a folder (``config.json``, ``model.safetensors``, optionally
``preprocessor_config.json``). Nothing is ever downloaded: the folder is opened with ``local_files_only`` and the
hub switched off. torch and transformers are imported only here, only when a model is used (the ``depth``
extra).

Polarity (docs/usage.md, tested): relative models (Depth Anything's ``depth_estimation_type = "relative"``,
DPT) predict *relative inverse depth*, near = large, which is disparity up to scale and shift: it is normalised
by its 0.5th..99.5th percentiles (``bokehray.photo.depth.normalize_relative``). Metric models
(``depth_estimation_type = "metric"``) predict metres, near = small: they go through ``1/z`` with the min-max
normalisation of metric depth (``bokehray.lens.disparity_from_depth``).

A folder is refused in one line naming its file, before anything large is built: a ``preprocessor_config.json``
of the wrong types or an input side beyond ``MAX_INPUT_SIDE``; a config.json whose declared transformer is larger
than the weights' headers say they hold (:func:`_check_declared_size`), or whose model at that input would not fit
the memory available; and, once loaded, weights that do not fit the model the config describes (missing,
unexpected or reshaped tensors: transformers would leave those layers random).
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..errors import InputError

__all__ = ["SUPPORTED", "estimate_disparity", "input_size", "model_kind", "tiny_configs"]

SUPPORTED = {"depth_anything": "Depth Anything (V1/V2)", "dpt": "DPT"}
_IMAGENET_MEAN = (0.485, 0.456, 0.406)
_IMAGENET_STD = (0.229, 0.224, 0.225)


def _config(folder: Path) -> dict:
    if not folder.exists():
        raise InputError(f"{folder}: --depth-model expects a local checkpoint folder, and there is none there "
                         "(nothing is downloaded: see README, 'A photo without a depth map')")
    if not folder.is_dir():
        raise InputError(f"{folder}: --depth-model expects a checkpoint folder (config.json, model.safetensors), "
                         "got a file")
    cfg_path = folder / "config.json"
    try:
        cfg = json.loads(cfg_path.read_text())
    except FileNotFoundError:
        raise InputError(f"{folder}: no config.json: not a transformers checkpoint folder") from None
    except (OSError, ValueError) as e:
        raise InputError(f"{cfg_path}: cannot read it as JSON ({e})") from None
    kind = cfg.get("model_type") if isinstance(cfg, dict) else None
    if kind not in SUPPORTED:
        names = ", ".join(f"{k} ({v})" for k, v in SUPPORTED.items())
        raise InputError(f"{cfg_path}: model_type {kind!r} is not a supported depth model; expected one of {names}")
    if cfg.get("max_depth") is not None:  # a metric model's range (the library's own check is a multi-line message)
        _positive_int(cfg["max_depth"], cfg_path, "max_depth")
    return cfg


def model_kind(cfg: dict) -> str:
    """``"metric"`` (metres, near = small) or ``"relative"`` (relative inverse depth, near = large)."""
    return "metric" if cfg.get("depth_estimation_type") == "metric" else "relative"


def _multiple(x: float, m: int) -> int:
    return max(m, int(round(x / m)) * m)


MAX_INPUT_SIDE = 8192
"""Largest network input side a checkpoint's ``preprocessor_config.json`` may declare: 16 times the models' own
(518 for Depth Anything, 384 for DPT); beyond it only memory and hours are spent."""


def _positive_int(value: object, where: Path, key: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise InputError(f"{where}: {key}: expected a positive integer, got {value!r}")
    return value


def _read_preprocessor(path: Path) -> dict:
    """The JSON object in ``path``, or one line naming the file."""
    try:
        pre = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise InputError(f"{path}: cannot read it as JSON ({e})") from None
    if not isinstance(pre, dict):
        raise InputError(f"{path}: expected a JSON object (the image processor's settings), got a "
                         f"{type(pre).__name__}")
    return pre


def _check_size(pre: dict, path: Path) -> None:
    """``size`` (one positive integer, or ``height``/``width``) and ``ensure_multiple_of``."""
    size = pre.get("size")
    if isinstance(size, dict):
        for key in ("height", "width"):
            if key in size:
                _positive_int(size[key], path, f"size.{key}")
    elif size is not None:
        _positive_int(size, path, "size")
    if pre.get("ensure_multiple_of") is not None:
        _positive_int(pre["ensure_multiple_of"], path, "ensure_multiple_of")


def _check_mean_std(pre: dict, path: Path) -> None:
    """``image_mean`` and ``image_std``: three finite numbers each, the standard deviations > 0."""
    for key, positive in (("image_mean", False), ("image_std", True)):
        v = pre.get(key)
        if v is None:
            continue
        ok = (isinstance(v, list) and len(v) == 3
              and all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in v)
              and (not positive or all(x > 0 for x in v)))
        if not ok:
            what = "three finite numbers > 0 (one per RGB channel)" if positive else "three finite numbers (RGB)"
            raise InputError(f"{path}: {key}: expected {what}, got {v!r}")


def _preprocessor(folder: Path) -> dict:
    """``preprocessor_config.json`` (if any), each key this module reads checked for its type."""
    path = folder / "preprocessor_config.json"
    if not path.exists():
        return {}
    pre = _read_preprocessor(path)
    _check_size(pre, path)
    if "keep_aspect_ratio" in pre and not isinstance(pre["keep_aspect_ratio"], bool):
        raise InputError(f"{path}: keep_aspect_ratio: expected true or false, got {pre['keep_aspect_ratio']!r}")
    _check_mean_std(pre, path)
    return pre


def input_size(folder: Path, cfg: dict, h: int, w: int) -> tuple[int, int, tuple, tuple]:
    """The network input size, as transformers' image processors of these models compute it, and mean/std."""
    pre = _preprocessor(folder)
    if cfg["model_type"] == "depth_anything":
        default, keep, mult = 518, True, 14
    else:  # DPT: a square input of the configured image size
        default, keep, mult = _positive_int(cfg.get("image_size", 384) or 384, folder / "config.json",
                                            "image_size"), False, 1
    size = pre.get("size", default)
    th, tw = (size.get("height", default), size.get("width", default)) if isinstance(size, dict) else (size, size)
    if max(th, tw) > MAX_INPUT_SIDE:
        raise InputError(f"{folder / 'preprocessor_config.json'}: size: expected at most {MAX_INPUT_SIDE} px a side "
                         f"(the models were trained at 518 and 384), got {tw} x {th}")
    keep = bool(pre.get("keep_aspect_ratio", keep))
    mult = int(pre.get("ensure_multiple_of", mult) or 1)
    if cfg["model_type"] == "dpt":
        keep = False  # the DPT backbone reshapes its tokens to a square grid
    if keep:  # scale the side whose scale is closer to 1 by the same factor as the other (DPTImageProcessor)
        sh, sw = th / h, tw / w
        if abs(1 - sw) < abs(1 - sh):
            sh = sw
        else:
            sw = sh
        th, tw = _multiple(h * sh, mult), _multiple(w * sw, mult)
    else:
        th, tw = _multiple(th, mult), _multiple(tw, mult)
    mean = tuple(pre.get("image_mean", _IMAGENET_MEAN))
    std = tuple(pre.get("image_std", _IMAGENET_STD))
    return int(th), int(tw), mean, std


def _stored_parameters(folder: Path) -> int | None:
    """How many parameters the folder's safetensors files hold, from their headers alone (nothing is loaded);
    None without safetensors files (a ``pytorch_model.bin`` is counted only by loading it)."""
    files = sorted(folder.glob("*.safetensors"))
    if not files:
        return None
    total = 0
    for f in files:
        try:
            with open(f, "rb") as fh:
                n = int.from_bytes(fh.read(8), "little")
                if not 2 <= n <= 100 << 20:
                    raise ValueError(f"a header of {n} bytes")
                header = json.loads(fh.read(n))
            for name, t in header.items():
                if name != "__metadata__":
                    total += math.prod(int(v) for v in t["shape"])
        except (OSError, ValueError, TypeError, KeyError, AttributeError) as e:
            raise InputError(f"{f}: cannot read it as safetensors ({e})") from None
    return total


def _declared(cfg: dict, folder: Path) -> dict:
    """The transformer's shape as config.json declares it (the backbone's for Depth Anything), each value checked."""
    where = folder / "config.json"
    shape = cfg.get("backbone_config") if cfg["model_type"] == "depth_anything" else cfg
    if shape is None:
        return {}
    if not isinstance(shape, dict):
        raise InputError(f"{where}: backbone_config: expected a JSON object, got {type(shape).__name__}")
    out = {k: _positive_int(shape[k], where, k) for k in ("hidden_size", "num_hidden_layers", "num_attention_heads",
                                                           "patch_size") if k in shape}
    if "patch_size" not in out and "patch_size" in cfg:
        out["patch_size"] = _positive_int(cfg["patch_size"], where, "patch_size")
    for k in ("fusion_hidden_size", "head_hidden_size"):
        if k in cfg:
            out[k] = _positive_int(cfg[k], where, k)
    return out


def _check_declared_size(folder: Path, cfg: dict, th: int, tw: int) -> None:
    """Refuse, from config.json and the weights' headers, a model that cannot be what the folder holds or cannot
    fit in memory, before transformers builds it (100 000 declared layers take minutes to build, then fail)."""
    from .._memory import available_bytes
    from ..errors import ResourceError

    shape = _declared(cfg, folder)
    h, layers = shape.get("hidden_size"), shape.get("num_hidden_layers")
    if h is None or layers is None:
        return  # transformers' defaults: the published sizes
    at_least = layers * 4 * h * h  # the attention's four h x h projections per layer: a lower bound of the model
    stored = _stored_parameters(folder)
    if stored is not None and at_least > 1.05 * stored:
        raise InputError(f"{folder / 'config.json'}: declares {layers} layers {h} wide (at least {at_least:,} "
                         f"parameters), but the weights in {folder} hold {stored:,}: the config does not fit them")
    patch = shape.get("patch_size", 14)
    tokens = (th // patch + 1) * (tw // patch + 1)
    heads = shape.get("num_attention_heads", 1)
    full_res = shape.get("fusion_hidden_size", 256) + 2 * shape.get("head_hidden_size", 32)
    need = 4 * (at_least + 24 * tokens * h + tokens * tokens * heads + th * tw * full_res)  # float32 bytes
    have = available_bytes()
    if need > have:
        raise ResourceError(f"{folder}: the model at an input of {tw} x {th} px needs about {need >> 20:,} MB, but "
                            f"only {have >> 20:,} MB of memory is available (a smaller size in "
                            "preprocessor_config.json needs less)")


def _check_loading(folder: Path, cfg: dict, loading: dict) -> None:
    """Refuse a checkpoint whose weights do not fit the model its config.json describes: transformers then
    leaves the missing layers random (and says so only in a log line) and would render from noise."""
    problems = []
    for key, what in (("missing_keys", "missing"), ("unexpected_keys", "unexpected"),
                      ("mismatched_keys", "of another shape")):
        names = sorted(str(k if isinstance(k, str) else k[0]) for k in loading.get(key) or ())
        if names:
            problems.append(f"{len(names)} {what} ({', '.join(names[:2])}{', ...' if len(names) > 2 else ''})")
    problems += [str(m).splitlines()[0] for m in loading.get("error_msgs") or ()]
    if problems:
        raise InputError(f"{folder}: the weights do not fit the {SUPPORTED[cfg['model_type']]} model its config.json "
                         f"describes: {'; '.join(problems)} (is model_type right?)")


def predict(model, image: np.ndarray, size: tuple[int, int], mean, std, device: str = "cpu") -> np.ndarray:
    """The model's raw prediction for a linear ``H x W x 3`` photo, resized back to ``H x W`` (float64)."""
    import torch

    from ..colour import linear_to_srgb

    h, w = image.shape[:2]
    srgb = np.clip(linear_to_srgb(np.clip(image[..., :3], 0.0, 1.0)), 0.0, 1.0)
    with torch.no_grad():
        x = torch.from_numpy(np.ascontiguousarray(srgb.transpose(2, 0, 1)))[None].to(device)
        x = torch.nn.functional.interpolate(x, size=size, mode="bicubic", align_corners=False, antialias=True)
        x = (x - torch.tensor(mean, device=device).view(1, 3, 1, 1)) / torch.tensor(std, device=device).view(1, 3, 1, 1)
        pred = model(pixel_values=x).predicted_depth
        pred = torch.nn.functional.interpolate(pred[:, None], size=(h, w), mode="bilinear", align_corners=False)
        return pred[0, 0].float().cpu().numpy().astype(np.float64)


def estimate_disparity(
    image: np.ndarray,
    folder: str | os.PathLike[str],
    *,
    device: str = "cpu",
    progress: Callable[[float], None] | None = None,
) -> tuple[np.ndarray, dict]:
    """Disparity in [0, 1] (1 = nearest, ``H x W`` float32) for a linear ``H x W x 3`` photo; and what was done.

    The photo is sRGB-encoded (the models were trained on display images), resized and normalised as the
    checkpoint's image processor would, run once, and the prediction resized back bilinearly to ``H x W``
    before it is turned into disparity (see the module's docstring for the polarity).
    """
    from ..lens import disparity_from_depth
    from .depth import normalize_relative

    folder = Path(folder)
    cfg = _config(folder)
    try:
        import torch  # noqa: F401 - the check that the extra is installed
        import transformers
    except ImportError as e:
        raise InputError(f"--depth-model needs torch and transformers: pip install 'bokehray[depth]' ({e})") from None
    os.environ.setdefault("HF_HUB_OFFLINE", "1")  # never reach for the hub, whatever the folder's config says
    transformers.logging.set_verbosity_error()  # one line per problem, no load report
    transformers.utils.logging.disable_progress_bar()  # bokehray's own bar covers the stage
    img = np.asarray(image, np.float32)
    if img.ndim != 3 or img.shape[2] < 3:
        raise InputError(f"depth model: expected an H x W x 3 photo, got shape {img.shape}")
    h, w = img.shape[:2]
    th, tw, mean, std = input_size(folder, cfg, h, w)
    cls = (transformers.DepthAnythingForDepthEstimation if cfg["model_type"] == "depth_anything"
           else transformers.DPTForDepthEstimation)
    _check_declared_size(folder, cfg, th, tw)
    try:
        model, loading = cls.from_pretrained(str(folder), local_files_only=True, output_loading_info=True)
        model = model.eval().to(device)
    except Exception as e:  # noqa: BLE001 - transformers raises OSError, ValueError, RuntimeError, safetensors errors
        why = " ".join(str(e).split())[:300]  # one line: the library's messages span several
        raise InputError(f"{folder}: cannot load the {SUPPORTED[cfg['model_type']]} checkpoint ({why})") from None
    _check_loading(folder, cfg, loading)
    if progress:
        progress(0.3)
    pred = predict(model, img, (th, tw), mean, std, device)
    if progress:
        progress(0.8)
    if not np.isfinite(pred).all():
        raise InputError(f"{folder}: the model predicted NaN or Inf for this photo")
    kind = model_kind(cfg)
    if kind == "metric":
        disparity, norm = disparity_from_depth(pred, source=str(folder))
        what = f"metric depth {norm.z_near_m:.3g}..{norm.z_far_m:.3g} m -> 1/z"
    else:
        disparity = normalize_relative(pred, source=str(folder))
        what = "relative inverse depth, normalised by its 0.5th..99.5th percentiles"
    if progress:
        progress(1.0)
    info = {"model": SUPPORTED[cfg["model_type"]], "kind": kind, "what": what, "input_size": (th, tw),
            "max_prediction": float(pred.max()) if math.isfinite(float(pred.max())) else None}
    return disparity, info


def tiny_configs():
    """``(DepthAnythingConfig, DPTConfig)`` of the tiny random checkpoints the tests and the soak build themselves
    (a few hundred thousand parameters, a 56 / 64 px input): the architectures this module loads, never real weights."""
    import transformers

    backbone = transformers.Dinov2Config(hidden_size=32, num_hidden_layers=4, num_attention_heads=2,
                                         intermediate_size=64, patch_size=14, image_size=56,
                                         out_features=["stage1", "stage2", "stage3", "stage4"],
                                         reshape_hidden_states=False)
    da = transformers.DepthAnythingConfig(backbone_config=backbone, reassemble_hidden_size=32,
                                          neck_hidden_sizes=[8, 16, 32, 32], fusion_hidden_size=16, head_hidden_size=8)
    dpt = transformers.DPTConfig(hidden_size=32, num_hidden_layers=4, num_attention_heads=2, intermediate_size=64,
                                 image_size=64, patch_size=16, backbone_out_indices=[0, 1, 2, 3],
                                 neck_hidden_sizes=[8, 16, 32, 32], fusion_hidden_size=16, use_auxiliary_head=False)
    return da, dpt
