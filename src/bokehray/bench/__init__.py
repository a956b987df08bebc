"""``bokehray bench``: run time against error, bokehray's quality levels and peers on the same inputs.

* :mod:`.methods`: the method registry (the one place to add a method);
* :mod:`.peers`: the peers (naive O(r^2) scatter, GEGL lens blur, Blender Defocus);
* :mod:`.ebb`: the EBB Val294 protocol (focus, K search, exposure alignment);
* :mod:`.run`: datasets, the measuring loop, Pareto front, reports.

See docs/benchmarks.md. Importing this package needs neither torch, bpy nor GEGL.
"""

from .methods import Method, registry, select
from .run import Case, SynthSplit, pareto_front, run_bench, write_reports

__all__ = ["Case", "Method", "SynthSplit", "pareto_front", "registry", "run_bench", "select", "write_reports"]
