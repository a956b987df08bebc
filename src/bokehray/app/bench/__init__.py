"""``bokehray bench``: run time against error, bokehray's quality levels and peers on the same inputs.

* :mod:`.methods`: the method registry (the one place to add a method);
* :mod:`.peers`: the peers (naive O(r^2) scatter, GEGL lens blur, Blender Defocus);
* :mod:`.ebb`: the EBB Val294 protocol (focus, K search, exposure alignment);
* :mod:`.run`: datasets, the measuring loop, Pareto front, reports.

See docs/benchmarks.md. Importing this package needs neither torch, bpy nor GEGL.
"""


from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

_EXPORTS = {"Method": "methods", "registry": "methods", "select": "methods", "Case": "run", "SynthSplit": "run",
            "pareto_front": "run", "run_bench": "run", "write_reports": "run"}
"""Resolved on first use (PEP 562): ``bokehray --help`` builds the bench sub-parser without the loop's imports."""

__all__ = ["Case", "Method", "SynthSplit", "pareto_front", "registry", "run_bench", "select", "write_reports"]


def __getattr__(name: str) -> Any:
    if name not in _EXPORTS:
        raise AttributeError(f"module 'bokehray.app.bench' has no attribute {name!r}")
    value = getattr(importlib.import_module(f".{_EXPORTS[name]}", __name__), name)
    globals()[name] = value
    return value


if TYPE_CHECKING:
    from .methods import Method, registry, select
    from .run import Case, SynthSplit, pareto_front, run_bench, write_reports
