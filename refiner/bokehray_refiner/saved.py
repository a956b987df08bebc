"""Loading the package's own networks from safetensors: the config in the file's metadata, the weights checked
against it, loaded models cached per file, modification time and device (inference only: do not train them)."""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from functools import lru_cache
from pathlib import Path

from safetensors import SafetensorError, safe_open
from safetensors.torch import load_file
from torch import nn

from bokehray.errors import InputError

__all__ = ["load_saved"]


def load_saved(path: str | os.PathLike | None, default: Path, device: str, build: Callable[[dict], nn.Module], *,
               what: str, made_by: str, how_to_make: str, kind: str | None = None) -> nn.Module:
    """The network at ``path`` (``default`` when None), made by ``build(config)`` from the config in the file's
    metadata and loaded strictly. With ``kind``, the metadata must carry that marker. A missing file, or one that
    is not such weights, raises :class:`InputError` naming it: ``<path>: no <what> there (<how_to_make>)``, ``<path>:
    not <what> written by <made_by> (<why>)``. ``build`` is a module-level function (it is part of the cache key)."""
    path = Path(path) if path is not None else default
    if not path.is_file():
        raise InputError(f"{path}: no {what} there ({how_to_make})")
    return _load(str(path.resolve()), path.stat().st_mtime_ns, str(device), build, kind, f"not {what} written by {made_by}")


@lru_cache(maxsize=8)
def _load(path: str, mtime_ns: int, device: str, build: Callable[[dict], nn.Module], kind: str | None,
          not_ours: str) -> nn.Module:
    try:
        with safe_open(path, framework="pt") as f:
            meta = f.metadata() or {}
        if kind is not None and meta.get("kind") != kind:
            raise ValueError(f"no {kind} marker in the metadata")
        model = build(json.loads(meta["config"]))
        model.load_state_dict(load_file(path), strict=True)
    except (KeyError, ValueError, TypeError, RuntimeError, OSError, SafetensorError, InputError) as e:
        raise InputError(f"{path}: {not_ours} ({e})") from None
    return model.to(device).eval()
