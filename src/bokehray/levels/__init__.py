"""The quality ladder: every level renders the same layered scene (``bokehray.scene``).

- ``preview`` (:mod:`.preview`): occlusion-aware row-span scatter of the layers, fast.
- ``raytrace`` (:mod:`.raytrace`): the same layers ray traced through the aperture by deterministic quadrature;
  the exact renderer of layer stacks (``bokehray.raytrace_layers``, ``bokehray synth``); on photos slower than and
  slightly below the preview (docs/raytracer.md).
- the refine hook (:mod:`.refine`): the optional neural pass over a preview render.

``LEVELS`` is the registry the API, the CLI and the benchmark read their choices from. Each entry holds the
level's renderer as a function that imports its module when it first renders (reading the registry imports no
renderer and no Warp).
"""

from __future__ import annotations

import numpy as np

from ..options import PreviewOptions, RaytraceOptions
from ..stats import RenderStats
from .base import Level, RenderContext

__all__ = ["LEVELS", "PHOTO_QUALITIES", "Level", "RenderContext", "check_photo_quality", "get_level"]



def _render_preview(ctx: RenderContext) -> tuple[np.ndarray, RenderStats]:
    from .preview import render_preview

    return render_preview(ctx)


def _preview_bytes() -> int:
    from .preview import WHOLE_IMAGE_B

    return WHOLE_IMAGE_B


def _render_raytrace(ctx: RenderContext) -> tuple[np.ndarray, RenderStats]:
    from .raytrace import render_raytrace

    return render_raytrace(ctx)


def _raytrace_bytes() -> int:
    from .raytrace import WHOLE_IMAGE_B

    return WHOLE_IMAGE_B


LEVELS: dict[str, Level] = {
    level.name: level
    for level in (
        Level("preview", "layered occlusion-aware scatter, fast, and the more accurate level for photos",
              PreviewOptions, _render_preview, _preview_bytes),
        Level("raytrace", "the same layers ray traced through the aperture: the exact renderer of true layer stacks "
              "(raytrace_layers, bokehray synth); on photos 30x slower than the preview and measured below it "
              "(docs/raytracer.md), so the command line and the page do not offer it for photos",
              RaytraceOptions, _render_raytrace, _raytrace_bytes,
              not_for_photos="on photos the ray tracer is slower than the preview and not more accurate "
              "(docs/raytracer.md); the preview (the default) is the exact level for photos, and the ray tracer "
              "renders layer stacks (bokehray synth, bokehray.raytrace_layers)"),
    )
}

PHOTO_QUALITIES = tuple(name for name, level in LEVELS.items() if not level.not_for_photos)
"""The levels the command line and the page offer for photos: a level is offered only where it beats the one below
on exact references (the ray tracer renders the same soft scene as the preview and scores below it on the
path-traced dev set at about 30 times its time)."""


def check_photo_quality(name: object, flag: str = "--quality") -> str:
    """``name`` if it is a level offered for photos; else one line pointing to the preview."""
    from ..errors import InputError

    level = LEVELS.get(name) if isinstance(name, str) else None
    if level is not None and level.not_for_photos:
        raise InputError(f"{flag} {name}: {level.not_for_photos}")
    if not isinstance(name, str) or name not in PHOTO_QUALITIES:
        raise InputError(f"{flag}: expected one of {', '.join(PHOTO_QUALITIES)}, got {str(name)[:40]!r}")
    return name


def get_level(name: str) -> Level:
    """The level called ``name``; InputError naming the choices otherwise."""
    from ..errors import InputError

    level = LEVELS.get(name) if isinstance(name, str) else None
    if level is None:
        raise InputError(f"quality: expected one of {', '.join(LEVELS)}, got {name!r}")
    return level
