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


    @property
    def shape(self) -> tuple[int, int]:
        return self.signed_coc.shape

    def with_image(self, image: np.ndarray) -> RenderContext:
        """The same render of other colour (an RGBA render's alpha goes through the level as grey), one depth a
        pixel (the split pixels' colours are the photo's)."""
        return RenderContext(image, self.disparity, self.signed_coc, self.blur, self.aperture, self.layers,
                             self.memory, self.options, self.device, None)


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
