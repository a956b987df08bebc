"""Shared fixtures. Tests live by category (kernels/, core/, refiner/, cli_io/, stress/); the NumPy oracles in
reference/ and the tolerances in tolerances.py are imported from this folder."""

import os
import signal
import sys
from pathlib import Path

import numpy as np
import pytest
import warp as wp
from hypothesis import settings

sys.path.insert(0, str(Path(__file__).parent))  # reference/, tolerances.py, conftest.DEVICES

# A test run started in the background by a non-interactive shell (`make test &`) inherits SIGINT ignored, and so
# would every CLI the tests start: the Ctrl-C tests would wait for an interrupt that never comes. Python's own
# handler again, here and (being a handler, not "ignored") reset to the default in every child process.
signal.signal(signal.SIGINT, signal.default_int_handler)

wp.config.log_level = wp.LOG_WARNING
wp.init()

settings.register_profile("ci", max_examples=40, deadline=None, derandomize=True)
settings.register_profile("dev", max_examples=15, deadline=None)
settings.register_profile("soak", max_examples=2000, deadline=None)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))

DEVICES = ["cpu", pytest.param("cuda", marks=[pytest.mark.gpu, pytest.mark.skipif(
    not wp.is_cuda_available(), reason="no CUDA device")])]


@pytest.fixture(params=DEVICES)
def device(request):
    return request.param


@pytest.fixture
def rng():
    return np.random.default_rng(1234)
