"""bokehray's neural refiner (torch): PISA attention, the one-step diffusion wrapper, the small shipped model.

Dependency direction is one way: ``bokehray_kernels`` <- ``bokehray`` <- ``bokehray_refiner``. ``bokehray``
imports this package only lazily, behind ``render(refine=...)`` / ``--refine``. Modules:

* ``attention``: windowed, energy-conserving PISA attention and its dense reference;
* ``masks``: PISA masks per attention grid (Warp kernels, handed to torch without a copy);
* ``processor``: the diffusers attention processor (``install_pisa``);
* ``onestep``: the one-step SDXL wrapper (``load_one_step``) and ``tiles`` for tiled inference;
* ``model``, ``data``, ``train``, ``refine``: the shipped CPU refiner, its training and ``refine()``;
* ``testing``: a tiny SDXL-layout checkpoint written locally, for tests and install checks.

See docs/refiner.md.
"""
