"""research/refiner_edges/refiner_edges.py: its labels, its oracle and its training crops are what the measurement says."""

from pathlib import Path

import numpy as np
import pytest
from scripts import load_script

torch = pytest.importorskip("torch")

from bokehray_refiner.edges import EdgeConfig  # noqa: E402

import bokehray as br  # noqa: E402

SMALL = EdgeConfig(width=8, dilations=(2, 1), radius_px=6)


@pytest.fixture(scope="module")
def bench():
    return load_script(Path("research/refiner_edges/refiner_edges.py"), "refiner_edges")


def _maps():
    truth = np.full((40, 60), 0.2, np.float32)
    truth[10:30, 20:40] = 0.8
    shrunk = truth.copy()
    shrunk[10:30, 20:24] = 0.2  # the near square's left 4 columns lost
    return truth, shrunk, br.BlurParams(10.0, 0.2)


def test_the_oracle_moves_only_wrong_sided_pixels_back(bench):
    truth, shrunk, _blur = _maps()
    band = np.ones(truth.shape, np.float32)
    np.testing.assert_array_equal(bench.oracle_map(truth, truth, band, SMALL), truth)  # a right map stays
    np.testing.assert_array_equal(bench.oracle_map(shrunk, truth, band, SMALL), truth)
    band[:, :22] = 0.0
    fixed = bench.oracle_map(shrunk, truth, band, SMALL)  # only where the band is open
    assert np.all(fixed[10:30, 20:22] == 0.2) and np.all(fixed[10:30, 22:24] == 0.8)


@pytest.fixture(scope="module")
def pairs(tmp_path_factory):
    from bokehray.data.synth import SynthConfig, generate

    root = tmp_path_factory.mktemp("synth")
    generate(SynthConfig(size=64, blur_levels=(6.0,), max_spp=16), 1, root, seed=7, workers=1, progress=False)
    return root


def test_the_run_flags_of_an_old_bank_are_the_ones_a_new_bank_records(bench, pairs, tmp_path):
    """A bank written before it kept whether refine runs the network on each map gets the flags by drawing the maps
    again; they are those of a bank made whole, and --runs-only trains on those maps alone."""
    import argparse

    from bokehray_refiner.refine import RefineOptions

    opts = RefineOptions()
    made = bench.bank(str(pairs), 4, 3, opts, SMALL)
    assert len(made) == 2 * 4 and [e["exact"] for e in made[:4]] == [True, False, False, False]
    flags = [bool(e["runs"]) for e in made]
    assert 0 < sum(flags) < len(flags)  # this scene's maps are some of each
    assert list(bench.run_flags(str(pairs), 4, 3, opts)) == flags
    path = str(tmp_path / "bank.npz")
    bench._save_bank(path, [{k: v for k, v in e.items() if k != "runs"} for e in made])  # an old bank
    args = argparse.Namespace(bank=path, train=str(pairs), variants=4, seed=3, runs_only=True, with_exact=False)
    kept = bench._entries(args, opts, SMALL)
    assert len(kept) == sum(flags)
    with np.load(path) as z:  # the flags were written back
        assert [bool(z[f"{i}_runs"]) for i in range(int(z["n"]))] == flags
    assert len(bench._entries(argparse.Namespace(**(vars(args) | {"runs_only": False})), opts, SMALL)) == len(made)
    exact = [e["exact"] for e in made]
    with_exact = bench._entries(argparse.Namespace(**(vars(args) | {"with_exact": True})), opts, SMALL)
    assert len(with_exact) == sum(f or x for f, x in zip(flags, exact)) > len(kept)
