"""The edge network's recipe (``bokehray_refiner.training.edges``): its labels, its training crops and its steps are
what the recipe says, a stopped run resumes bit for bit, and the command trains and exports loadable weights."""

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from bokehray_refiner.edges import EdgeConfig, edge_features  # noqa: E402
from bokehray_refiner.training import edges as recipe  # noqa: E402
from bokehray_refiner.training.common import region  # noqa: E402
from bokehray_refiner.training.edges import EdgeRecipe  # noqa: E402

import bokehray as br  # noqa: E402

SMALL = EdgeConfig(width=8, dilations=(2, 1), radius_px=6)



def _maps():
    truth = np.full((40, 60), 0.2, np.float32)
    truth[10:30, 20:40] = 0.8
    shrunk = truth.copy()
    shrunk[10:30, 20:24] = 0.2  # the near square's left 4 columns lost
    return truth, shrunk, br.BlurParams(10.0, 0.2)


def test_labels_are_the_true_side_weighted_by_the_candidates_span():
    truth, shrunk, blur = _maps()
    rng = np.random.default_rng(0)
    focus = rng.random(truth.shape + (3,), dtype=np.float32)
    band = np.ones(truth.shape, np.float32)
    x = torch.from_numpy(edge_features(focus, shrunk, blur, band, SMALL))[None]
    cost = torch.from_numpy(recipe.side_costs(shrunk, truth, blur, SMALL).astype(np.float32))[None]
    label, span = recipe.side_labels(cost, x, SMALL)
    assert torch.all(label[0, 10:30, 20:30] == 1)  # the lost columns and the square's inside near them: near
    assert torch.all(label[0, 4:10, 20:30] == 0) and torch.all(span[0, 4:10, 20:30] > 0)  # above it: far, counted
    assert torch.all(span[0, 15, 18:30] == 1.0) and span[0, 15, 17] == 0  # an edge of 6 px CoC within 6 px: counts
    assert torch.all(span[0, 0, :] == 0.0)  # no edge within 6 px: does not count


def test_training_windows_pad_with_zeros_beyond_the_frame():
    a = np.arange(2 * 5 * 6, dtype=np.float32).reshape(2, 5, 6) + 1
    w = region(a, -2, 3, 4, lead=1)
    assert w.shape == (2, 4, 4)
    assert np.all(w[:, :2] == 0) and np.all(w[:, :, 3:] == 0)
    np.testing.assert_array_equal(w[:, 2:, :3], a[:, :2, 3:6])


def test_a_few_training_steps_run_and_count_only_the_crop():
    truth, shrunk, blur = _maps()
    rng = np.random.default_rng(1)
    focus = rng.random(truth.shape + (3,), dtype=np.float32)
    band = np.ones(truth.shape, np.float32)
    entry = {"x": edge_features(focus, shrunk, blur, band, SMALL).astype(np.float16),
             "cost": recipe.side_costs(shrunk, truth, blur, SMALL).astype(np.float16), "exact": False}
    _model, losses = recipe.train([entry], SMALL, EdgeRecipe(steps=3, batch=2, crop=16, seed=0, exact_weight=2.0))
    assert len(losses) == 3 and all(np.isfinite(losses))


def test_the_render_price_is_the_squared_colour_step_between_the_sides():
    """Two flat sides: the network's colour inputs hold photo - near mean and photo - far mean, so the price is the
    squared distance between the means over the scale squared, clamped to [1/20, 4] (no step: the floor)."""
    from bokehray_refiner.edges import N_BASE, N_INPUTS

    x = torch.zeros(3, N_INPUTS, 2, 2)
    for b, step in enumerate((0.0, 0.1, 1.0)):  # far mean - near mean, along red
        x[b, N_BASE] = 0.0
        x[b, N_BASE + 3] = -step
    price = recipe.render_price(x, 0.2)
    assert price.shape == (3, 2, 2)
    assert torch.allclose(price[0], torch.tensor(0.05)) and torch.allclose(price[1], torch.tensor(0.25))
    assert torch.allclose(price[2], torch.tensor(4.0))


def _entry(seed=1):
    truth, shrunk, blur = _maps()
    focus = np.random.default_rng(seed).random(truth.shape + (3,), dtype=np.float32)
    band = np.ones(truth.shape, np.float32)
    return {"x": edge_features(focus, shrunk, blur, band, SMALL).astype(np.float16),
            "cost": recipe.side_costs(shrunk, truth, blur, SMALL).astype(np.float16), "exact": False}


def test_training_from_given_weights_starts_where_they_are():
    from bokehray_refiner.edges import EdgeNet

    torch.manual_seed(7)
    start = EdgeNet(SMALL)
    tiny_lr = EdgeRecipe(steps=2, batch=1, crop=16, seed=0, exact_weight=1.0, lr=1e-12)
    still, _ = recipe.train([_entry()], SMALL, tiny_lr, init=start)
    fresh, _ = recipe.train([_entry()], SMALL, tiny_lr)
    for (name, a), b, c in zip(still.state_dict().items(), start.state_dict().values(), fresh.state_dict().values()):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-6, msg=name)
        assert not torch.allclose(a, c), name  # a fresh start is another network


@pytest.fixture(scope="module")
def pairs(tmp_path_factory):
    from bokehray.data.synth import SynthConfig, generate

    root = tmp_path_factory.mktemp("synth")
    generate(SynthConfig(size=64, blur_levels=(6.0,), max_spp=16), 1, root, seed=7, workers=1, progress=False)
    return root


def test_a_third_layer_the_map_has_nearly_right_is_labelled_to_stay():
    """A strip between the near square and the background: the map has it a little too near (0.55, on the near
    side), the truth at 0.45 (nearer the far candidate). Moving it to either candidate costs more than keeping it, so
    with keep_margin its label is the map's own side; without, the far candidate's."""
    truth, _, blur = _maps()
    truth[10:30, 40:44] = 0.45
    used = truth.copy()
    used[10:30, 40:44] = 0.55
    x = torch.from_numpy(edge_features(np.zeros(truth.shape + (3,), np.float32), used, blur,
                                       np.ones(truth.shape, np.float32), SMALL))[None]
    cost = torch.from_numpy(recipe.side_costs(used, truth, blur, SMALL).astype(np.float32))[None]
    plain, _ = recipe.side_labels(cost, x, SMALL)
    kept, _ = recipe.side_labels(cost, x, SMALL, keep_margin=0.5)
    assert torch.all(plain[0, 10:30, 40:44] == 0) and torch.all(kept[0, 10:30, 40:44] == 1)
    outside = torch.ones_like(plain[0], dtype=torch.bool)
    outside[10:30, 40:44] = False
    assert torch.equal(plain[0][outside], kept[0][outside])  # two-layer edges keep their labels
    assert torch.all(recipe.side_labels(cost, x, SMALL, keep_margin=2.0)[0][0, 10:30, 40:44] == 0)  # 1.5 px < 2


def test_a_stopped_run_resumed_from_its_checkpoint_is_the_same_run_bit_for_bit(tmp_path, monkeypatch):
    def run(checkpoint=None):
        return recipe.train([_entry()], SMALL, EdgeRecipe(steps=4, batch=2, crop=16, seed=3, exact_weight=2.0),
                            checkpoint, checkpoint_every=2)

    whole, whole_losses = run()
    step_and_save = recipe.optimise

    def stop_after_step_2(loss, step, *args):
        step_and_save(loss, step, *args)
        if step + 1 == 2:
            raise KeyboardInterrupt  # killed right after its checkpoint of step 2

    ckpt = str(tmp_path / "run.pt")
    monkeypatch.setattr(recipe, "optimise", stop_after_step_2)
    with pytest.raises(KeyboardInterrupt):
        run(ckpt)
    monkeypatch.setattr(recipe, "optimise", step_and_save)
    torch.manual_seed(123)  # the resumed run takes its generators from the checkpoint, not from here
    resumed, losses = run(ckpt)
    assert losses == whole_losses
    for (name, a), b in zip(resumed.state_dict().items(), whole.state_dict().values()):
        assert torch.equal(a, b), name


def test_the_command_makes_the_bank_trains_and_exports_weights_refine_loads(pairs, tmp_path):
    from bokehray_refiner.edges import load_edge_net

    out, bank = tmp_path / "edges.safetensors", tmp_path / "bank.npz"
    argv = [str(pairs), "--export", str(out), "--bank", str(bank), "--variants", "3", "--steps", "2", "--batch", "1",
            "--crop", "16", "--width", "8", "--dilations", "2,1", "--threads", "1"]
    threads = torch.get_num_threads()
    assert recipe.main(argv) == 0
    assert torch.get_num_threads() == threads  # the recipe's torch settings do not outlive it
    assert np.finfo(np.float32).smallest_subnormal > 0 and torch.tensor(1e-40).item() != 0.0
    net = load_edge_net(str(out))
    assert net.config.width == 8 and net.config.dilations == (2, 1)
    with np.load(bank) as z:
        assert int(z["n"]) == 2 * 3  # the scene's two pairs, three maps each
    again = tmp_path / "again.safetensors"
    assert recipe.main([argv[0], "--export", str(again), *argv[3:]]) == 0  # the bank is read back: the same run
    for (name, a), b in zip(net.state_dict().items(), load_edge_net(str(again)).state_dict().values()):
        assert torch.equal(a, b), name


def test_the_command_refuses_a_missing_training_folder_in_one_line(tmp_path, capsys):
    assert recipe.main([str(tmp_path / "nowhere"), "--export", str(tmp_path / "w.safetensors")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "nowhere" in err[0]
    assert not (tmp_path / "w.safetensors").exists()
