"""Replay the fuzzer's files (tests/data/fuzz/) through every reader of their format; no atheris needed.

``seeds/`` holds small valid files of every variant the writers produce (what the fuzzer
starts from): each must be read. ``found/`` holds inputs the fuzzer (benchmarks/robustness/fuzz_readers.py)
turned up, each once a failure: each must now be read, or refused with one InputError or
ResourceError naming the file, and nothing else may be printed. docs/robustness.md lists
what each found input was.
"""

from pathlib import Path

import numpy as np
import pytest

import bokehray as br
from bokehray.errors import InputError, ResourceError
from bokehray.photo import read as rd

DATA = Path(__file__).parents[1] / "data" / "fuzz"
READERS = {".png": ("read_image", "read_disparity"), ".jpg": ("read_image",),
           ".tif": ("read_image", "read_disparity", "read_depth"), ".exr": ("read_image", "read_disparity", "read_depth"),
           ".npy": ("read_disparity", "read_depth")}
FILES = sorted(p for p in DATA.rglob("*") if p.is_file() and p.suffix in READERS)


def test_the_regression_files_are_there_and_small():
    assert len([p for p in FILES if p.parent.name == "seeds"]) >= 10
    assert sum(p.stat().st_size for p in FILES) < 200_000


@pytest.mark.parametrize("path", FILES, ids=lambda p: f"{p.parent.name}/{p.name}")
def test_reader_returns_finite_values_or_one_clear_error(path, monkeypatch, capfd):
    monkeypatch.setattr(rd, "MAX_PIXELS", 2_000_000)  # as the fuzzer ran
    read_any = False
    for name in READERS[path.suffix]:
        try:
            a = getattr(br, name)(path)
        except (InputError, ResourceError) as e:
            assert str(path) in str(e) and "\n" not in str(e), str(e)
            continue
        read_any = True
        if name == "read_depth":  # metres in float64; +inf is a pixel without depth
            assert a.dtype == np.float64 and a.ndim == 2 and not np.isnan(a).any()
        else:
            assert a.dtype == np.float32 and a.ndim in (2, 3) and np.isfinite(a).all()
    if path.parent.name == "seeds":
        assert read_any, f"{path}: a seed must be readable"
    # nothing of the decoders' own chatter (OpenEXR prints to fd 1/2, tifffile logs) reaches the user
    out, err = capfd.readouterr()
    assert out == "" and err == "", (out + err)[:300]
