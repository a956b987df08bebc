"""Render options, grouped by the concern they belong to.

- :class:`LayerOptions` shape the layered scene built from the photo (``bokehray.scene``); both quality levels
  read them.
- :class:`MemoryOptions` bound one render's memory (``bokehray.tiling``); both levels read them.
- :class:`PreviewOptions` are read only by the preview (``bokehray.levels.preview``).
- :class:`RaytraceOptions` are read only by the ray tracer (``bokehray.levels.raytrace``).

A level is given only its own options type: ``render(..., quality="raytrace", options=PreviewOptions())`` is an
error, not a silently ignored knob. Defaults are what the benchmarks measure.
"""

from __future__ import annotations

from dataclasses import dataclass

from .errors import InputError
from .validate import check_int, check_number, shown

__all__ = ["MAX_TILE_PX", "LayerOptions", "MemoryOptions", "PreviewOptions", "RaytraceOptions"]


MAX_TILE_PX = 1024
"""Largest ``LayerOptions.tile_px``: the preview pads the frame by whole tiles and expands its tile grid to pixels, so
a tile far larger than any photo only costs memory (the default is 16)."""


@dataclass(frozen=True, slots=True)
class LayerOptions:
    """How the photo is cut into depth layers (``bokehray.scene``).

    Args:
        max_layers: most depth layers; more resolves more occlusion, costs more.
        max_layer_px: widest layer (in CoC pixels) on a gap-free depth range.
        min_layer_px: a CoC range narrower than this is one layer.
        fill: extend layers behind nearer ones by pull-push (see bokehray_kernels.fill).
        tile_px: side of the grid on which in-focus tiles are skipped and layers' boxes are planned, at most
            :data:`MAX_TILE_PX` (the frame is padded by whole tiles, so a huge one only exhausts memory).
        soft_edges: split the mixed pixels at depth edges into a near part (foreground colour with its coverage,
            at the near depth) and a far part (background colour, at the far depth) by matting
            (``bokehray.matting.split_mixed_pixels``), so that neither share takes the other's blur; False gives
            every pixel one depth and one colour.
        soft_maps: read a ramp in the map between two depths as an edge (``bokehray.ramps.snap_ramps``): each pixel
            strictly inside it takes the depth of the side its colour belongs to, so no pixel is rendered at a
            depth no surface has; slopes that do not end within 40 px (floors, walls) stay. With ``soft_edges``.
        thin_depth: before the ramps, give the structures a soft map's blur flattened (wires, twigs, strokes)
            their depth back from the photo's colour (``bokehray.thin_depth.restore_thin``); hard maps, tilted
            planes and smooth slopes stay as they are. With ``soft_maps``. Off by default: it costs about 0.04 CPU-s
            a megapixel of soft map (0.06 at 1.5 MP, 0.3 at 12 MP), twice the edge step's share of a 1.5 MP render
            (docs/soft-scene.md, "Soft maps").
        strand_gaps: bridge the gaps of a strand the map breaks into dashes (``bokehray.strands.bridge_strands``):
            a pixel between two dashes of the same depth takes the strand's depth where the photo shows the strand
            going on there, so the matting splits it instead of leaving its share of the strand sharp inside the
            strand's blur; so do the pixels beyond a dash end the photo shows holding the strand. After the matting,
            a light seen on both sides of an opaque strand is split behind it (``bokehray.strands.hidden_lights``).
            With ``soft_edges``.
    """

    max_layers: int = 8
    max_layer_px: float = 8.0
    min_layer_px: float = 1.0
    fill: bool = True
    tile_px: int = 16
    soft_edges: bool = True
    soft_maps: bool = True
    thin_depth: bool = False
    strand_gaps: bool = True

    def __post_init__(self) -> None:
        check_int(self.max_layers, "max_layers", lo=1)
        check_int(self.tile_px, "tile_px", lo=1, hi=MAX_TILE_PX)
        check_number(self.max_layer_px, "max_layer_px", 0.0, lo_open=True)
        check_number(self.min_layer_px, "min_layer_px", 0.0, lo_open=True)
        for name in ("fill", "soft_edges", "soft_maps", "thin_depth", "strand_gaps"):
            if not isinstance(getattr(self, name), bool):
                raise InputError(f"{name}: expected True or False, got {getattr(self, name)!r}")


@dataclass(frozen=True, slots=True)
class MemoryOptions:
    """The memory budget of one render (``bokehray.tiling``).

    Args:
        tile_size: render in independent square tiles of this many pixels a side (each with a halo that makes
            the result equal the untiled render); None (default) tiles only when the untiled render would not
            fit the budget. At least the layer grid (``LayerOptions.tile_px``).
        memory_limit_mb: memory budget of one render in MB; None (default) is 80 % of the memory available when
            the render starts. A render that cannot fit even in tiles raises
            :class:`~bokehray.errors.ResourceError` before allocating anything large.
    """

    tile_size: int | None = None
    memory_limit_mb: float | None = None

    def __post_init__(self) -> None:
        if self.tile_size is not None:
            try:
                check_int(self.tile_size, "tile_size", lo=1)
            except InputError:
                raise InputError(f"tile_size: expected None (automatic) or an integer >= 1, got {shown(self.tile_size)}") from None
        if self.memory_limit_mb is not None:
            try:
                check_number(self.memory_limit_mb, "memory_limit_mb", 0.0, lo_open=True)
            except InputError:
                raise InputError(f"memory_limit_mb: expected None (automatic) or a finite number > 0, "
                                 f"got {shown(self.memory_limit_mb)}") from None


@dataclass(frozen=True, slots=True)
class PreviewOptions:
    """Knobs only the preview reads (``bokehray.levels.preview``).

    Args:
        level_radius_px: largest radius scattered at a pyramid level before moving to the next coarser one
            (cost per source is O(level_radius_px)).
        threads: worker threads on the CPU (default: all cores).
        exact_highlights: scatter the light of sources whose own disc outline is visible (lights, highlights:
            ``levels.preview.route_salient``), their excess over the local colour, at full resolution instead of
            on the radius pyramid (the default);
            False leaves every source on the pyramid (measured in docs/renderer.md).
        clamp_border: take the unknown outside the frame as its edge pixels continued outwards
            (``levels.preview.border_pad``, the default); False divides by the coverage the frame got instead (the
            rule before, which brightens lights near the border).
        merge_sources: on each pyramid level, scatter the sources of one cell whose CoCs are near-equal as one
            (their summed light at their centroid: ``bk.scatter_merged_kernel``), the default; False scatters each
            (the render before, for measurements: docs/renderer.md).
    """

    level_radius_px: float = 8.0
    threads: int | None = None
    exact_highlights: bool = True
    clamp_border: bool = True
    merge_sources: bool = True

    def __post_init__(self) -> None:
        check_number(self.level_radius_px, "level_radius_px", 0.0, lo_open=True)
        if self.level_radius_px < 2.0:
            raise InputError(f"level_radius_px: expected >= 2 px (smaller coarsens every blur), got {self.level_radius_px}")
        if self.threads is not None and (isinstance(self.threads, bool) or not isinstance(self.threads, int)
                                         or self.threads < 1):
            raise InputError(f"threads: expected None (all cores) or an integer >= 1, got {shown(self.threads)}")
        for name in ("exact_highlights", "clamp_border", "merge_sources"):
            if not isinstance(getattr(self, name), bool):
                raise InputError(f"{name}: expected True or False, got {getattr(self, name)!r}")


@dataclass(frozen=True, slots=True)
class RaytraceOptions:
    """The aperture quadrature, read only by the ray tracer (``bokehray.levels.quadrature``; docs/raytracer.md).

    Args:
        samples_per_px2: cells per square pixel of the largest CoC a pixel can see: the aperture is cut into
            ``g = ceil(2 r sqrt(samples_per_px2))`` strips of square-ish cells (about ``(pi / 4) g^2`` of them)
            plus thin cells along its outline. Each cell is one ray whose texture lookups average the cell's
            footprint, so this sets how finely occlusion between layers is resolved, not the noise (there is none).
        max_spp: most rays (cells) per pixel: the strips are capped at ``sqrt(4 max_spp / pi)`` and, where the
            full cells and the thin cells along the outline exceed it, the outline is coarsened, then strips
            dropped (``bokehray.levels.raytrace_launch.choose_levels``). 1 is a single box cell of the aperture's
            area.
        min_spp: the fewest rays per pixel; 1 lets in-focus pixels (CoC below half a pixel) take the single centre
            ray.
    """

    samples_per_px2: float = 0.5
    max_spp: int = 128
    min_spp: int = 1

    def __post_init__(self) -> None:
        check_number(self.samples_per_px2, "samples_per_px2", 0.0, lo_open=True)
        check_int(self.max_spp, "max_spp")
        check_int(self.min_spp, "min_spp")
        if not 1 <= self.min_spp <= self.max_spp <= 65536:
            raise InputError(f"rays per pixel: expected 1 <= min_spp <= max_spp <= 65536, "
                             f"got {shown(self.min_spp)}, {shown(self.max_spp)}")
