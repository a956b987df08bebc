"""bokehray bench: Pareto extraction, EBB protocol on known answers, peers, the runner and the CLI."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from scipy import ndimage

from bokehray.app.bench import Method, SynthSplit, pareto_front, registry, run_bench, select
from bokehray.app.bench.ebb import focus_from_mask, focus_from_sharpness, search_k
from bokehray.app.bench.peers import NaiveScatter, coc_radius_map
from bokehray.app.bench.run import Case, dominators, ebb_cases, perturb_disparity, robustness_subset, synth_cases
from bokehray.data.datasets import write_blb_scene
from bokehray.errors import InputError

# ----------------------------------------------------------------------------- Pareto


def test_pareto_front_hand_made():
    pts = {"a": (1.0, 30.0), "b": (2.0, 32.0), "c": (2.0, 31.0), "d": (0.5, 20.0), "e": (3.0, 32.0),
           "f": (1.0, 30.0)}
    # c is beaten by b (as fast, better); e by b (faster, as good); a and f tie and both stay
    assert pareto_front(pts) == ["d", "a", "f", "b"]
    assert dominators("c", pts, list(pts)) == ["b"]
    assert dominators("a", pts, list(pts)) == []
    assert pareto_front({}) == []


# ----------------------------------------------------------------------------- EBB protocol


def _texture(h=64, w=64, seed=0):
    rng = np.random.default_rng(seed)
    return ndimage.zoom(rng.random((h // 4, w // 4, 3)), (4, 4, 1), order=1).astype(np.float32)


def test_k_search_finds_the_known_blur():
    img = _texture()

    def render(k):  # a stand-in renderer whose blur grows with K
        return ndimage.gaussian_filter(img, (k / 10.0, k / 10.0, 0), mode="nearest")

    target = render(23.0)
    k, ssim, evals = search_k(render, target, 0.0, 64.0, tol=0.1)
    assert k == pytest.approx(23.0, abs=0.15) and ssim == pytest.approx(1.0, abs=1e-4) and evals <= 24


def test_focus_from_sharpness_and_mask():
    img = _texture(64, 64, 1)
    target = img.copy()
    target[:, 32:] = ndimage.gaussian_filter(img, (3, 3, 0))[:, 32:]  # right half defocused
    disp = np.full((64, 64), 0.2, np.float32)
    disp[:, :32] = 0.8  # the sharp half is at disparity 0.8
    assert focus_from_sharpness(target, disp) == pytest.approx(0.8)
    mask = np.zeros((64, 64), np.float32)
    mask[10:20, 40:50] = 1.0
    assert focus_from_mask(disp, mask) == pytest.approx(0.2)
    with pytest.raises(InputError, match="empty"):
        focus_from_mask(disp, np.zeros((64, 64)))
    with pytest.raises(InputError, match="pixels"):
        focus_from_mask(disp, np.ones((8, 8)))


def _write_ebb(root: Path, gain: float = 1.5, k_true: float = 4.0) -> None:
    from bokehray.output.write import write_disparity, write_image

    img = _texture(48, 48, 2)
    disp = np.full((48, 48), 0.25, np.float32)
    disp[12:36, 12:36] = 0.75
    target = NaiveScatter()(img, disp, k_true, 0.75) * np.float32(gain)
    for sub in ("input", "target", "disparity", "mask"):
        (root / sub).mkdir(parents=True)
    write_image(root / "input" / "a.exr", img)
    write_image(root / "target" / "a.exr", target)
    write_disparity(root / "disparity" / "a.exr", disp)
    mask = np.zeros((48, 48, 3), np.float32)
    mask[20:28, 20:28] = 1.0
    write_image(root / "mask" / "a.png", mask)


def test_ebb_protocol_known_answer(tmp_path):
    _write_ebb(tmp_path, gain=1.5, k_true=4.0)
    (case,) = ebb_cases(tmp_path)
    assert case.focus_disparity == pytest.approx(0.75) and case.focus_source == "salient mask"
    assert case.exposure_gain == pytest.approx(1.5, rel=0.02)  # the scatter keeps the mean up to borders
    naive = [m for m in registry() if m.name == "naive-scatter"]
    res = run_bench([case], naive, runs=1, k_range=(0.0, 12.0), log=lambda s: None)
    row = res["per_image"][0]
    assert row["k_px"] == pytest.approx(4.0, abs=0.3)
    assert row["aligned_psnr"] > 40 > row["psnr"]  # alignment removes the exposure error


# ----------------------------------------------------------------------------- peers and perturbations


def test_naive_scatter_keeps_a_constant_image_and_spreads_a_point():
    disp = np.linspace(0, 1, 30 * 30, dtype=np.float32).reshape(30, 30)
    const = np.full((30, 30, 3), 0.3, np.float32)
    np.testing.assert_allclose(NaiveScatter()(const, disp, 6.0, 0.5), 0.3, rtol=1e-6)
    point = np.zeros((31, 31, 3), np.float32)
    point[15, 15] = 1.0
    out = NaiveScatter()(point, np.full((31, 31), 0.5, np.float32), 8.0, 0.0)  # r = 4 everywhere
    w = lambda dist: (0.5 + 0.5 * math.tanh(4 * (4 - dist))) / (16 + 0.2)  # noqa: E731
    # interior pixels receive from all their neighbours alike, so out = w(dist) / sum of all weights
    total = sum(w(math.hypot(dy, dx)) for dy in range(-5, 6) for dx in range(-5, 6))
    assert out[15, 15, 0] == pytest.approx(w(0) / total, rel=1e-6)
    assert out[15, 18, 0] == pytest.approx(w(3) / total, rel=1e-6)
    assert out[15, 21, 0] == 0.0 and out[..., 0].sum() == pytest.approx(1.0, rel=1e-6)
    assert coc_radius_map(np.array([[0.0, 1.0]]), 10.0, 0.25).tolist() == [[2.5, 7.5]]


def test_perturb_disparity_is_a_disc_erosion_or_dilation():
    d = np.zeros((11, 11), np.float32)
    d[5, 5] = 1.0
    assert perturb_disparity(d, 2).sum() == 13  # disc of radius 2: 13 pixels
    assert perturb_disparity(d, -1).sum() == 0
    np.testing.assert_array_equal(perturb_disparity(1 - d, -2), 1 - perturb_disparity(d, 2))
    np.testing.assert_array_equal(perturb_disparity(d, 0), d)


# ----------------------------------------------------------------------------- runner


def _case(seed=0, size=32) -> Case:
    img = _texture(size, size, seed)
    disp = np.full((size, size), 0.2, np.float32)
    disp[8:24, 8:24] = 0.9
    return Case(f"c{seed}", img, disp, NaiveScatter()(img, disp, 6.0, 0.9), 6.0, 0.9)


def test_runner_skips_missing_and_failing_methods_without_crashing():
    def boom():
        def render(*a):
            raise RuntimeError("peer crashed")
        return render

    methods = [m for m in registry() if m.name == "naive-scatter"] + [
        Method("absent", "peer", "not installed", boom, unavailable=lambda: "module 'x' not installed"),
        Method("crashing", "peer", "raises", boom),
    ]
    logs = []
    res = run_bench([_case()], methods, runs=2, robustness_cases=1, robustness_radii=(-1, 1), log=logs.append)
    assert set(res["skipped"]) == {"absent", "crashing"} and "not installed" in res["skipped"]["absent"]
    assert list(res["summary"]) == ["naive-scatter"]
    s = res["summary"]["naive-scatter"]
    assert s["psnr"] > 60 and s["time_min"] <= s["time_median"] <= s["time_max"]  # it is its own truth
    assert set(s["robustness_drop_db"]) == {"-1", "1"} and all(v < 0 for v in s["robustness_drop_db"].values())
    assert res["per_image"][0]["runs"] == 2


def test_robustness_cases_spread_over_the_list():
    assert robustness_subset(list(range(24)), 4) == [0, 8, 15, 23]
    assert robustness_subset([1, 2], 5) == [1, 2] and robustness_subset([1, 2], 0) == []


def test_select_and_registry():
    names = [m.name for m in registry()]
    assert len(names) == len(set(names)) and "preview" in names
    assert {m.family for m in registry()} == {"bokehray", "peer"}
    assert [m.name for m in select("preview,naive-scatter", False)] == ["preview", "naive-scatter"]
    assert "preview" in [m.name for m in select(None, True)]
    with pytest.raises(InputError, match="unknown method"):
        select("preview,nope", False)


def test_synth_split_is_cached(tmp_path):
    split = SynthSplit(scenes=1, size=40, blur_levels=(5.0,), max_spp=4, seed=7)
    cases, root = synth_cases(split, tmp_path, workers=1, progress=False, log=lambda s: None)
    assert len(cases) == 2 and cases[0].k_px == 5.0 and (root / "COMPLETE").is_file()
    stamp = (root / "scene_00000" / "image.exr").stat().st_mtime_ns
    again, _ = synth_cases(split, tmp_path, workers=1, progress=False, log=lambda s: pytest.fail(s))
    assert (root / "scene_00000" / "image.exr").stat().st_mtime_ns == stamp
    np.testing.assert_array_equal(again[1].target, cases[1].target)


# ----------------------------------------------------------------------------- CLI


def _blb(root: Path, n: int = 2, size: int = 40) -> None:
    for i in range(n):
        c = _case(i, size)
        info = {"blur_parameters": [3.0, 6.0], "focus_disparities": [0.9]}
        renders = [{"k_index": k, "f_index": 0, "image": NaiveScatter()(c.image, c.disparity, kk, 0.9)}
                   for k, kk in enumerate(info["blur_parameters"])]
        write_blb_scene(root / f"s{i}", c.image, c.disparity, renders, info, previews=False)


def _bench(capsys, *args: str) -> tuple[int, str, str]:
    from bokehray.app.cli import main

    capsys.readouterr()
    try:
        rc = main(["bench", "--quiet", *args])
    except SystemExit as e:  # argparse errors
        rc = e.code
    out = capsys.readouterr()
    return rc, out.out, out.err


def test_cli_smoke_is_deterministic(tmp_path, capsys):
    _blb(tmp_path / "blb")
    outs = []
    for run in ("r1", "r2"):
        rc, stdout, stderr = _bench(capsys, "--blb", str(tmp_path / "blb"), "--blb-level", "1", "--methods", "preview,naive-scatter",
                   "--runs", "1", "--robustness", "1", "--out", str(tmp_path / run))
        assert rc == 0, stderr
        outs.append(json.loads((tmp_path / run / "bench_blb-l1.json").read_text()))
    assert "peers both faster and more accurate than preview:" in stdout
    for name in ("bench_blb-l1.csv", "bench_blb-l1.md", "bench_blb-l1_pareto.png", "bench_blb-l1_robustness.png"):
        assert (tmp_path / "r2" / name).stat().st_size > 0
    keys = ("psnr", "ssim", "band_psnr", "band_ssim")
    errs = [[(r["case"], r["method"], *(r[k] for k in keys)) for r in o["per_image"]] for o in outs]
    assert errs[0] == errs[1] and len(errs[0]) == 4  # bit for bit: same floats in the JSON
    assert outs[0]["summary"]["naive-scatter"]["psnr"] > 60  # the truth was made by it
    assert outs[0]["dataset"]["images"] == 2 and outs[0]["machine"]["cores"] >= 1


def test_cli_bad_input_is_one_line(tmp_path, capsys):
    rc, _, err = _bench(capsys, "--ebb", str(tmp_path / "missing"))
    assert rc == 2 and err.count("\n") == 1 and "does not exist" in err
    rc, _, err = _bench(capsys, "--methods", "nope", "--blb", str(tmp_path))
    assert rc == 2 and "unknown method" in err
    rc, _, err = _bench(capsys, "--runs", "0")
    assert rc == 2 and "--runs" in err
