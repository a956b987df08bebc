"""NVIDIA Warp kernels of bokehray: pure compute, no IO, no validation, no policy.

The launchers that allocate, validate and choose devices live in ``bokehray``
(``bokehray.scene`` builds the layers, ``bokehray.levels`` renders them); this
package imports neither ``bokehray`` nor torch. Each kernel here has a float64
NumPy oracle in ``tests/reference/`` and a test comparing them.
"""

from .aperture import chord as chord
from .scatter import (
    composite_kernel as composite_kernel,
    finalize_kernel as finalize_kernel,
    halve_mean_kernel as halve_mean_kernel,
    radiance_mean_kernel as radiance_mean_kernel,
    route_cells_kernel as route_cells_kernel,
    scatter_clusters_kernel as scatter_clusters_kernel,
    prefix_rows_kernel as prefix_rows_kernel,
    resolve_levels_kernel as resolve_levels_kernel,
    scatter_kernel as scatter_kernel,
    MAX_LEVELS as MAX_LEVELS,
)
from .raytrace import raytrace_kernel as raytrace_kernel
from .matting import matting_band_kernel as matting_band_kernel
from .soft import near_sources_kernel as near_sources_kernel
from .fill import (
    FILL_GATE_SLOPE as FILL_GATE_SLOPE,
    fill_sources_kernel as fill_sources_kernel,
    pull_kernel as pull_kernel,
    push_kernel as push_kernel,
    column_distance_kernel as column_distance_kernel,
    layer_sources_kernel as layer_sources_kernel,
    row_distance_kernel as row_distance_kernel,
)

__all__ = [
    "FILL_GATE_SLOPE",
    "MAX_LEVELS",
    "chord",
    "column_distance_kernel",
    "row_distance_kernel",
    "composite_kernel",
    "fill_sources_kernel",
    "finalize_kernel",
    "halve_mean_kernel",
    "layer_sources_kernel",
    "near_sources_kernel",
    "prefix_rows_kernel",
    "pull_kernel",
    "raytrace_kernel",
    "push_kernel",
    "radiance_mean_kernel",
    "resolve_levels_kernel",
    "route_cells_kernel",
    "scatter_clusters_kernel",
    "scatter_kernel",
]
