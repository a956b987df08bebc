"""What every quality level takes and returns: the render context and the level's entry in the registry."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ..lens import Aperture, BlurParams
from ..options import LayerOptions, MemoryOptions
from ..stats import RenderStats

if TYPE_CHECKING:
    from ..scene import SoftEdges  # bokehray.scene imports Warp: reading the registry must not

__all__ = ["Level", "RenderContext"]

Progress = Callable[[int, int], None]


@dataclass(frozen=True, slots=True, eq=False)
class RenderContext:
    """One render's inputs, validated by ``bokehray.pipeline``: what travels together through a level.

    ``image`` is H x W x 3 float32 scene-linear, ``disparity`` H x W in [0, 1], ``signed_coc`` the capped
    ``K (d - d_f)`` (``bokehray.scene.cap_coc``); ``options`` is the level's own options type. ``soft``: the
    mixed pixels at depth edges split into near and far parts (``bokehray.scene.SoftEdges``, on ``signed_coc``);
    None: one depth a pixel.

    ``disposable``: nothing after the level reads the context's pixels (the pipeline sets it when the input has no
    alpha to render and no refiner runs), so the level may drop the context's references to them once it has read
    them (:meth:`release_pixels`). Dropping a reference never writes to an array nor frees one a caller still
    holds: a caller's arrays are freed early only when the caller handed them over
    (``bokehray.pipeline.render_handed_over``).
    """

    image: np.ndarray
    disparity: np.ndarray
    signed_coc: np.ndarray
    blur: BlurParams
    aperture: Aperture
    layers: LayerOptions
    memory: MemoryOptions
    options: object
    device: str
    progress: Progress | None = None
    soft: SoftEdges | None = None
    disposable: bool = False

    @property
    def shape(self) -> tuple[int, int]:
        return self.signed_coc.shape

    def with_image(self, image: np.ndarray) -> RenderContext:
        """The same render of other colour (an RGBA render's alpha goes through the level as grey), one depth a
        pixel (the split pixels' colours are the photo's)."""
        return RenderContext(image, self.disparity, self.signed_coc, self.blur, self.aperture, self.layers,
                             self.memory, self.options, self.device, None)

    def release_pixels(self) -> None:
        """Drop the context's references to its whole-image arrays (image, disparity, signed CoC, soft edges) when it
        is ``disposable``; else nothing. The preview calls it once the scene is split (it reads them no more): at
        12 MP the photo, its disparity and the CoC are 240 MB, otherwise held through the layers."""
        if self.disposable:
            for name in ("image", "disparity", "signed_coc", "soft"):
                object.__setattr__(self, name, None)  # frozen for the level's readers; this is the one writer


@dataclass(frozen=True, slots=True)
class Level:
    """A rung of the quality ladder: its name, what it is, its options type, its renderer and its memory.

    ``render(ctx)`` returns (H x W x 3 float32, stats); ``whole_image_bytes()`` is what it holds per pixel of the
    whole image whatever the tiling (a render is refused from its shape when that alone exceeds the budget). Both
    import the level's module on first use (``bokehray.levels``), so that reading the registry
    (``bokehray --help``) imports no renderer and no Warp.
    """

    name: str
    summary: str
    options_type: type
    render: Callable[[RenderContext], tuple[np.ndarray, RenderStats]]
    whole_image_bytes: Callable[[], int]
    not_for_photos: str = ""  # why the command line and the page do not offer it for photos ("": they do)
