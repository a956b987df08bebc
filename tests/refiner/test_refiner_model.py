"""``--refiner-model DIR`` and ``RefineOptions(model=DIR)``: a one-step diffusion checkpoint with PISA attention from a
local diffusers-layout folder (a tiny one, built here) renders the frame; weights that do not fit its config are
refused in one line naming the folder."""

import json
import shutil

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("diffusers")

from bokehray_refiner.onestep import load_one_step  # noqa: E402
from bokehray_refiner.onestep.testing import write_tiny_sdxl  # noqa: E402
from bokehray_refiner.refine import RefineOptions  # noqa: E402

import bokehray as br  # noqa: E402
from bokehray.app.cli import main  # noqa: E402
from bokehray.errors import InputError  # noqa: E402


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    return write_tiny_sdxl(tmp_path_factory.mktemp("tiny-sdxl"))


@pytest.fixture(scope="module")
def misfit(tiny, tmp_path_factory):
    """The tiny model with a config its U-Net's weights do not fit (cross-attention 48 wide, the weights 64)."""
    path = tmp_path_factory.mktemp("misfit") / "model"
    shutil.copytree(tiny, path)
    cfg = json.loads((path / "unet" / "config.json").read_text())
    cfg["cross_attention_dim"] = 48
    (path / "unet" / "config.json").write_text(json.dumps(cfg))
    return path


def _scene(h=48, w=64):
    rng = np.random.default_rng(4)
    img = rng.uniform(0, 1, (h, w, 3)).astype(np.float32)
    d = np.full((h, w), 0.2, np.float32)
    d[12:36, 16:48] = 0.9
    return img, d


def test_the_api_renders_with_the_one_step_model_on_the_device_given(tiny):
    img, d = _scene()
    blur = br.BlurParams(8.0, 0.9)
    out, stats = br.render_with_stats(img, d, blur, refine=True, refine_options=RefineOptions(model=str(tiny)),
                                      device="cpu")
    want = load_one_step(tiny).render(img, d, blur)
    assert out.shape == img.shape and np.isfinite(out).all()
    np.testing.assert_array_equal(out, want)
    assert stats.refine["tiles_refined"] == stats.refine["tiles_total"] >= 1
    shipped = br.render(img, d, blur, refine=True)  # without the option: the shipped networks, another image
    assert not np.array_equal(shipped, out)


def test_the_command_line_renders_with_refiner_model_and_implies_refine(tiny, tmp_path, capsys):
    img, d = _scene()
    br.write_image(tmp_path / "img.exr", img)
    np.save(tmp_path / "d.npy", d)
    base = ["render", str(tmp_path / "img.exr"), "--disparity", str(tmp_path / "d.npy"), "--blur", "8", "--focus",
            "0.9", "--device", "cpu"]
    assert main(base + ["-o", str(tmp_path / "out.exr"), "--refiner-model", str(tiny)]) == 0
    assert "refined" in capsys.readouterr().out
    got = br.read_image(tmp_path / "out.exr")
    np.testing.assert_allclose(got[..., :3], load_one_step(tiny).render(img, d, br.BlurParams(8.0, 0.9)), atol=1e-3)


def test_weights_that_do_not_fit_the_config_are_refused_naming_the_folder(misfit, tmp_path, capsys):
    img, d = _scene()
    br.write_image(tmp_path / "img.exr", img)
    np.save(tmp_path / "d.npy", d)
    out = tmp_path / "out.exr"
    rc = main(["render", str(tmp_path / "img.exr"), "--disparity", str(tmp_path / "d.npy"), "--blur", "8",
               "--focus", "0.9", "-o", str(out), "--refiner-model", str(misfit)])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1, err
    assert str(misfit) in err[0] and "do not fit unet/config.json" in err[0]
    assert not out.exists()
    with pytest.raises(InputError, match="do not fit unet/config.json"):
        br.render(img, d, br.BlurParams(8.0, 0.9), refine=True, refine_options=RefineOptions(model=str(misfit)))


@pytest.mark.parametrize("extra, words", [
    (["--refiner-model", "{tmp}/nowhere"], "not a folder"),
    (["--refiner-model", "{tiny}", "--refine", "{tmp}/w.safetensors"], "takes no --refine WEIGHTS"),
    (["--refiner-model", "{tiny}", "--refine-everywhere"], "replaces them"),
])
def test_refiner_model_refusals_are_one_line(tiny, tmp_path, capsys, extra, words):
    img, d = _scene(16, 16)
    br.write_image(tmp_path / "img.exr", img)
    np.save(tmp_path / "d.npy", d)
    extra = [e.format(tmp=tmp_path, tiny=tiny) for e in extra]
    rc = main(["render", str(tmp_path / "img.exr"), "--disparity", str(tmp_path / "d.npy"), "--blur", "8",
               "--focus", "0.9", "-o", str(tmp_path / "o.exr"), *extra])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and words in err[0], err
    assert not (tmp_path / "o.exr").exists()


def test_lora_and_encoder_weights_in_the_folder_load_on_top(tmp_path):
    """A folder holding lora/ and encoder.safetensors (BokehDiff's fine-tuning) renders with both; they change it."""
    full = write_tiny_sdxl(tmp_path / "full", lora=True, encoder_weights=True)
    img, d = _scene(32, 32)
    blur = br.BlurParams(8.0, 0.9)
    out = br.render(img, d, blur, refine=True, refine_options=RefineOptions(model=str(full)))
    want = load_one_step(full, lora=full / "lora", encoder_weights=full / "encoder.safetensors").render(img, d, blur)
    np.testing.assert_array_equal(out, want)
    assert not np.array_equal(out, load_one_step(full).render(img, d, blur))
