"""The quality ladder: every level renders the same layered scene (``bokehray.scene``).

- ``preview`` (:mod:`.preview`): occlusion-aware row-span scatter of the layers, fast.
- ``raytrace`` (:mod:`.raytrace`): the same layers ray traced through the aperture by deterministic quadrature;
  the exact renderer of layer stacks (``bokehray.raytrace_layers``, ``bokehray synth``); on photos slower than and
  slightly below the preview (docs/raytracer.md).
- the refine hook (:mod:`.refine`): the optional neural pass over a preview render.

``LEVELS`` is the registry the API, the CLI and the benchmark read their choices from; a level's module is
imported when it first renders (reading the registry imports no renderer and no Warp).
"""

from __future__ import annotations

from ..options import PreviewOptions, RaytraceOptions
from .base import Level, RenderContext

__all__ = ["LEVELS", "Level", "RenderContext", "get_level"]

LEVELS: dict[str, Level] = {
    level.name: level
    for level in (
        Level("preview", "layered occlusion-aware scatter, fast, and the more accurate level for photos",
              PreviewOptions, f"{__name__}.preview", "render_preview"),
        Level("raytrace", "the same layers ray traced through the aperture: much slower and, on photos, measured "
              "slightly below the preview (docs/raytracer.md); the exact renderer of true layer stacks (synth)",
              RaytraceOptions, f"{__name__}.raytrace", "render_raytrace"),
    )
}


def get_level(name: str) -> Level:
    """The level called ``name``; InputError naming the choices otherwise."""
    from ..errors import InputError

    level = LEVELS.get(name) if isinstance(name, str) else None
    if level is None:
        raise InputError(f"quality: expected one of {', '.join(LEVELS)}, got {name!r}")
    return level
