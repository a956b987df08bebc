"""What a render did and skipped: one stats protocol for every quality level.

:class:`RenderStats` holds what every level reports; each level adds its own counters in a subclass
(:class:`PreviewStats`, :class:`RaytraceStats`). ``as_dict`` works for all of them (floats rounded for
printing), and is what ``bokehray render --stats`` prints.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field

__all__ = ["Clock", "PreviewStats", "RaytraceStats", "RenderStats"]


class Clock:
    """The stages of a command or a render on one clock, in the order they ran: :meth:`lap` closes the stage that
    ran since the last lap (or the start), so the laps sum to the time since the start (:meth:`total`)."""

    def __init__(self, start: float | None = None) -> None:
        self.start = time.perf_counter() if start is None else start
        self.last = self.start
        self.laps: dict[str, float] = {}

    def lap(self, name: str) -> float:
        """Close the stage ``name`` (added to an earlier one of that name); returns its length."""
        now = time.perf_counter()
        dt = now - self.last
        self.laps[name] = self.laps.get(name, 0.0) + dt
        self.last = now
        return dt

    def lap_as(self, stages: dict[str, float], rest: str) -> None:
        """Close the time since the last lap as ``stages``, timed inside it (a level's own stages; a "total" among
        them is left out), and what they leave of it under ``rest``."""
        parts = {k: v for k, v in stages.items() if k != "total"}
        left = self.lap(rest) - sum(parts.values())
        del self.laps[rest]
        for name, dt in {**parts, rest: max(0.0, left)}.items():
            self.laps[name] = self.laps.get(name, 0.0) + dt

    def total(self) -> float:
        return time.perf_counter() - self.start


def _rounded(value):
    if isinstance(value, float):
        return round(value, 4)
    if isinstance(value, dict):
        return {k: _rounded(v) for k, v in value.items()}
    if isinstance(value, tuple):
        return list(value)
    return value


@dataclass(slots=True)
class RenderStats:
    """What every level reports. Times in seconds.

    ``image_tiles`` > 1: the render went tile by tile (``bokehray.tiling``). ``memory_estimate_mb``: the
    estimated peak that chose between tiled and untiled. ``refine``: what ``refine=`` did (tiles refined,
    share, seconds), None without it.
    """

    quality: str = ""
    shape: tuple[int, int] = (0, 0)
    device: str = "cpu"
    max_coc_px: float = 0.0
    layers: int = 0
    image_tiles: int = 1
    memory_estimate_mb: float = 0.0
    stage_seconds: dict[str, float] = field(default_factory=dict)
    refine: dict | None = None

    def as_dict(self) -> dict:
        return {f.name: _rounded(getattr(self, f.name)) for f in dataclasses.fields(self)}


@dataclass(slots=True)
class PreviewStats(RenderStats):
    """The preview's counters: tiles copied from the input, sources scattered (``sources_filled`` of them made by
    the hidden-region fill; with tiles, the fill of each tile's halo counts again), radius-pyramid depth, threads."""

    tiles_total: int = 0
    tiles_copied: int = 0
    sources_scattered: int = 0
    sources_filled: int = 0
    pyramid_levels: int = 0
    threads: int = 1


@dataclass(slots=True)
class RaytraceStats(RenderStats):
    """The ray tracer's counters: rays (aperture cells) traced in all, per pixel on average and at most, and the
    aperture partitions used as (strips, outline) pairs."""

    samples_total: int = 0
    spp_mean: float = 0.0
    spp_max: int = 0
    partitions: list = field(default_factory=list)
