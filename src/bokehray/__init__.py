"""bokehray: physics-first lens blur for one photo and its disparity map.

Quick start::

    import bokehray as br
    image = br.read_image("photo.png")            # H x W x 3 scene-linear float32
    disparity = br.read_disparity("disp.png")     # H x W in [0, 1], 1 = nearest
    out = br.render(image, disparity, br.BlurParams(k_px=24.0, focus_disparity=0.8))
    br.write_image("bokeh.png", out)

Layout (docs/architecture.md): ``scene`` builds the layered scene from a photo; ``levels`` holds the quality
ladder (``preview``, ``raytrace``, the ``refine`` hook) over it; ``tiling`` bounds memory for every level;
``pipeline`` is the public entry point.
"""

from __future__ import annotations

import warp as _wp

_wp.config.log_level = _wp.LOG_WARNING  # no banner or per-module load lines

from . import datasets  # noqa: E402
from .errors import BokehrayError, InputError, NumericalError, OutputError, ResourceError  # noqa: E402
from .io import read_depth, read_disparity, read_image, write_disparity, write_image  # noqa: E402
from .lens import (  # noqa: E402
    Aperture,
    BlurParams,
    DepthNormalization,
    ThinLens,
    depth_from_disparity,
    disparity_from_depth,
)
from .levels.raytrace import Layer, raytrace_layers  # noqa: E402
from .options import LayerOptions, MemoryOptions, PreviewOptions, RaytraceOptions  # noqa: E402
from .pipeline import QUALITIES, boost_highlights, focus_at, render, render_with_stats  # noqa: E402
from .stats import PreviewStats, RaytraceStats, RenderStats  # noqa: E402

__version__ = "0.1.0"

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
    "raytrace_layers",
    "read_depth",
    "read_disparity",
    "read_image",
    "render",
    "render_with_stats",
    "write_disparity",
    "write_image",
]
