"""The speed guard's verdicts (benchmarks/renderer/bench_guard.py): a figure 15 % worse than its baseline is marked
REGRESSION, a 12 MP stage only when it also moved by a fifth of an FFT; nothing is timed here."""

from __future__ import annotations

import pytest
from scripts import load_script


@pytest.fixture(scope="module")
def guard():
    return load_script("benchmarks/renderer/bench_guard.py", "bench_guard")


def _marks(guard, now, base):
    lines = guard.compare(now, {"figures": base})
    return {line[:28].strip(): line.endswith("REGRESSION") for line in lines[1:]}


def test_a_figure_15_percent_worse_is_a_regression(guard):
    marks = _marks(guard, {"t32/tFFT": 14.2, "t128/t16": 1.70}, {"t32/tFFT": 12.3, "t128/t16": 1.60})
    assert marks == {"t32/tFFT": True, "t128/t16": False}


def test_a_small_stage_s_noise_is_not_a_regression(guard):
    base = {"12MP soft maps/tFFT": 0.31, "12MP layers/tFFT": 10.3}
    marks = _marks(guard, {"12MP soft maps/tFFT": 0.40, "12MP layers/tFFT": 12.0}, base)
    assert marks == {"12MP soft maps/tFFT": False, "12MP layers/tFFT": True}


def test_figures_without_a_baseline_and_raw_times_are_left_unmarked(guard):
    lines = guard.compare({"t32/tFFT": 30.0, "t32_s": 9.0, "12MP stage_s": {"layers": 1.0}}, None)
    assert lines[1:] == [f"{'t32/tFFT':28s} {30.0:9.2f} {'-':>9s}"]
