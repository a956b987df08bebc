"""The small refiner: identity at initialisation, training, exact resume, shipped weights, ``--refine``."""

import json
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

torch = pytest.importorskip("torch")

from bokehray_refiner.gate import GateOptions  # noqa: E402
from bokehray_refiner.masks import PisaMaskProvider  # noqa: E402
from bokehray_refiner.model import BokehRefiner, fingerprint  # noqa: E402
from bokehray_refiner.refine import (  # noqa: E402
    DEFAULT_WEIGHTS,
    RefineOptions,
    corrected_disparity,
    load_refiner,
    refine,
    tiles_to_refine,
)
from bokehray_refiner.training.data import PairBank, corrupt_disparity  # noqa: E402
from bokehray_refiner.training.residual import TrainConfig, edge_loss, hardness_at, train  # noqa: E402

import bokehray as br  # noqa: E402
from bokehray.data.synth import SynthConfig, generate  # noqa: E402
from bokehray.errors import InputError  # noqa: E402


@pytest.fixture(scope="module")
def pairs(tmp_path_factory):
    root = tmp_path_factory.mktemp("synth")
    generate(SynthConfig(size=64, blur_levels=(6.0,), max_spp=16), 2, root, seed=5, workers=1, progress=False)
    return root


@pytest.fixture(scope="module")
def bank(pairs):
    return PairBank(str(pairs), variants=1, seed=0, progress=False)


UNGATED = GateOptions(enabled=False)  # the tiling and blending mechanics, without the confidence gate


def _cfg(pairs, out, **kw):
    base = dict(data=str(pairs), out=str(out), steps=4, batch=2, crop=32, warmup=2, checkpoint_every=2, lr=3e-3,
                variants=1)
    return TrainConfig(**(base | kw))


def test_untrained_model_returns_the_classical_render():
    model = BokehRefiner()
    x, r = torch.rand(2, 3, 32, 40), torch.rand(2, 3, 32, 40)
    out = model(x, r, torch.zeros(2, 32, 40), PisaMaskProvider(np.zeros((2, 32, 40), np.float32), 0.0, 8.0))
    assert torch.equal(out, r)


def test_corruptions_move_edges_the_right_way():
    d = np.zeros((32, 32), np.float32)
    d[8:24, 8:24] = 1.0
    assert corrupt_disparity(d, "erode", 2).sum() < d.sum() < corrupt_disparity(d, "dilate", 2).sum()
    assert np.array_equal(corrupt_disparity(d, "none", 3), d)
    blurred = corrupt_disparity(d, "blur", 4)
    assert 0 < blurred[8, 16] < 1 and blurred.sum() == pytest.approx(d.sum(), rel=0.02)
    shifted = corrupt_disparity(d, "shift", 3, np.random.default_rng(0))
    assert shifted.sum() == pytest.approx(d.sum(), rel=0.5) and not np.array_equal(shifted, d)


def test_edge_loss_is_zero_for_the_target_and_sees_blur():
    g = torch.Generator().manual_seed(0)
    target = torch.rand(1, 3, 24, 24, generator=g)
    focus = torch.rand(1, 3, 24, 24, generator=g)
    assert edge_loss(target, target, focus) == 0
    flat = target.mean(dim=(2, 3), keepdim=True).expand_as(target)
    assert edge_loss(flat, target, focus) > edge_loss(target + 0.01, target, focus)


def test_hardness_ramps_to_k_max():
    cfg = TrainConfig(data=".", out=".", steps=100, hardness_ramp=0.5)
    assert hardness_at(0, cfg) == pytest.approx(cfg.hardness_start)
    assert hardness_at(50, cfg) == pytest.approx(1e6) and hardness_at(99, cfg) == pytest.approx(1e6)
    assert hardness_at(10, cfg) < hardness_at(20, cfg)


def test_training_lowers_the_loss(pairs, tmp_path):
    import csv

    one = PairBank(str(pairs), variants=1, seed=0, limit=1, progress=False)  # one whole 64 x 64 crop: no sampling noise
    cfg = _cfg(pairs, tmp_path, steps=16, batch=1, crop=64, checkpoint_every=16, limit=1, lr=1e-3)
    weights = train(cfg, resume=False, progress=False, bank=one)
    with open(tmp_path / "loss.csv") as f:
        loss = [float(r["loss"]) for r in csv.DictReader(f)]
    assert len(loss) == 16 and loss[-1] < 0.98 * loss[0] and np.mean(loss[-4:]) < np.mean(loss[4:8]) < loss[0]
    assert (tmp_path / "loss.png").is_file() and weights.is_file()
    meta = json.loads(weights.with_suffix(".json").read_text())
    assert meta["steps"] == 16 and meta["fingerprint"] == pytest.approx(fingerprint(load_refiner(weights)))


def test_resume_continues_exactly(pairs, bank, tmp_path):
    straight = train(_cfg(pairs, tmp_path / "a"), resume=False, progress=False, bank=bank)
    early = train(_cfg(pairs, tmp_path / "b"), resume=False, progress=False, bank=bank, stop_at=2)
    assert json.loads(early.with_suffix(".json").read_text())["steps"] == 2
    resumed = train(_cfg(pairs, tmp_path / "b"), resume=True, progress=False, bank=bank)
    from safetensors.torch import load_file

    a, b = load_file(str(straight)), load_file(str(resumed))
    assert all(torch.equal(a[k], b[k]) for k in a)
    with pytest.raises(ValueError, match="different configuration"):
        train(_cfg(pairs, tmp_path / "b", lr=1e-2), resume=True, progress=False, bank=bank)


def test_shipped_weights_load_and_reproduce_their_fingerprint():
    if not DEFAULT_WEIGHTS.is_file():
        pytest.fail(f"the package must ship refiner weights at {DEFAULT_WEIGHTS}")
    meta = json.loads(DEFAULT_WEIGHTS.with_suffix(".json").read_text())
    model = load_refiner()
    assert fingerprint(model) == pytest.approx(meta["fingerprint"], rel=1e-4, abs=1e-5)
    assert fingerprint(model) == fingerprint(model)  # deterministic



def test_bad_weights_are_refused(tmp_path):
    with pytest.raises(InputError, match="no refiner weights"):
        load_refiner(tmp_path / "missing.safetensors")
    bad = tmp_path / "bad.safetensors"
    bad.write_bytes(b"not a safetensors file")
    with pytest.raises(InputError, match="not refiner weights"):
        load_refiner(bad)


def test_refine_leaves_an_in_focus_flat_scene_alone():
    rng = np.random.default_rng(0)
    img = rng.uniform(0, 1, (96, 80, 3)).astype(np.float32)
    d = np.full((96, 80), 0.4, np.float32)
    blur = br.BlurParams(16.0, 0.4)
    classical = br.render(img, d, blur)
    out, stats = refine(img, d, blur, classical, model=BokehRefiner())
    assert stats.tiles_refined == 0 and stats.tiles_total == 4
    assert np.array_equal(out, classical)


def test_refine_touches_only_tiles_near_depth_edges():
    rng = np.random.default_rng(0)
    img = rng.uniform(0, 1, (256, 256, 3)).astype(np.float32)
    d = np.full((256, 256), 0.2, np.float32)
    d[:40, :40] = 0.9  # one near block in a corner
    blur = br.BlurParams(8.0, 0.9)
    need = tiles_to_refine(blur.signed_coc(d), 64, 1.0)
    assert need[0, 0] and need.sum() <= 4 and not need[3, 3]
    model = BokehRefiner()
    with torch.no_grad():
        model.head.bias.fill_(0.05)  # a model that changes every pixel it sees
    classical = br.render(img, d, blur)
    out, stats = refine(img, d, blur, classical, model=model, options=RefineOptions(tile=64, halo=16, gate=UNGATED))
    assert 0 < stats.tiles_refined < stats.tiles_total and stats.share_refined == stats.tiles_refined / 16
    assert np.array_equal(out[160:, 160:], classical[160:, 160:])  # far from the edge: bit-identical
    assert np.abs(out[:40, :40] - classical[:40, :40]).max() > 0.01
    assert np.isfinite(out).all() and out.min() >= 0


def test_full_frame_and_tiled_refinement_blend_the_same_way():
    rng = np.random.default_rng(1)
    img = rng.uniform(0, 1, (128, 96, 3)).astype(np.float32)
    d = np.where(rng.uniform(size=(128, 96)) < 0.5, 0.2, 0.8).astype(np.float32)  # edges everywhere
    blur = br.BlurParams(8.0, 0.8)
    model = BokehRefiner()
    with torch.no_grad():
        model.head.bias.fill_(0.03)  # a constant correction: both paths must place it identically
    classical = br.render(img, d, blur)
    full, s1 = refine(img, d, blur, classical, model=model, options=RefineOptions(gate=UNGATED))
    tiled, s2 = refine(img, d, blur, classical, model=model, options=RefineOptions(full_frame_px=0, gate=UNGATED))
    assert s1.tiles_refined == s2.tiles_refined == s1.tiles_total
    np.testing.assert_allclose(full, tiled, rtol=0, atol=1e-5)
    assert np.abs(full - classical).mean() > 0.01


@pytest.fixture(scope="module")
def weights(tmp_path_factory):
    from pathlib import Path

    from bokehray_refiner.training.residual import export_weights

    model = BokehRefiner()
    with torch.no_grad():
        model.head.bias.fill_(0.02)
    path = Path(tmp_path_factory.mktemp("weights")) / "refiner.safetensors"
    export_weights(model, path, {"fingerprint": fingerprint(model)})
    return path


def test_render_api_refines_and_reports(weights):
    rgb, exact = _edge_scene(2)
    img = np.concatenate([rgb, np.full(rgb.shape[:2] + (1,), 0.7, np.float32)], axis=2)  # RGBA: alpha not refined
    d = np.clip(corrupt_disparity(exact, "erode", 5), 0, 1)  # off the photo's edges: refine finds it wrong,
    # and the fix leaves some of it for the residual network (at 3 px it fixes all, and the gate keeps the render)
    blur = br.BlurParams(10.0, 0.9)
    _, st0 = br.render_with_stats(img, d, blur)
    out, st = br.render_with_stats(img, d, blur, refine=str(weights))
    assert st0.refine is None and st.refine["found_wrong"] and st.refine["fixed_share"] >= 0.01
    assert st.refine["tiles_refined"] > 0 and "refine" in st.stage_seconds
    level = br.render(img, corrected_disparity(img, d, blur)[0], blur)  # the level on the corrected map
    assert np.array_equal(out[..., 3], level[..., 3]) and not np.array_equal(out[..., :3], level[..., :3])
    # the exact map: the depth fix finds it right, so refine leaves the level's render as it is
    same, st_exact = br.render_with_stats(img, exact, blur, refine=str(weights))
    assert not st_exact.refine["found_wrong"] and st_exact.refine["tiles_refined"] == 0
    assert np.array_equal(same, br.render(img, exact, blur))
    flat = np.full(d.shape, 0.5, np.float32)
    same, st_flat = br.render_with_stats(img, flat, br.BlurParams(10.0, 0.5), refine=str(weights))
    assert st_flat.refine["tiles_refined"] == 0 and np.array_equal(same, br.render(img, flat, br.BlurParams(10.0, 0.5)))


def _noise_square_command(tmp_path) -> list[str]:
    """``bokehray render`` of a noise photo with a square's exact map (files in ``tmp_path``), with ``--stats``."""
    rng = np.random.default_rng(3)
    img = rng.uniform(0, 1, (64, 64, 3)).astype(np.float32)
    d = np.full((64, 64), 0.1, np.float32)
    d[20:44, 20:44] = 0.8
    br.write_image(tmp_path / "img.exr", img)
    np.save(tmp_path / "d.npy", d)
    return ["render", str(tmp_path / "img.exr"), "--disparity", str(tmp_path / "d.npy"), "--blur", "12",
            "--focus", "0.8", "--stats"]


def test_cli_refine(weights, tmp_path, capsys):
    from bokehray.app.cli import main

    base = _noise_square_command(tmp_path)
    assert main(base + ["-o", str(tmp_path / "out.exr"), "--refine", str(weights)]) == 0
    text = capsys.readouterr().out
    assert "refined" in text and '"tiles_refined"' in text
    assert main(base + ["-o", str(tmp_path / "bad.exr"), "--refine", str(tmp_path / "none.safetensors")]) == 2
    assert "no refiner weights" in capsys.readouterr().err and not (tmp_path / "bad.exr").exists()


def test_refine_everywhere_refines_a_map_the_depth_fix_finds_right(weights, tmp_path, capsys):
    """The noise photo's exact square: the depth fix finds nothing, so ``--refine`` leaves the preview as it is and
    ``--refine-everywhere`` (``RefineOptions(min_fixed_share=0)``) runs the networks anyway."""
    from bokehray.app.cli import main

    base = _noise_square_command(tmp_path) + ["--refine", str(weights), "-o"]
    stats = lambda text: json.loads(text[text.index("{"):])["refine"]  # noqa: E731
    assert main(base + [str(tmp_path / "kept.exr")]) == 0
    kept = stats(capsys.readouterr().out)
    assert not kept["found_wrong"] and kept["tiles_refined"] == 0
    assert main(base + [str(tmp_path / "all.exr"), "--refine-everywhere"]) == 0
    everywhere = stats(capsys.readouterr().out)
    assert everywhere["found_wrong"] and everywhere["tiles_refined"] > 0
    assert main(base[:-3] + ["-o", str(tmp_path / "no.exr"), "--refine-everywhere"]) == 2
    assert "needs --refine" in capsys.readouterr().err and not (tmp_path / "no.exr").exists()


def test_refine_options_are_checked():
    from bokehray_refiner.refine import RefineOptions

    img = np.zeros((16, 16, 3), np.float32)
    d = np.zeros((16, 16), np.float32)
    with pytest.raises(InputError, match="refine_options: given without refine"):
        br.render(img, d, br.BlurParams(4.0, 0.5), refine_options=RefineOptions())
    with pytest.raises(InputError, match="refine_options: expected"):
        br.render(img, d, br.BlurParams(4.0, 0.5), refine=True, refine_options={"min_fixed_share": 0})


def test_edge_band_follows_each_edges_reach():
    from bokehray_refiner.refine import edge_band, edge_reach

    coc = np.zeros((1, 60), np.float32)
    coc[0, 30:] = 10.0  # one edge at x = 29/30 with CoC 10 on its far side
    reach = edge_reach(coc, 1.0)
    assert reach[0, 29] == 10.0 and reach.sum() == 10.0
    band = edge_band(reach, margin_px=2.0, feather_px=4.0)
    assert band[0, 29] == 1.0 and band[0, 29 + 12] == 1.0  # within CoC + margin
    assert 0.0 < band[0, 29 + 14] < 1.0 and band[0, 29 + 17] == 0.0  # fades out over the feather
    assert np.array_equal(edge_band(np.zeros((4, 4), np.float32), 2.0, 4.0), np.zeros((4, 4), np.float32))


def test_refine_needs_the_preview_quality(weights):
    img = np.zeros((16, 16, 3), np.float32)
    with pytest.raises(InputError, match="preview"):
        br.render(img, np.zeros((16, 16), np.float32), br.BlurParams(4.0, 0.5), quality="raytrace",
                  refine=str(weights))


def test_tile_search_is_bounded_by_the_grid_not_the_blur():
    """Regression: the tile search looped over a window growing with the uncapped CoC (K = 1e5: 125 s on 256 x 256).
    A reach far beyond the image marks every tile, exactly as a reach of the image's size does."""
    from bokehray_refiner.refine import tiles_near

    reach = np.zeros((96, 80), np.float32)
    reach[40, 30] = 1e5
    need = tiles_near(reach, 16)
    assert need.all()
    np.testing.assert_array_equal(need, tiles_near(np.minimum(reach, 200.0), 16))


def _edge_scene(seed: int = 0, size: int = 128):
    """A textured near block over a textured far plane: colour edges exactly on the depth edges."""
    rng = np.random.default_rng(seed)
    from scipy import ndimage

    far = ndimage.gaussian_filter(rng.uniform(0.05, 0.35, (size, size, 3)), (1.5, 1.5, 0)).astype(np.float32)
    near = ndimage.gaussian_filter(rng.uniform(0.5, 0.9, (size, size, 3)), (1.5, 1.5, 0)).astype(np.float32)
    d = np.full((size, size), 0.2, np.float32)
    d[24:104, 20:60] = 0.9
    img = np.where((d > 0.5)[..., None], near, far).astype(np.float32)
    return img, d


def test_gate_trusts_depth_edges_on_colour_edges_and_opens_where_the_map_is_eroded():
    from bokehray_refiner.gate import refine_gate

    from bokehray.colour import linear_to_srgb

    img, d = _edge_scene()
    blur = br.BlurParams(12.0, 0.9)
    f = linear_to_srgb(img)
    gates = {}
    for kind, px in (("none", 0), ("erode", 3), ("dilate", 3)):
        dc = corrupt_disparity(d, kind, px)
        g = refine_gate(img, f, dc, br.render(img, dc, blur), blur.signed_coc(dc), 1.0)
        assert g.dtype == np.float32 and 0.0 <= g.min() and g.max() <= 1.0
        edge = np.abs(np.diff(dc, axis=1)) > 0.1
        gates[kind] = float(g[:, :-1][edge].mean())
    assert gates["none"] < 0.05 < 0.8 < gates["erode"]  # exact: closed; eroded near region: open
    assert gates["dilate"] < 0.05  # too fat near regions: the shipped model is not trusted there
    open_all = refine_gate(img, f, d, img, blur.signed_coc(d), 1.0, GateOptions(enabled=False))
    assert np.array_equal(open_all, np.ones_like(d))
    flat = np.full_like(d, 0.5)
    assert not refine_gate(img, f, flat, img, blur.signed_coc(flat), 1.0).any()  # no depth edge: nothing opens


@pytest.mark.parametrize("which", ["biased", "shipped"])
def test_a_defocused_light_near_a_depth_edge_keeps_its_energy_and_gains_no_core(which):
    img, d = _edge_scene(1)
    yy, xx = np.mgrid[0:128, 0:128]
    light = np.hypot(yy - 64, xx - 76) <= 3.0  # 16 px from the near block's edge, on the far plane
    img[light] = 8.0
    blur = br.BlurParams(16.0, 0.9)  # the light's CoC: 11.2 px, its ball reaches the edge
    dc = corrupt_disparity(d, "erode", 3)  # so that the gate opens along the edge
    model = load_refiner() if which == "shipped" else BokehRefiner()
    if which == "biased":
        with torch.no_grad():
            model.head.bias.fill_(0.05)  # a model that changes every pixel it is allowed to
    classical = br.render(img, dc, blur)
    out, st = refine(img, dc, blur, classical, model=model)
    assert st.tiles_refined > 0 and st.gate_open > 0.05  # the gate is open at the eroded edge...
    ball = np.hypot(yy - 64, xx - 76) <= 11.2 + 2
    assert out[ball].sum() == pytest.approx(classical[ball].sum(), rel=0.02)  # ...but the light keeps its energy
    assert out[light].max() <= 1.02 * classical[light].max()  # and no in-focus core comes back
    assert out[light].max() < 0.5 * 8.0
    assert np.isfinite(out).all()


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**16), k=st.floats(0.0, 40.0), df=st.floats(0.0, 1.0), edges=st.integers(0, 6))
def test_gate_is_a_weight_and_stays_shut_without_depth_edges(seed, k, df, edges):
    from bokehray_refiner.gate import refine_gate

    from bokehray.colour import linear_to_srgb

    rng = np.random.default_rng(seed)
    img = rng.uniform(0, 1.5, (40, 48, 3)).astype(np.float32)  # includes clipped values
    d = np.full((40, 48), rng.uniform(0, 1), np.float32)
    for _ in range(edges):
        y, x = rng.integers(0, 36), rng.integers(0, 44)
        d[y:y + rng.integers(1, 20), x:x + rng.integers(1, 20)] = rng.uniform(0, 1)
    blur = br.BlurParams(k, df)
    coc = blur.signed_coc(d)
    g = refine_gate(img, linear_to_srgb(np.clip(img, 0, 1)), d, img, coc, 1.0)
    assert g.shape == d.shape and np.isfinite(g).all() and g.min() >= 0 and g.max() <= 1
    if not (np.abs(np.diff(coc, axis=0)) > 1).any() and not (np.abs(np.diff(coc, axis=1)) > 1).any():
        assert not g.any()


def test_depth_fix_corrects_the_map_and_renders_the_level_again_before_the_residual():
    img, d = _edge_scene(2)
    blur = br.BlurParams(12.0, 0.9)
    dc = corrupt_disparity(d, "erode", 3)
    calls = []

    def rerender(dd):
        calls.append(dd.copy())
        return br.render(img, dd, blur)

    classical = br.render(img, dc, blur)
    out, st = refine(img, dc, blur, classical, model=BokehRefiner(), rerender=rerender)  # a zero residual
    assert len(calls) == 1 and st.depth_fixed_px > 0 and st.as_dict()["depth_fixed_px"] == st.depth_fixed_px
    assert np.array_equal(st.disparity, calls[0])
    wrong = lambda m: int((np.abs(m - d) > 0.05).sum())  # noqa: E731
    assert wrong(calls[0]) < 0.2 * wrong(dc)  # the eroded near block is back on its colour edge
    np.testing.assert_allclose(out, br.render(img, calls[0], blur), rtol=0, atol=1e-6)
    err = lambda a: float(np.abs(a - br.render(img, d, blur)).mean())  # noqa: E731
    assert err(out) < 0.5 * err(classical)
    # without the callback, or with the fix off, the map and the render stay as given
    same, st0 = refine(img, dc, blur, classical, model=BokehRefiner())
    off, st1 = refine(img, dc, blur, classical, model=BokehRefiner(), rerender=rerender,
                      options=RefineOptions(depthfix=replace(RefineOptions().depthfix, enabled=False)))
    assert st0.depth_fixed_px == st1.depth_fixed_px == 0 and st0.disparity is None and len(calls) == 1
    assert np.array_equal(same, off)


def test_depth_fix_leaves_exact_edges_and_flat_scenes_alone():
    img, d = _edge_scene(3)
    blur = br.BlurParams(12.0, 0.9)
    calls = []
    for dd in (d, np.full_like(d, 0.9)):
        classical = br.render(img, dd, blur)
        out, st = refine(img, dd, blur, classical, model=BokehRefiner(),
                         rerender=lambda x: calls.append(x) or br.render(img, x, blur))
        assert st.depth_fixed_px == 0 and np.array_equal(out, classical)
    assert not calls


def test_render_api_runs_the_depth_fix_and_blurs_alpha_with_the_corrected_map(weights):
    img, d = _edge_scene(4, 96)
    d = d[:96, :96]
    rgba = np.concatenate([img[:96, :96], (d > 0.5)[..., None].astype(np.float32)], axis=2)
    blur = br.BlurParams(10.0, 0.9)
    dc = corrupt_disparity(d, "erode", 3)
    out, st = br.render_with_stats(rgba, dc, blur, refine=str(weights))
    assert st.refine["depth_fixed_px"] > 0 and st.refine["rerender_seconds"] > 0
    plain = br.render(rgba, dc, blur)
    assert not np.array_equal(out[..., 3], plain[..., 3])  # alpha went through the level on the fixed map too


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**16), p=st.floats(0.05, 0.9))
def test_refine_boxes_cover_every_tile_once_inside_its_box(seed, p):
    from bokehray_refiner.refine import refine_boxes

    need = np.random.default_rng(seed).uniform(size=(7, 9)) < p
    boxes = refine_boxes(need, 64, 32)
    members = [m for _, ms in boxes for m in ms]
    assert sorted(members) == sorted((int(y), int(x)) for y, x in zip(*np.nonzero(need)))  # each tile once
    for (ty0, ty1, tx0, tx1), ms in boxes:
        assert ms and all(ty0 <= y < ty1 and tx0 <= x < tx1 for y, x in ms)


def test_merged_boxes_and_single_tiles_blend_the_same_way():
    """Tiles refined as merged boxes (the default) place a correction with the same per-tile blend weights as one
    pass per tile: equal for a model whose correction does not depend on its context."""
    rng = np.random.default_rng(2)
    img = rng.uniform(0, 1, (192, 320, 3)).astype(np.float32)
    d = np.full((192, 320), 0.2, np.float32)
    d[20:70, 30:150] = 0.8  # two separate near blocks: groups of tiles, an uncovered rest
    d[120:170, 250:300] = 0.8
    blur = br.BlurParams(8.0, 0.8)
    model = BokehRefiner()
    with torch.no_grad():
        model.head.bias.fill_(0.03)
    classical = br.render(img, d, blur)
    opts = RefineOptions(full_frame_px=0, gate=UNGATED)
    merged, s1 = refine(img, d, blur, classical, model=model, options=opts)
    single, s2 = refine(img, d, blur, classical, model=model, options=replace(opts, merge_tiles=False))
    assert 0 < s1.tiles_refined == s2.tiles_refined < s1.tiles_total
    np.testing.assert_allclose(merged, single, rtol=0, atol=1e-5)
    assert np.abs(merged - classical).mean() > 1e-3


def test_render_refine_renders_the_level_once_and_equals_fixing_an_existing_render(weights):
    """``render --refine`` corrects the map first and renders the level once, on the corrected map: the same image
    as rendering, correcting, then rendering again."""
    img, d = _edge_scene(2)
    blur = br.BlurParams(12.0, 0.9)
    dc = corrupt_disparity(d, "erode", 3)
    model = load_refiner(weights)
    calls = []

    def rerender(dd):
        calls.append(dd)
        return br.render(img, dd, blur)

    once, st1 = refine(img, dc, blur, None, model=model, rerender=rerender)
    assert len(calls) == 1 and st1.depth_fixed_px > 0 and np.array_equal(calls[0], st1.disparity)
    twice, _st2 = refine(img, dc, blur, br.render(img, dc, blur), model=model, rerender=rerender)
    np.testing.assert_array_equal(once, twice)
    api, st = br.render_with_stats(img, dc, blur, refine=str(weights))
    np.testing.assert_allclose(api, once, rtol=0, atol=1e-6)
    assert st.refine["depth_fixed_px"] == st1.depth_fixed_px
    flat = np.full_like(d, 0.9)  # nothing to correct: the level renders once on the given map
    calls.clear()
    out, st3 = refine(img, flat, blur, None, model=model, rerender=rerender)
    assert len(calls) == 1 and calls[0] is flat and st3.depth_fixed_px == 0
    np.testing.assert_array_equal(out, br.render(img, flat, blur))
    with pytest.raises(InputError):
        refine(img, dc, blur, None, model=model)


def test_missing_strands_vanish_from_the_map_and_large_regions_keep_their_outline():
    d = np.full((48, 48), 0.1, np.float32)
    d[10:30, 10:30] = 0.9  # a body
    d[5:45, 38:40] = 0.9  # a 2 px strand
    out = corrupt_disparity(d, "missing", 2)
    assert np.all(out[5:45, 38:40] == pytest.approx(0.1))  # the strand is gone: the background's depth
    assert np.array_equal(out[12:28, 12:28], d[12:28, 12:28]) and out[10, 20] == 0.9 and out[20, 10] == 0.9
    assert np.array_equal(corrupt_disparity(d, "missing", 0), d)


def test_local_misplacement_moves_edges_by_at_most_the_amount_and_not_all_the_same_way():
    d = np.full((192, 192), 0.1, np.float32)
    d[:, 96:] = 0.9  # one long vertical edge
    out = corrupt_disparity(d, "local", 12, np.random.default_rng(1))
    assert set(np.unique(out)) <= {np.float32(0.1), np.float32(0.9)}  # edges stay steps: no new depths
    cols = np.array([np.argmax(row > 0.5) for row in out])  # where each row's edge went
    moved = cols - 96
    assert np.abs(moved).max() <= 12 and np.ptp(moved) >= 4  # each stretch of the edge moved its own way
    assert np.array_equal(corrupt_disparity(d, "local", 12, np.random.default_rng(1)), out)  # deterministic


def test_pair_bank_makes_the_input_refine_makes_and_caches_it(pairs, tmp_path):
    from bokehray_refiner.refine import correct_and_render

    from bokehray.colour import linear_to_srgb
    from bokehray.data.datasets import BLBDataset

    bank = PairBank(str(pairs), variants=1, seed=3, limit=2, progress=False, probs=(0, 0, 0, 0, 0, 0, 1.0, 0))
    s = BLBDataset(str(pairs))[0]
    blur = br.BlurParams(s.k_px, s.focus_disparity)
    dc = np.clip(corrupt_disparity(s.disparity, "local", 0), 0, 1)  # amount 0 is the exact map: a known input
    assert bank.pairs[0].kinds == ["local"]
    rendered, used = correct_and_render(s.image, dc, blur, lambda d: br.render(s.image, d, blur))
    exact = PairBank(str(pairs), variants=1, seed=3, limit=1, progress=False, probs=(1.0, 0, 0, 0, 0, 0, 0, 0))
    expect = linear_to_srgb(np.clip(rendered[..., :3], 0, 1)).astype(np.float16)
    assert np.array_equal(exact.pairs[0].renders[0], expect)
    assert np.array_equal(exact.pairs[0].disparities[0], used.astype(np.float16))
    path = tmp_path / "bank.npz"
    first = PairBank.cached(path, str(pairs), progress=False, variants=1, seed=3, limit=2)
    again = PairBank.cached(path, str(pairs), progress=False, variants=1, seed=3, limit=2)
    for a, b in zip(first.pairs, again.pairs):
        assert all(np.array_equal(x, y) for x, y in zip(a.renders + a.bands + a.disparities,
                                                         b.renders + b.bands + b.disparities))
        assert a.kinds == b.kinds and np.array_equal(a.target, b.target) and np.array_equal(a.focus, b.focus)
    other = PairBank.cached(path, str(pairs), progress=False, variants=1, seed=4, limit=2)  # another key: rebuilt
    assert other.pairs[0].kinds != first.pairs[0].kinds or not np.array_equal(other.pairs[0].renders[0],
                                                                             first.pairs[0].renders[0])


def test_pair_bank_corrects_each_map_at_each_focus(pairs, monkeypatch):
    """The map-level gate and the edge network read the CoC, which depends on the focus: a scene's corrupted map is
    corrected anew for each of its foci, not once per scene and K."""
    import bokehray_refiner.refine as refine_module

    from bokehray.data.datasets import BLBDataset

    seen = []
    real = refine_module.correct_and_render

    def recording(image, disparity, blur, rerender, options):
        seen.append((blur.k_px, blur.focus_disparity, disparity.copy()))
        return real(image, disparity, blur, rerender, options)

    monkeypatch.setattr(refine_module, "correct_and_render", recording)
    bank = PairBank(str(pairs), variants=2, seed=3, limit=2, progress=False)
    ds = BLBDataset(str(pairs))
    assert ds[0].name.split("/")[0] == ds[1].name.split("/")[0] and ds[0].focus_disparity != ds[1].focus_disparity
    assert [(k, f) for k, f, _ in seen] == [(ds[i].k_px, ds[i].focus_disparity) for i in range(2) for _ in range(2)]
    assert all(np.array_equal(seen[j][2], seen[2 + j][2]) for j in range(2))  # the same corrupted maps at both foci
    assert len(bank.pairs) == 2


def test_a_gated_bank_weighs_each_input_as_refine_blends_it(pairs):
    """Training behind the gate: the loss weight is the band times the confidence gate, as refine() blends."""
    from bokehray_refiner.refine import RefineOptions, blend_weight

    from bokehray.colour import linear_to_srgb
    from bokehray.data.datasets import BLBDataset

    probs = (0, 0.5, 0, 0, 0, 0, 0.5, 0)  # eroded or locally misplaced edges: the gate opens somewhere
    gated = PairBank(str(pairs), variants=2, seed=1, limit=2, progress=False, probs=probs, gated=True)
    plain = PairBank(str(pairs), variants=2, seed=1, limit=2, progress=False, probs=probs)
    ds = BLBDataset(str(pairs))
    for i, (g, p) in enumerate(zip(gated.pairs, plain.pairs)):
        assert all(np.array_equal(a, b) for a, b in zip(g.renders, p.renders))  # same inputs, other weights
        s = ds[i]
        blur = br.BlurParams(s.k_px, s.focus_disparity)
        for d, w, wp in zip(g.disparities, g.bands, p.bands):
            linear = br.render(s.image, d.astype(np.float32), blur)
            coc = blur.signed_coc(d.astype(np.float32)).astype(np.float32)
            band, weight = blend_weight(s.image, linear_to_srgb(np.clip(s.image, 0, 1)), d.astype(np.float32),
                                        linear, coc, RefineOptions())
            # the bank stores the map in float16, from which this recomputes it: equal up to that rounding
            assert np.abs(w.astype(np.float32) - weight).max() < 0.02
            assert np.abs(wp.astype(np.float32) - band).max() < 0.02
            assert np.all(w <= wp)
    assert any((w > 0).any() for p in gated.pairs for w in p.bands)  # the gate let something through
    assert any(((w == 0) & (wp > 0)).any() for p, q in zip(gated.pairs, plain.pairs)
               for w, wp in zip(p.bands, q.bands))  # and closed something


def test_batches_mark_the_crops_of_exact_inputs(pairs, tmp_path):
    """``exact`` marks crops rendered on the exact map (the ones --exact-weight weighs), and only those."""
    exact = PairBank(str(pairs), variants=1, seed=3, limit=2, progress=False, probs=(1.0, 0, 0, 0, 0, 0, 0, 0))
    local = PairBank(str(pairs), variants=1, seed=3, limit=2, progress=False, probs=(0, 0, 0, 0, 0, 0, 1.0, 0))
    rng = np.random.default_rng(0)
    assert exact.batch(rng, 4, 32)["exact"].all() and not local.batch(rng, 4, 32)["exact"].any()
    with pytest.raises(InputError, match="exact_weight"):
        _cfg(pairs, tmp_path, exact_weight=-1.0)
    import csv

    for weight, zero in ((0.0, True), (1.0, False)):  # weight 0: the exact inputs' band error does not count
        out = tmp_path / f"w{weight}"
        train(_cfg(pairs, out, steps=2, batch=4, edge_share=1.0, exact_weight=weight, behind_gate=False),
              resume=False, progress=False, bank=exact)
        with open(out / "loss.csv") as f:
            mse = [float(r["mse"]) for r in csv.DictReader(f)]
        assert all(m == 0.0 for m in mse) == zero


def test_edge_crops_are_centred_on_the_band(bank):
    b = bank.batch(np.random.default_rng(0), 16, 32, edge_share=1.0)
    assert (b["band"][:, 16, 16] > 0).mean() >= 0.9  # crop centres (clamped only at the image border)


def test_gate_without_the_agreement_opens_the_whole_band_but_guards_lights():
    from bokehray_refiner.gate import refine_gate

    rng = np.random.default_rng(0)
    img = rng.uniform(0.1, 0.6, (48, 48, 3)).astype(np.float32)
    d = np.full((48, 48), 0.1, np.float32)
    d[:, 24:] = 0.9
    img[:, 24:] *= 0.3  # a colour edge right on the depth edge: the agreement closes the gate there
    img[4, 4] = 5.0  # a clipped light far from the edge, within its own reach
    coc = 20.0 * (d - 0.1)
    srgb = br.colour.linear_to_srgb(np.clip(img, 0, 1))
    shut = refine_gate(img, srgb, d, img, coc, 1.0, GateOptions())
    free = refine_gate(img, srgb, d, img, coc, 1.0, GateOptions(agreement=False))
    assert shut[:, 20:28].max() < 0.5 and free[20:28, 20:28].min() == 1.0
    assert free[4, 4] == 0.0  # the highlight guard still holds
    assert np.array_equal(refine_gate(img, srgb, np.full_like(d, 0.5), img, np.zeros_like(coc), 1.0,
                                      GateOptions(agreement=False)), np.zeros_like(d))


def test_refine_leaves_a_map_the_depth_fix_finds_right_as_the_level_rendered_it(monkeypatch):
    """A map whose edges sit on the photo's: the depth fix moves (almost) nothing, so refine changes nothing: its few
    moves are dropped, no network runs, and the render is the level's on the given map, bit for bit. With
    ``min_fixed_share=0`` the same moves are kept and the residual network runs (behind no confidence gate, which
    would trust these edges)."""
    import bokehray_refiner.refine as refine_module

    img, d = _edge_scene(3)
    blur = br.BlurParams(12.0, 0.9)
    few = d.copy()
    few[24, 20:25] = 0.2  # five pixels of the near block's corner: far below 1 % of the band
    monkeypatch.setattr(refine_module, "correction_steps", lambda *a, **k: ((0, 0), d, few))
    seen, runs = [], []
    model = BokehRefiner().eval()
    model.register_forward_hook(lambda *a: runs.append(1))
    rer = lambda dd: seen.append(dd.copy()) or br.render(img, dd, blur)  # noqa: E731
    out, st = refine(img, d, blur, None, model=model, rerender=rer)
    assert not st.found_wrong and 0 < st.fixed_share < 0.01 and st.depth_fixed_px == 0 and st.disparity is None
    assert len(seen) == 1 and np.array_equal(seen[0], d) and not runs and st.tiles_refined == 0
    np.testing.assert_array_equal(out, br.render(img, d, blur))
    assert not refine_module.corrected_disparity(img, d, blur, RefineOptions(edges=False))[1].any()
    seen.clear()
    _, st0 = refine(img, d, blur, None, model=model, rerender=rer,
                    options=RefineOptions(min_fixed_share=0.0, edges=False, gate=GateOptions(enabled=False)))
    assert st0.found_wrong and st0.depth_fixed_px == 5 and np.array_equal(seen[0], few) and runs


def test_a_map_shifted_back_as_a_whole_is_rendered_shifted_without_the_networks(monkeypatch):
    """The depth fix's global shift moves every pixel, which is no evidence that edges are misplaced locally: where the
    local passes then move under ``min_fixed_share`` of the band, the shifted map is rendered and no network runs (the
    edge network on a map the shift made right punched holes in it: -2.9 dB on the dev set's 2 px shift)."""
    import bokehray_refiner.refine as refine_module
    from bokehray_refiner.depthfix import shift_map

    img, d = _edge_scene(4)
    blur = br.BlurParams(12.0, 0.9)
    given = shift_map(d, 0, 2)  # misregistered by 2 px
    monkeypatch.setattr(refine_module, "correction_steps", lambda *a, **k: ((0, -2), d, d))
    seen, runs = [], []
    model = BokehRefiner().eval()
    model.register_forward_hook(lambda *a: runs.append(1))
    edge_model = refine_module.load_edge_net()
    edge_model.register_forward_hook(lambda *a: runs.append(1))
    out, st = refine(img, given, blur, None, model=model, edge_model=edge_model,
                     rerender=lambda dd: seen.append(dd.copy()) or br.render(img, dd, blur))
    assert not st.found_wrong and st.fixed_share == 0.0 and not runs
    assert len(seen) == 1 and np.array_equal(seen[0], d) and st.depth_fixed_px == int((d != given).sum())
    np.testing.assert_array_equal(out, br.render(img, d, blur))


def test_a_map_the_depth_fix_takes_for_noise_is_refined_as_without_the_fix():
    """On a map of noise the depth fix does not run (``correction_steps`` says so with no shift), so there is no
    evidence either way: the residual network runs, as with the fix off, and nothing counts as moved."""
    from bokehray_refiner.depthfix import correct_disparity, correction_steps

    from bokehray.colour import linear_to_srgb

    img, d = _edge_scene(5)
    noisy = np.clip(d + np.random.default_rng(5).normal(0.0, 0.15, d.shape), 0, 1).astype(np.float32)
    blur = br.BlurParams(12.0, 0.9)
    focus = linear_to_srgb(np.clip(img, 0, 1))
    shift, _, out = correction_steps(focus, noisy, blur.k_px)
    assert shift is None and np.array_equal(out, noisy)
    nan_map = noisy.copy()
    nan_map[0, 0] = np.nan
    assert not correct_disparity(focus, nan_map, 0.0)[1].any()  # not run: nothing moved, NaN or not
    _, st = refine(img, noisy, blur, None, model=BokehRefiner().eval(), rerender=lambda dd: br.render(img, dd, blur),
                   options=RefineOptions(gate=GateOptions(enabled=False)))
    assert st.found_wrong and st.fixed_share is None and st.depth_fixed_px == 0 and st.tiles_refined > 0
