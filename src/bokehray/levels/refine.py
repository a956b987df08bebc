"""The refine hook: the optional neural pass over a preview render (``bokehray_refiner``, docs/refiner.md).

Not a level of its own: it corrects the colour of a classical render near depth edges. torch is imported only
here, and only when asked, so ``bokehray`` never needs it otherwise.
"""

from __future__ import annotations

import os

import numpy as np

from ..errors import InputError
from ..lens import BlurParams

__all__ = ["REFINABLE", "check_refine_options", "refine_options", "refine_render"]

REFINABLE = ("preview",)
"""Levels whose renders the refiner corrects (it was trained on preview renders)."""


def _refiner_module():
    try:
        import bokehray_refiner.refine as module
    except ImportError as e:
        raise InputError(f"refine: the neural refiner needs its extra: pip install 'bokehray[refiner]' ({e})") from None
    return module


def refine_options(**overrides):
    """A ``bokehray_refiner.refine.RefineOptions`` with these fields changed (the command line's refine flags)."""
    return _refiner_module().RefineOptions(**overrides)


def check_refine_options(options) -> None:
    """``options`` is a ``bokehray_refiner.refine.RefineOptions`` (or None): checked before any work is done."""
    if options is not None and not isinstance(options, _refiner_module().RefineOptions):
        raise InputError(f"refine_options: expected a bokehray_refiner.refine.RefineOptions, got "
                         f"{type(options).__name__}")


def refine_render(image: np.ndarray, disparity: np.ndarray, blur: BlurParams, classical: np.ndarray | None,
                  weights: bool | str | os.PathLike, device: str, rerender=None, options=None):
    """Run the refiner on ``classical`` (the level's RGB render); returns (refined RGB, the refiner's stats).

    ``rerender(disparity)`` renders the level (again) on a corrected disparity (the refiner's depth correction);
    with ``classical=None`` the level has not rendered yet and renders once, after the correction. ``options``: a
    ``bokehray_refiner.refine.RefineOptions`` (None: its defaults).
    """
    module = _refiner_module()
    import torch

    options = module.RefineOptions() if options is None else options  # its type checked by the pipeline already

    tdev = "cuda" if device.startswith("cuda") and torch.cuda.is_available() else "cpu"
    if options.model is not None:
        if weights is not True:
            raise InputError("refine: a one-step model (refine_options.model) replaces the shipped network; give no "
                             "refiner weights with it")
        import bokehray_refiner.onestep as onestep

        return onestep.refine_one_step(image, disparity, blur, options.model, tdev, classical, rerender)
    model = module.load_refiner(None if weights is True else weights, tdev)
    return module.refine(image, disparity, blur, classical, model=model, rerender=rerender, options=options)
