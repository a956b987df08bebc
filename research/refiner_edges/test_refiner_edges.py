"""research/refiner_edges/refiner_edges.py: its labels, its oracle and its training crops are what the measurement says."""

from pathlib import Path

import numpy as np
import pytest
from scripts import load_script

torch = pytest.importorskip("torch")

from bokehray_refiner.edges import EdgeConfig, edge_features  # noqa: E402

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


def test_labels_are_the_true_side_weighted_by_the_candidates_span(bench):
    truth, shrunk, blur = _maps()
    rng = np.random.default_rng(0)
    focus = rng.random(truth.shape + (3,), dtype=np.float32)
    band = np.ones(truth.shape, np.float32)
    x = torch.from_numpy(edge_features(focus, shrunk, blur, band, SMALL))[None]
    cost = torch.from_numpy(bench.side_costs(shrunk, truth, blur, SMALL).astype(np.float32))[None]
    label, span = bench.side_labels(cost, x, SMALL)
    assert torch.all(label[0, 10:30, 20:30] == 1)  # the lost columns and the square's inside near them: near
    assert torch.all(label[0, 4:10, 20:30] == 0) and torch.all(span[0, 4:10, 20:30] > 0)  # above it: far, counted
    assert torch.all(span[0, 15, 18:30] == 1.0) and span[0, 15, 17] == 0  # an edge of 6 px CoC within 6 px: counts
    assert torch.all(span[0, 0, :] == 0.0)  # no edge within 6 px: does not count


def test_training_windows_pad_with_zeros_beyond_the_frame(bench):
    a = np.arange(2 * 5 * 6, dtype=np.float32).reshape(2, 5, 6) + 1
    w = bench._region(a, -2, 3, 4, lead=1)
    assert w.shape == (2, 4, 4)
    assert np.all(w[:, :2] == 0) and np.all(w[:, :, 3:] == 0)
    np.testing.assert_array_equal(w[:, 2:, :3], a[:, :2, 3:6])


def test_a_few_training_steps_run_and_count_only_the_crop(bench):
    truth, shrunk, blur = _maps()
    rng = np.random.default_rng(1)
    focus = rng.random(truth.shape + (3,), dtype=np.float32)
    band = np.ones(truth.shape, np.float32)
    entry = {"x": edge_features(focus, shrunk, blur, band, SMALL).astype(np.float16),
             "cost": bench.side_costs(shrunk, truth, blur, SMALL).astype(np.float16), "exact": False}
    _model, losses = bench.train([entry], SMALL, steps=3, batch=2, crop=16, seed=0, exact_weight=2.0,
                                checkpoint=None)
    assert len(losses) == 3 and all(np.isfinite(losses))


def test_the_render_price_is_the_squared_colour_step_between_the_sides(bench):
    """Two flat sides: the network's colour inputs hold photo - near mean and photo - far mean, so the price is the
    squared distance between the means over the scale squared, clamped to [1/20, 4] (no step: the floor)."""
    from bokehray_refiner.edges import N_BASE, N_INPUTS

    x = torch.zeros(3, N_INPUTS, 2, 2)
    for b, step in enumerate((0.0, 0.1, 1.0)):  # far mean - near mean, along red
        x[b, N_BASE] = 0.0
        x[b, N_BASE + 3] = -step
    price = bench.render_price(x, 0.2)
    assert price.shape == (3, 2, 2)
    assert torch.allclose(price[0], torch.tensor(0.05)) and torch.allclose(price[1], torch.tensor(0.25))
    assert torch.allclose(price[2], torch.tensor(4.0))


def _entry(bench, seed=1):
    truth, shrunk, blur = _maps()
    focus = np.random.default_rng(seed).random(truth.shape + (3,), dtype=np.float32)
    band = np.ones(truth.shape, np.float32)
    return {"x": edge_features(focus, shrunk, blur, band, SMALL).astype(np.float16),
            "cost": bench.side_costs(shrunk, truth, blur, SMALL).astype(np.float16), "exact": False}


def test_training_from_given_weights_starts_where_they_are(bench):
    from bokehray_refiner.edges import EdgeNet

    torch.manual_seed(7)
    start = EdgeNet(SMALL)
    still, _ = bench.train([_entry(bench)], SMALL, steps=2, batch=1, crop=16, seed=0, exact_weight=1.0,
                           checkpoint=None, lr=1e-12, init=start)
    fresh, _ = bench.train([_entry(bench)], SMALL, steps=2, batch=1, crop=16, seed=0, exact_weight=1.0,
                           checkpoint=None, lr=1e-12)
    for (name, a), b, c in zip(still.state_dict().items(), start.state_dict().values(), fresh.state_dict().values()):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-6, msg=name)
        assert not torch.allclose(a, c), name  # a fresh start is another network


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


def test_a_third_layer_the_map_has_nearly_right_is_labelled_to_stay(bench):
    """A strip between the near square and the background: the map has it a little too near (0.55, on the near
    side), the truth at 0.45 (nearer the far candidate). Moving it to either candidate costs more than keeping it, so
    with keep_margin its label is the map's own side; without, the far candidate's."""
    truth, _, blur = _maps()
    truth[10:30, 40:44] = 0.45
    used = truth.copy()
    used[10:30, 40:44] = 0.55
    x = torch.from_numpy(edge_features(np.zeros(truth.shape + (3,), np.float32), used, blur,
                                       np.ones(truth.shape, np.float32), SMALL))[None]
    cost = torch.from_numpy(bench.side_costs(used, truth, blur, SMALL).astype(np.float32))[None]
    plain, _ = bench.side_labels(cost, x, SMALL)
    kept, _ = bench.side_labels(cost, x, SMALL, keep_margin=0.5)
    assert torch.all(plain[0, 10:30, 40:44] == 0) and torch.all(kept[0, 10:30, 40:44] == 1)
    outside = torch.ones_like(plain[0], dtype=torch.bool)
    outside[10:30, 40:44] = False
    assert torch.equal(plain[0][outside], kept[0][outside])  # two-layer edges keep their labels
    assert torch.all(bench.side_labels(cost, x, SMALL, keep_margin=2.0)[0][0, 10:30, 40:44] == 0)  # 1.5 px < 2
