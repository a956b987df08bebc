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
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..errors import InputError

__all__ = ["SUPPORTED", "estimate_disparity", "model_kind"]

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
    return cfg


def model_kind(cfg: dict) -> str:
    """``"metric"`` (metres, near = small) or ``"relative"`` (relative inverse depth, near = large)."""
    return "metric" if cfg.get("depth_estimation_type") == "metric" else "relative"


def _multiple(x: float, m: int) -> int:
    return max(m, int(round(x / m)) * m)


def _input_size(folder: Path, cfg: dict, h: int, w: int) -> tuple[int, int, tuple, tuple]:
    """The network input size, as transformers' image processors of these models compute it, and mean/std."""
    pre: dict = {}
    if (folder / "preprocessor_config.json").exists():
        try:
            pre = json.loads((folder / "preprocessor_config.json").read_text())
        except (OSError, ValueError) as e:
            raise InputError(f"{folder / 'preprocessor_config.json'}: cannot read it as JSON ({e})") from None
    if cfg["model_type"] == "depth_anything":
        default, keep, mult = 518, True, 14
    else:  # DPT: a square input of the configured image size
        default, keep, mult = int(cfg.get("image_size", 384) or 384), False, 1
    size = pre.get("size", default)
    th, tw = (size.get("height", default), size.get("width", default)) if isinstance(size, dict) else (size, size)
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
    th, tw, mean, std = _input_size(folder, cfg, h, w)
    cls = (transformers.DepthAnythingForDepthEstimation if cfg["model_type"] == "depth_anything"
           else transformers.DPTForDepthEstimation)
    try:
        model = cls.from_pretrained(str(folder), local_files_only=True).eval().to(device)
    except Exception as e:  # noqa: BLE001 - transformers raises OSError, ValueError, RuntimeError, safetensors errors
        raise InputError(f"{folder}: cannot load the {SUPPORTED[cfg['model_type']]} checkpoint ({e})") from None
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
