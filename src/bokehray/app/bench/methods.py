"""The method registry of ``bokehray bench``: the one place that lists what is measured.

A :class:`Method` renders ``(image, disparity, K, d_f)`` into a scene-linear H x W x 3 image.
To add one, append an entry to :func:`registry`.

Every method is optional at run time: ``unavailable()`` returns a one-line reason (and the
method is skipped) or None. Peers are imported lazily, so ``bokehray`` never needs bpy, GEGL
or torch to import.
"""

from __future__ import annotations

import importlib.util
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

__all__ = ["Method", "registry", "select"]

Renderer = Callable[[np.ndarray, np.ndarray, float, float], np.ndarray]


@dataclass
class Method:
    """One measured renderer at one setting.

    Args:
        name: unique id, used on the command line (``--methods``) and in the results.
        family: ``"bokehray"`` or ``"peer"`` (the Pareto check asks whether a peer beats bokehray).
        description: one line for the docs and plots.
        make: builds the renderer (called once per run, so a peer can start its worker);
            the renderer may have ``close()``, ``last_peak_mb`` and ``last_inner_seconds``.
        unavailable: returns why the method cannot run here, or None.
        quick: part of ``bokehray bench --quick``.
        robustness: part of the erode/dilate robustness sweep.
    """

    name: str
    family: str
    description: str
    make: Callable[[], Renderer]
    unavailable: Callable[[], str | None] = field(default=lambda: None)
    quick: bool = False
    robustness: bool = True


def _bokehray(**render_kwargs) -> Callable[[], Renderer]:
    """A bokehray renderer: ``bokehray.render`` with a disc aperture and these keyword arguments."""

    def make() -> Renderer:
        from ...lens import Aperture, BlurParams
        from ...pipeline import render

        def run(image: np.ndarray, disparity: np.ndarray, k_px: float, focus_disparity: float) -> np.ndarray:
            return render(image, disparity, BlurParams(k_px, focus_disparity), Aperture(), **render_kwargs)

        return run

    return make


def _preview(level_radius_px: float | None = None, **layers) -> Callable[[], Renderer]:
    from ...options import LayerOptions, PreviewOptions

    preview = PreviewOptions() if level_radius_px is None else PreviewOptions(level_radius_px=level_radius_px)
    return _bokehray(options=preview, layers=LayerOptions(**layers))


def _raytrace(spp: int) -> Callable[[], Renderer]:
    from ...options import RaytraceOptions

    return _bokehray(quality="raytrace", options=RaytraceOptions(max_spp=spp))


def _needs_module(module: str, hint: str = "") -> Callable[[], str | None]:
    def check() -> str | None:
        return None if importlib.util.find_spec(module) is not None else f"module {module!r} not installed{hint}"

    return check


def _refiner_missing() -> str | None:
    if importlib.util.find_spec("bokehray_refiner") is None:
        return "module 'bokehray_refiner' not installed (pip install 'bokehray[refiner]')"
    from bokehray_refiner.refine import DEFAULT_WEIGHTS

    return None if DEFAULT_WEIGHTS.is_file() else f"no shipped refiner weights at {DEFAULT_WEIGHTS}"


def _peer(cls_name: str) -> tuple[Callable[[], Renderer], Callable[[], str | None]]:
    def cls():
        from . import peers

        return getattr(peers, cls_name)

    return (lambda: cls()()), (lambda: cls().unavailable())


def registry() -> list[Method]:
    """Every method the benchmark knows, bokehray first, in plotting order."""
    gegl_make, gegl_missing = _peer("GeglLensBlur")
    blender_make, blender_missing = _peer("BlenderDefocus")
    naive_make, naive_missing = _peer("NaiveScatter")
    return [
        Method("preview", "bokehray", "preview, defaults (8 layers, fill, pyramid r0 = 8 px)", _preview(), quick=True),
        Method("preview-fast", "bokehray", "preview, 4 layers", _preview(max_layers=4)),
        Method("preview-fine", "bokehray", "preview, 12 layers, pyramid r0 = 16 px",
               _preview(max_layers=12, level_radius_px=16.0)),
        Method("preview-nofill", "bokehray", "preview without hidden-region fill", _preview(fill=False),
               robustness=False),
        Method("preview+refine", "bokehray", "preview, then the shipped neural refiner near depth edges",
               _bokehray(refine=True), _refiner_missing),
        Method("raytrace-16", "bokehray", "raytrace, at most 16 rays per pixel", _raytrace(16), quick=True,
               robustness=False),
        Method("raytrace-64", "bokehray", "raytrace, at most 64 rays per pixel", _raytrace(64), robustness=False),
        Method("raytrace-128", "bokehray", "raytrace, at most 128 rays per pixel (default)", _raytrace(128)),
        Method("naive-scatter", "peer", "O(r^2) scatter, BokehMe classical-renderer style (numpy)", naive_make,
               naive_missing, quick=True),
        Method("gegl-lens-blur", "peer", "GEGL gegl:lens-blur, radius map as aux", gegl_make, gegl_missing,
               quick=True),
        Method("blender-defocus", "peer", "Blender compositor Defocus node, radius map as Z", blender_make,
               blender_missing, quick=True),
    ]


def select(names: str | None, quick: bool) -> list[Method]:
    """Methods by comma-separated ``names`` (all by default, or the quick subset)."""
    from ...errors import InputError

    methods = registry()
    if names:
        by_name = {m.name: m for m in methods}
        wanted = [n.strip() for n in names.split(",") if n.strip()]
        unknown = [n for n in wanted if n not in by_name]
        if unknown:
            raise InputError(f"--methods: unknown method {unknown[0]!r}; known: {', '.join(by_name)}")
        return [by_name[n] for n in wanted]
    return [m for m in methods if m.quick] if quick else methods
