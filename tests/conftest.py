"""Shared fixtures. Tests live by category (kernels/, core/, refiner/, cli_io/, stress/); the NumPy oracles in
reference/ and the tolerances in tolerances.py are imported from this folder."""

import os
import sys
from pathlib import Path

import numpy as np
import pytest
import warp as wp
from hypothesis import settings

sys.path.insert(0, str(Path(__file__).parent))  # reference/, tolerances.py, conftest.DEVICES

wp.config.log_level = wp.LOG_WARNING
wp.init()

settings.register_profile("ci", max_examples=40, deadline=None, derandomize=True)
settings.register_profile("dev", max_examples=15, deadline=None)
settings.register_profile("soak", max_examples=2000, deadline=None)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))

DEVICES = ["cpu"] + (["cuda"] if wp.is_cuda_available() else [])


@pytest.fixture(params=DEVICES)
def device(request):
    return request.param


@pytest.fixture
def rng():
    return np.random.default_rng(1234)
