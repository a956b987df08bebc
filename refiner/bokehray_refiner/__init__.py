"""bokehray's neural refiner (torch): PISA attention, the one-step diffusion wrapper, the small shipped model.

Dependency direction is one way: ``bokehray_kernels`` <- ``bokehray`` <- ``bokehray_refiner``. ``bokehray``
imports this package only lazily, behind ``render(refine=...)`` / ``--refine``. The run-time path (``render(refine=True)``) is at the top:

* ``refine``: ``refine()`` and ``RefineOptions``, the pass over a preview render;
* ``depthfix``: the colour-guided correction of misplaced depth edges, run first;
* ``gate``: where the network may act (the edge band, the confidence gate);
* ``edges``: the edge network, which places depth edges in the corrected map;
* ``model``, ``attention``, ``masks``, ``pisa``: the shipped residual network and its PISA attention;
* ``saved``, ``tiles``: loading checked weights, tiling.

``training/`` holds how the shipped weights are made (the residual and the edge networks' recipes);
``onestep/`` the one-step diffusion model with PISA attention, loaded from a local checkpoint folder.

See docs/refiner.md.
"""
