"""Data tools: exact synthetic training pairs (``synth``), the BLB / EBB dataset layouts (``datasets``) and the
image-quality metrics of the benchmarks (``metrics``)."""
