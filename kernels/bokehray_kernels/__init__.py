"""NVIDIA Warp kernels of bokehray: pure compute, no IO, no validation, no policy.

The launchers that allocate, validate and choose devices live in ``bokehray``
(``bokehray.scene`` builds the layers, ``bokehray.levels`` renders them); this
package imports neither ``bokehray`` nor torch. Each kernel here has a float64
NumPy oracle in ``tests/reference/`` and a test comparing them.

By concern: ``aperture`` (the shape's chords), ``spans`` (a source's row-span deposits), ``pyramid`` (the radius
pyramid: scatter, prefix sums, resolve), ``routing`` (salient lights to level 0), ``composite`` (layers back to
front), ``interior`` (a layer's interior opaque), ``fill`` (layer sources and the pull-push fill), ``soft`` (the near parts of split pixels), ``matting``
(soft edges at depth edges), ``split`` (a band pixel's near and far parts from its estimate), ``ramps`` (a soft
map's ramps read as edges), ``thin`` (a soft map's thin structures: the frame's grid, the window regressions,
the hardening), ``vote`` (the depth correction's colour vote), ``raytrace`` (the layered ray tracer),
``pisa`` (the refiner's attention masks); ``support``, ``reduce`` and ``sampling`` hold what several of them share.
"""

from .aperture import chord as chord
from .composite import composite_kernel as composite_kernel
from .composite import finalize_kernel as finalize_kernel
from .fill import FILL_GATE_SLOPE as FILL_GATE_SLOPE
from .fill import PullPushLevel as PullPushLevel
from .fill import column_distance_kernel as column_distance_kernel
from .fill import fill_sources_kernel as fill_sources_kernel
from .fill import layer_pull_kernel as layer_pull_kernel
from .fill import layer_sources_kernel as layer_sources_kernel
from .fill import pull_kernel as pull_kernel
from .fill import push_kernel as push_kernel
from .fill import row_distance_kernel as row_distance_kernel
from .interior import boundary_kernel as boundary_kernel
from .interior import mark_split_kernel as mark_split_kernel
from .interior import opaque_flag_kernel as opaque_flag_kernel
from .interior import row_sweep_kernel as row_sweep_kernel
from .matting import matting_band_kernel as matting_band_kernel
from .pyramid import MAX_LEVELS as MAX_LEVELS
from .pyramid import Levels as Levels
from .pyramid import clear_support_kernel as clear_support_kernel
from .pyramid import prefix_rows_kernel as prefix_rows_kernel
from .pyramid import resolve_levels_kernel as resolve_levels_kernel
from .pyramid import scatter_kernel as scatter_kernel
from .pyramid import scatter_merged_kernel as scatter_merged_kernel
from .raytrace import raytrace_kernel as raytrace_kernel
from .routing import Routing as Routing
from .routing import Salience as Salience
from .routing import halve_mean_kernel as halve_mean_kernel
from .routing import radiance_mean_kernel as radiance_mean_kernel
from .routing import route_cells_kernel as route_cells_kernel
from .soft import near_sources_kernel as near_sources_kernel
from .spans import Shape as Shape
from .split import split_kernel as split_kernel
from .support import Support as Support

__all__ = [
    "FILL_GATE_SLOPE",
    "MAX_LEVELS",
    "Levels",
    "PullPushLevel",
    "Routing",
    "Salience",
    "Shape",
    "Support",
    "boundary_kernel",
    "chord",
    "clear_support_kernel",
    "column_distance_kernel",
    "composite_kernel",
    "fill_sources_kernel",
    "finalize_kernel",
    "halve_mean_kernel",
    "layer_pull_kernel",
    "layer_sources_kernel",
    "mark_split_kernel",
    "matting_band_kernel",
    "near_sources_kernel",
    "opaque_flag_kernel",
    "prefix_rows_kernel",
    "pull_kernel",
    "push_kernel",
    "radiance_mean_kernel",
    "raytrace_kernel",
    "resolve_levels_kernel",
    "route_cells_kernel",
    "row_distance_kernel",
    "row_sweep_kernel",
    "scatter_kernel",
    "scatter_merged_kernel",
    "split_kernel",
]
