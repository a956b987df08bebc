"""The one-step diffusion model with PISA attention: an SDXL-layout checkpoint from a local folder.

* ``pipeline``: ``load_one_step`` (a local diffusers-layout folder) and ``OneStepBokeh`` (the model; ``render``
  runs it tile by tile on a whole image);
* ``processor``: the diffusers attention processor that puts PISA attention in place (``install_pisa``);
* ``testing``: a tiny randomly initialised checkpoint written locally, for tests and install checks.

See docs/refiner.md, "A one-step diffusion checkpoint".
"""

from .pipeline import OneStepOptions, load_one_step, refine_one_step

__all__ = ["OneStepOptions", "load_one_step", "refine_one_step"]
