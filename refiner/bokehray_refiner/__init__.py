"""bokehray's neural refiner (torch): PISA attention, the one-step diffusion wrapper, the small shipped model.

Dependency direction is one way: ``bokehray_kernels`` <- ``bokehray`` <- ``bokehray_refiner``. ``bokehray``
imports this package only lazily, behind ``--refine``.
"""
