"""bokehray: physics-first lens blur for one photo and its disparity map.

Quick start::

    import bokehray as br
    image = br.read_image("photo.png")            # H x W x 3 scene-linear float32
    disparity = br.read_disparity("disp.png")     # H x W in [0, 1], 1 = nearest
    out = br.render(image, disparity, br.BlurParams(k_px=24.0, focus_disparity=0.8))
    br.write_image("bokeh.png", out)

Layout (docs/architecture.md), in the order a render goes: ``photo`` reads photos and depth maps as people have
them (formats, orientation, colour profiles, depth conventions, default blur and focus); ``scene`` builds the
layered scene from them; ``levels`` holds the quality ladder (``preview``, ``raytrace``, the ``refine`` hook) over
it; ``tiling`` bounds memory for every level; ``output`` writes the result atomically; ``pipeline`` is the public
entry point. Beside them: ``data`` (synthetic pairs, datasets, metrics) and ``app`` (the command line, the refocus
page, the benchmark).

The names below are resolved lazily (PEP 562): ``import bokehray`` costs a few milliseconds and imports
neither Warp nor the image codecs; the first use of ``br.render`` (or any other export) imports its module.
"""

from __future__ import annotations

import importlib
import importlib.util
from typing import TYPE_CHECKING, Any

from ._quiet import quiet_warp_on_import

quiet_warp_on_import()  # whoever imports Warp later: no banner or per-module load lines

__version__ = "0.1.0"

_EXPORTS: dict[str, str] = {
    "datasets": "data.datasets",
    "BokehrayError": "errors", "InputError": "errors", "NumericalError": "errors", "OutputError": "errors",
    "ResourceError": "errors",
    "read_depth": "photo.depth", "read_disparity": "photo.read", "read_image": "photo.read",
    "keep_grain": "photo.grain",
    "write_disparity": "output.write", "write_image": "output.write",
    "Aperture": "lens", "BlurParams": "lens", "DepthNormalization": "lens", "ThinLens": "lens",
    "depth_from_disparity": "lens", "disparity_from_depth": "lens",
    "Layer": "levels.raytrace", "raytrace_layers": "levels.raytrace",
    "LayerOptions": "options", "MemoryOptions": "options", "PreviewOptions": "options", "RaytraceOptions": "options",
    "QUALITIES": "pipeline", "boost_highlights": "pipeline", "focus_at": "pipeline", "render": "pipeline",
    "render_with_stats": "pipeline",
    "PreviewStats": "stats", "RaytraceStats": "stats", "RenderStats": "stats",
}  # fmt: skip
"""Public name -> the submodule that defines it (or the submodule itself, named by its last part)."""

__all__ = [
    "QUALITIES",
    "Aperture",
    "BlurParams",
    "BokehrayError",
    "DepthNormalization",
    "InputError",
    "Layer",
    "LayerOptions",
    "MemoryOptions",
    "NumericalError",
    "OutputError",
    "PreviewOptions",
    "PreviewStats",
    "RaytraceOptions",
    "RaytraceStats",
    "RenderStats",
    "ResourceError",
    "ThinLens",
    "__version__",
    "boost_highlights",
    "datasets",
    "depth_from_disparity",
    "disparity_from_depth",
    "focus_at",
    "keep_grain",
    "raytrace_layers",
    "read_depth",
    "read_disparity",
    "read_image",
    "render",
    "render_with_stats",
    "write_disparity",
    "write_image",
]


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        if not name.startswith("_") and importlib.util.find_spec(f"{__name__}.{name}") is not None:
            return importlib.import_module(f".{name}", __name__)  # a submodule: br.photo, br.scene, ...
        raise AttributeError(f"module 'bokehray' has no attribute {name!r}")
    value = importlib.import_module(f".{module}", __name__)
    if module.rpartition(".")[2] != name:  # a name in a module (else the module itself: br.datasets)
        value = getattr(value, name)
    globals()[name] = value  # resolved once: later lookups do not come back here
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))


if TYPE_CHECKING:  # what type checkers and IDEs see: the eager imports
    # (__all__ above must list exactly the names of _EXPORTS; tests/cli_io/test_startup.py checks it)
    from .data import datasets
    from .errors import BokehrayError, InputError, NumericalError, OutputError, ResourceError
    from .lens import Aperture, BlurParams, DepthNormalization, ThinLens, depth_from_disparity, disparity_from_depth
    from .levels.raytrace import Layer, raytrace_layers
    from .options import LayerOptions, MemoryOptions, PreviewOptions, RaytraceOptions
    from .output.write import write_disparity, write_image
    from .photo.depth import read_depth
    from .photo.grain import keep_grain
    from .photo.read import read_disparity, read_image
    from .pipeline import QUALITIES, boost_highlights, focus_at, render, render_with_stats
    from .stats import PreviewStats, RaytraceStats, RenderStats
