"""research/refiner_choice/refiner_choice.py: its oracle and its chooser do what the measurement says they do."""

from pathlib import Path

import numpy as np
import pytest
from scripts import load_script

torch = pytest.importorskip("torch")


@pytest.fixture(scope="module")
def choice():
    return load_script(Path("research/refiner_choice/refiner_choice.py"), "refiner_choice")


def _entry(choice, rng, band):
    h, w = band.shape
    cands = rng.random((choice.N_CAND, h, w, 3), dtype=np.float32)
    return {"focus": rng.random((h, w, 3), dtype=np.float32), "cands": cands, "band": band.astype(np.float32),
            "disparity": rng.random((h, w), dtype=np.float32), "target": cands[3].copy(), "weight": 1.0,
            "align": rng.random((choice.N_CAND, h, w), dtype=np.float32)}


def test_the_oracle_takes_the_render_that_is_right_and_only_in_the_band(choice):
    rng = np.random.default_rng(0)
    band = np.zeros((24, 32))
    band[:, 16:] = 1.0
    e = _entry(choice, rng, band)
    out = choice.oracle(e)
    np.testing.assert_array_equal(out[:, 16:], e["target"][:, 16:])  # the exact render is a candidate: taken
    np.testing.assert_array_equal(out[:, :16], e["cands"][0][:, :16])  # outside the band: the render as it is


@pytest.mark.parametrize("alignment", [False, True])
def test_the_chooser_blends_candidates_within_the_band_only(choice, alignment):
    rng = np.random.default_rng(1)
    torch.manual_seed(0)
    band = np.zeros((16, 40))
    band[:, 20:] = 1.0
    e = _entry(choice, rng, band)
    with torch.no_grad():
        out = choice.make_chooser(alignment=alignment)(*choice._tensors([e])[:5])[0].permute(1, 2, 0).numpy()
    np.testing.assert_array_equal(out[:, :20], e["cands"][0][:, :20])
    lo, hi = e["cands"].min(0), e["cands"].max(0)  # a convex combination of the candidates
    inside = out[:, 20:]
    assert np.all(inside >= lo[:, 20:] - 1e-6) and np.all(inside <= hi[:, 20:] + 1e-6)
    assert not np.allclose(inside, e["cands"][0][:, 20:])


def test_edge_alignment_reads_highest_for_the_map_whose_edge_is_the_photos(choice):
    # a photo whose colour edge is at column 40; the map's near region ends there, 6 px short of it, or 12 px past it
    h, w = 48, 96
    focus = np.zeros((h, w, 3), np.float32)
    focus[:, :40] = 0.8
    right = np.zeros((h, w), np.float32)
    right[:, :40] = 1.0
    short, long_ = np.roll(right, -6, axis=1), np.roll(right, 12, axis=1)
    short[:, -6:] = 0.0
    long_[:, :12] = 1.0
    a = choice.edge_alignment(focus, [short, right, long_], lambda m: 10.0 * m)
    near_edge = a[:, :, 34:52].mean(axis=(1, 2))
    assert a.shape == (3, h, w) and a.min() >= 0.0 and a.max() <= 1.0
    assert near_edge[1] > 0.9 and near_edge[1] > 3 * max(near_edge[0], near_edge[2])
    flat = choice.edge_alignment(np.full((h, w, 3), 0.5, np.float32), [short, right, long_], lambda m: 10.0 * m)
    assert flat.max() == 0.0  # no colour edge anywhere: no map is preferred


def test_training_resumed_from_its_checkpoint_is_the_same_run_bit_for_bit(choice, tmp_path, monkeypatch):
    """Long training in pieces: a run killed right after its checkpoint at step 3 of 6, started again, ends with the
    weights and losses of one run of 6 steps."""
    # one thread: with two, a convolution's backward may sum in another order from one call to the next (it did once
    # in CI on a loaded machine), and bit identity is a property of the training state, not of the thread scheduling
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        _resume_bit_for_bit(choice, tmp_path, monkeypatch)
    finally:
        torch.set_num_threads(threads)


def _resume_bit_for_bit(choice, tmp_path, monkeypatch):
    rng = np.random.default_rng(2)
    band = np.zeros((40, 40))
    band[:, 18:26] = 1.0
    entries = [_entry(choice, rng, band) | {"exact": i == 0} for i in range(3)]
    kw = {"batch": 2, "crop": 32, "seed": 5, "choice_weight": 0.01, "log_every": 1000}
    whole, whole_losses = choice.train(entries, 6, **kw)

    class Killed(Exception):
        pass

    import bokehray_refiner.training.common as loop

    real_save = loop.save_state

    def save_then_die(path, state):
        real_save(path, state)
        raise Killed

    ckpt = str(tmp_path / "run.pt")
    monkeypatch.setattr(loop, "save_state", save_then_die)
    with pytest.raises(Killed):
        choice.train(entries, 6, checkpoint=ckpt, checkpoint_every=3, **kw)
    monkeypatch.undo()
    resumed, losses = choice.train(entries, 6, checkpoint=ckpt, checkpoint_every=3, **kw)
    assert len(losses) == 6 and losses == whole_losses
    for a, b in zip(whole.state_dict().values(), resumed.state_dict().values(), strict=True):
        assert torch.equal(a, b)
