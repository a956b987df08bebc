"""The synthetic pair generator: structure, determinism, BLB output, bad input."""

import itertools
import json
from dataclasses import replace

import numpy as np
import pytest

import bokehray as br
from bokehray.app.cli import main
from bokehray.data.datasets import BLBDataset
from bokehray.data.synth import SynthConfig, generate, make_scene

SMALL = SynthConfig(size=48, blur_levels=(6.0, 12.0), max_spp=8)


@pytest.mark.parametrize("index", range(6))
def test_layers_are_ordered_and_do_not_interpenetrate(index):
    layers, desc = make_scene(SMALL, seed=7, index=index)
    assert len(layers) == len(desc["layers"]) >= 2
    n = SMALL.size
    corners = np.array([[0.5, 0.5], [n - 0.5, 0.5], [0.5, n - 0.5], [n - 0.5, n - 0.5]])
    spans = []
    for lyr in layers:
        a, b, c = lyr.plane
        d = corners @ np.array([a, b]) + c
        spans.append((d.min(), d.max()))
        assert 0.0 <= d.min() and d.max() <= 1.0
    for (near_lo, _), (_, far_hi) in itertools.pairwise(spans):
        assert near_lo > far_hi  # nearest first, no crossing: composite order is valid for every ray
    np.testing.assert_array_equal(layers[-1].rgba[..., 3], 1.0)  # an opaque background ends every ray


def test_generation_is_deterministic_and_reads_back(tmp_path):
    a = generate(SMALL, 2, tmp_path / "a", seed=3, workers=1, progress=False)
    b = generate(SMALL, 2, tmp_path / "b", seed=3, workers=1, progress=False)
    for pa, pb in zip(a, b):
        for f in sorted(p.name for p in (tmp_path / "a" / pa.split("/")[-1]).iterdir()):
            if f.endswith(".exr"):
                assert (tmp_path / "a" / pa.split("/")[-1] / f).read_bytes() == \
                       (tmp_path / "b" / pb.split("/")[-1] / f).read_bytes(), f
    ds = BLBDataset(tmp_path / "a")
    assert len(ds) == 2 * 2 * 2  # scenes x blur levels x focus choices
    s = ds[0]
    assert s.image.shape == (48, 48, 3) and s.target.shape == (48, 48, 3)
    assert s.k_px in SMALL.blur_levels and 0.0 <= s.focus_disparity <= 1.0
    info = json.loads((tmp_path / "a" / "scene_00000" / "info.json").read_text())
    assert info["seed"] == 3 and info["aperture"]["blades"] == 0 and "disparity_normalisation" in info
    # the target differs from the input (something is blurred) and in-focus content stays close
    assert np.abs(s.target - s.image).max() > 0.01


def test_cli_synth_and_bad_input(tmp_path, capsys):
    code = main(["synth", "-n", "1", "-o", str(tmp_path / "out"), "--size", "40", "--blur-levels", "5",
                 "--max-spp", "4", "--workers", "1", "--quiet"])
    assert code == 0
    assert (tmp_path / "out" / "scene_00000" / "bokeh_0_1.exr").exists()
    (tmp_path / "empty").mkdir()
    code = main(["synth", "-n", "1", "-o", str(tmp_path / "o2"), "--fg", str(tmp_path / "empty"), "--quiet"])
    assert code == 2 and "no images" in capsys.readouterr().err
    br.write_image(tmp_path / "fg" / "noalpha.png", np.ones((20, 20, 3), np.float32))
    code = main(["synth", "-n", "1", "-o", str(tmp_path / "o3"), "--fg", str(tmp_path / "fg"), "--size", "40",
                 "--workers", "1", "--quiet"])
    err = capsys.readouterr().err
    assert code == 2 and "alpha" in err
    assert not any((tmp_path / "o3").glob("scene_*"))  # no partial dataset entry
    code = main(["synth", "-n", "1", "-o", str(tmp_path / "o4"), "--blur-levels", "a,b", "--quiet"])
    assert code == 2 and "--blur-levels" in capsys.readouterr().err


def test_synth_progress_off_a_terminal_is_plain_lines(tmp_path, capsys, monkeypatch):
    """Regression: ``synth``'s tqdm bar wrote carriage-return frames into a stderr that was a file or a CI log. Off a
    terminal it prints a plain line now and then (here every time: the interval is set to 0), never a frame."""
    import bokehray._quiet

    monkeypatch.setattr(bokehray._quiet, "PLAIN_PROGRESS_EVERY_S", 0.0)
    code = main(["synth", "-n", "2", "-o", str(tmp_path / "out"), "--size", "40", "--blur-levels", "5",
                 "--max-spp", "4", "--workers", "1"])
    err = capsys.readouterr().err
    assert code == 0 and "\r" not in err, repr(err)
    assert "scenes: 1 of 2 (50%)\n" in err, err


def test_focus_choices_are_the_foreground_and_background_planes():
    from bokehray.data.synth import mean_disparity

    layers, _ = make_scene(SMALL, seed=1, index=3)
    n = SMALL.size
    a, b, c = layers[0].plane
    d_fg = mean_disparity(layers[0])
    corners = [a * x + b * y + c for x in (0, n) for y in (0, n)]
    assert min(corners) - 1e-6 <= d_fg <= max(corners) + 1e-6  # within the nearest layer's own disparity range
    assert mean_disparity(layers[-1]) < d_fg


def test_corrupt_foreground_is_a_clear_error_with_no_scene(tmp_path, capsys):
    (tmp_path / "fg").mkdir()
    (tmp_path / "fg" / "broken.png").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(20))
    code = main(["synth", "-n", "1", "-o", str(tmp_path / "out"), "--fg", str(tmp_path / "fg"), "--size", "40",
                 "--workers", "1", "--quiet"])
    err = capsys.readouterr().err
    assert code == 2 and "broken.png" in err
    assert not any((tmp_path / "out").glob("scene_*"))


def test_existing_scenes_need_overwrite(tmp_path):
    generate(SMALL, 1, tmp_path, seed=0, workers=1, progress=False)
    with pytest.raises(br.InputError, match="--overwrite"):
        generate(SMALL, 1, tmp_path, seed=0, workers=1, progress=False)
    generate(SMALL, 1, tmp_path, seed=1, workers=1, progress=False, overwrite=True)
    assert json.loads((tmp_path / "scene_00000" / "info.json").read_text())["seed"] == 1


def test_any_foreground_coverage_is_labelled_with_the_foregrounds_depth():
    """Mixed edge pixels and sub-pixel strands (alpha < 0.5) take the foreground's disparity, not the background's."""
    from bokehray.data.synth import pinhole_layers
    from bokehray.levels.raytrace import Layer

    n = 16
    fg = np.zeros((n, n, 4), np.float32)
    fg[..., :3] = 0.8
    fg[4:12, 4:8, 3] = 1.0  # a solid block
    fg[4:12, 8, 3] = 0.3  # its antialiased edge
    fg[2, :, 3] = 0.1  # a sub-pixel strand
    fg[0, 0, 3] = 0.5 / 255  # invisible dust
    bg = np.ones((n, n, 4), np.float32)
    bg[..., :3] = 0.2
    layers = [Layer(fg, plane=(0.0, 0.0, 0.9)), Layer(bg, plane=(0.0, 0.0, 0.1))]
    _, d = pinhole_layers(layers)
    assert np.allclose(d[4:12, 4:9], 0.9) and np.allclose(d[2], 0.9)
    assert d[0, 0] == pytest.approx(0.1) and np.allclose(d[13:], 0.1) and np.allclose(d[4:12, 9:], 0.1)


def test_weighted_kinds_draw_only_what_is_named_and_bad_weights_are_refused(tmp_path, capsys):
    from bokehray.data.synth import ALL_KINDS

    cfg = SynthConfig(size=48, blur_levels=(6.0,), max_spp=8, kinds=(("fur", 1.0), ("whiskers", 1.0),
                                                                     ("softcut", 1.0), ("mesh", 0.0)))
    drawn = {lyr["kind"] for i in range(12) for lyr in make_scene(cfg, seed=2, index=i)[1]["layers"][:-1]}
    assert drawn == {"fur", "whiskers", "softcut"}
    for kind in ALL_KINDS:  # every kind makes some coverage, none above 1
        layers, _ = make_scene(SynthConfig(size=64, kinds=((kind, 1.0),)), seed=1, index=0)
        a = layers[0].rgba[..., 3]
        assert 0 < a.mean() and a.max() <= 1.0 and np.isfinite(layers[0].rgba).all()
    for bad in ((("hair", 1.0),), (("fur", -1.0),), (("fur", 0.0),), ()):
        with pytest.raises(br.InputError, match="kinds"):
            SynthConfig(kinds=bad)
    code = main(["synth", "-n", "1", "-o", str(tmp_path / "o"), "--kinds", "fur:2", "--quiet"])
    assert code == 2 and "--kinds" in capsys.readouterr().err and not (tmp_path / "o").exists()
    code = main(["synth", "-n", "1", "-o", str(tmp_path / "o"), "--kinds", "hair=2", "--quiet"])
    assert code == 2 and "kinds" in capsys.readouterr().err and not (tmp_path / "o").exists()


def test_the_half_rule_labels_only_pixels_a_foreground_covers_at_least_half(tmp_path):
    from bokehray.data.synth import pinhole_layers
    from bokehray.levels.raytrace import Layer

    fg = np.zeros((16, 16, 4), np.float32)
    fg[..., :3] = 0.8
    fg[4:12, 4:8, 3] = 1.0
    fg[4:12, 8, 3] = 0.3  # an antialiased edge below one half
    fg[4:12, 3, 3] = 0.5  # one at one half
    fg[2, :, 3] = 0.1  # a sub-pixel strand
    bg = np.ones((16, 16, 4), np.float32)
    layers = [Layer(fg, plane=(0.0, 0.0, 0.9)), Layer(bg, plane=(0.0, 0.0, 0.1))]
    _, d = pinhole_layers(layers, "half")
    assert np.allclose(d[4:12, 3:8], 0.9) and np.allclose(d[4:12, 8], 0.1) and np.allclose(d[2], 0.1)
    with pytest.raises(br.InputError, match="depth rule"):
        pinhole_layers(layers, "most")
    generate(replace(SMALL, depth_rule="half"), 1, tmp_path, seed=3, workers=1, progress=False)
    assert json.loads((tmp_path / "scene_00000" / "info.json").read_text())["depth_rule"] == "half"
