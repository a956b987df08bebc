"""The one-step diffusion wrapper, end to end on a tiny SDXL-layout model the test writes itself."""

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("diffusers")

from bokehray_refiner.masks import PisaMaskProvider  # noqa: E402
from bokehray_refiner.onestep import OneStepOptions, load_one_step  # noqa: E402
from bokehray_refiner.onestep.processor import PassThroughAttnProcessor, PISAAttnProcessor  # noqa: E402
from bokehray_refiner.onestep.testing import write_tiny_sdxl  # noqa: E402
from bokehray_refiner.tiles import blend_tiles, tile_grid  # noqa: E402

from bokehray.errors import InputError  # noqa: E402
from bokehray.lens import BlurParams  # noqa: E402


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    return write_tiny_sdxl(tmp_path_factory.mktemp("tiny-sdxl"), lora=True, encoder_weights=True)


def _scene(h=64, w=80):
    rng = np.random.default_rng(0)
    img = rng.uniform(0, 1, (h, w, 3)).astype(np.float32)
    d = np.full((h, w), 0.3, np.float32)
    d[20:40, 20:50] = 0.9
    return img, d


def test_pipeline_runs_end_to_end_and_is_deterministic(tiny):
    model = load_one_step(tiny)
    img, d = _scene()
    out = model.render(img, d, BlurParams(8.0, 0.9))
    assert out.shape == img.shape and out.dtype == np.float32 and np.isfinite(out).all()
    assert 0.0 <= out.min() and out.max() <= 1.0
    np.testing.assert_array_equal(out, model.render(img, d, BlurParams(8.0, 0.9)))
    # PISA is in the down blocks' self-attention and only there.
    procs = model.unet.attn_processors
    assert model.pisa_layers == [n for n in procs if n.startswith("down_blocks") and ".attn1." in n]
    assert all(isinstance(procs[n], PISAAttnProcessor) for n in model.pisa_layers)
    assert all(type(p) is PassThroughAttnProcessor for n, p in procs.items() if n not in model.pisa_layers)


def test_one_step_formula(tiny):
    from diffusers import DDPMScheduler

    model = load_one_step(tiny)
    abar = float(DDPMScheduler.from_pretrained(tiny / "scheduler").alphas_cumprod[499])
    assert model.alpha == pytest.approx(abar ** 0.5) and model.beta == pytest.approx((1 - abar) ** 0.5)
    x = torch.rand(1, 3, 32, 32)
    pisa = PisaMaskProvider(np.full((32, 32), 0.5, np.float32), 0.2, 6.0)
    z_t = model.encode(x)
    with torch.no_grad():
        eps = model.unet(z_t, torch.tensor([499]), encoder_hidden_states=model.prompt_embeds,
                         added_cond_kwargs={"text_embeds": model.pooled_prompt_embeds,
                                            "time_ids": torch.tensor([[32.0, 32, 0, 0, 32, 32]])},
                         cross_attention_kwargs={"pisa": pisa}).sample
        torch.testing.assert_close(model.denoise(z_t, pisa), (z_t - model.beta * eps) / model.alpha)


def test_masks_reach_the_attention(tiny):
    model = load_one_step(tiny)
    x = torch.rand(1, 3, 32, 32)
    flat = PisaMaskProvider(np.full((32, 32), 0.5, np.float32), 0.5, 6.0)  # all in focus
    blurry = PisaMaskProvider(np.full((32, 32), 0.0, np.float32), 1.0, 6.0)  # all out of focus
    with torch.no_grad():
        a, b = model(x, flat), model(x, blurry)
    assert (a - b).abs().max() > 1e-4
    assert set(flat._cache) == {(4, 4), (2, 2)}  # one mask set per PISA grid: latent 1/8 and its 1/2


def test_lora_and_encoder_weights_load_and_act(tiny):
    img, d = _scene(32, 32)
    p = BlurParams(8.0, 0.9)
    base = load_one_step(tiny).render(img, d, p)
    with_lora = load_one_step(tiny, lora=tiny / "lora").render(img, d, p)
    with_enc = load_one_step(tiny, encoder_weights=tiny / "encoder.safetensors").render(img, d, p)
    assert np.abs(with_lora - base).max() > 1e-4
    assert np.abs(with_enc - base).max() > 1e-4


def test_fixed_prompt_embedding_replaces_text_encoders(tiny, tmp_path):
    import shutil

    from safetensors.torch import save_file

    model = load_one_step(tiny)
    local = tmp_path / "no-text"
    for sub in ("unet", "vae", "scheduler"):
        shutil.copytree(tiny / sub, local / sub)
    save_file({"prompt_embeds": model.prompt_embeds.contiguous(),
               "pooled_prompt_embeds": model.pooled_prompt_embeds.contiguous()}, str(local / "prompt_embeds.safetensors"))
    img, d = _scene(32, 32)
    np.testing.assert_array_equal(load_one_step(local).render(img, d, BlurParams(4.0, 0.3)),
                                  model.render(img, d, BlurParams(4.0, 0.3)))


def test_tiled_render_bounds_tile_size_and_covers_the_image(tiny):
    model = load_one_step(tiny, options=OneStepOptions(tile=32, overlap=8))
    assert model.size_multiple == 16
    img, d = _scene(48, 70)  # not a multiple of the model's size constraint: tiles are padded
    out = model.render(img, d, BlurParams(8.0, 0.9))
    assert out.shape == img.shape and np.isfinite(out).all()


def test_tiles_cover_the_image_and_cross_fade_in_overlaps():
    grid = tile_grid((50, 77), 24, 8, multiple=8)
    boxes = [b for b, _ in grid]
    assert all((y1 - y0 + ph) % 8 == 0 and (x1 - x0 + pw) % 8 == 0 for (y0, y1, x0, x1), (ph, pw) in grid)
    covered = np.zeros((50, 77), int)
    for y0, y1, x0, x1 in boxes:
        covered[y0:y1, x0:x1] += 1
    assert covered.min() >= 1
    # Two tiles of constant 0 and 1 overlapping by 8 columns: 0 and 1 outside, a rising ramp inside.
    boxes = [(0, 4, 0, 24), (0, 4, 16, 40)]
    tiles = [np.zeros((4, 24, 1), np.float32), np.ones((4, 24, 1), np.float32)]
    row = blend_tiles(tiles, boxes, (4, 40), 8)[0, :, 0]
    assert np.all(row[:16] == 0) and np.all(row[24:] == 1)
    ramp = row[16:24]
    assert np.all(np.diff(ramp) > 0) and 0 < ramp[0] < 0.1 and 0.9 < ramp[-1] < 1
    np.testing.assert_allclose(ramp + ramp[::-1], 1.0, atol=1e-6)  # symmetric cross-fade


def test_prediction_types(tiny):
    model = load_one_step(tiny)
    z = torch.rand(1, 4, 4, 4)
    pisa = PisaMaskProvider(np.full((32, 32), 0.5, np.float32), 0.2, 6.0)
    with torch.no_grad():
        eps_form = model.denoise(z, pisa)
        out = (z - eps_form * model.alpha) / model.beta  # the network's raw output, recovered
        model.prediction_type = "v_prediction"
        torch.testing.assert_close(model.denoise(z, pisa), model.alpha * z - model.beta * out, rtol=1e-4, atol=1e-5)
        model.prediction_type = "sample"
        torch.testing.assert_close(model.denoise(z, pisa), out, rtol=1e-4, atol=1e-5)


def test_processor_matches_pisa_attention_on_a_non_square_grid():
    from bokehray_refiner.attention import pisa_attention
    from bokehray_refiner.pisa import pisa_masks
    from diffusers.models.attention_processor import Attention

    torch.manual_seed(0)
    attn = Attention(query_dim=16, heads=2, dim_head=8)
    attn.set_processor(PISAAttnProcessor())
    d = np.random.default_rng(0).uniform(0, 1, (6, 10)).astype(np.float32)
    pisa = PisaMaskProvider(d, 0.3, 20.0)
    x = torch.randn(1, 3 * 5, 16)  # tokens of the 3 x 5 grid (image / 2)
    with torch.no_grad():
        got = attn(x, pisa=pisa)
        m = pisa.at(3, 5)
        small = torch.nn.functional.interpolate(torch.from_numpy(d)[None, None], size=(3, 5), mode="area")[0, 0]
        ref_masks = pisa_masks(small.numpy(), 0.3, 20.0 * 5 / 10, window=m.window)
        np.testing.assert_array_equal(m.coc[0].numpy(), ref_masks.coc.numpy())  # K rescaled with the grid
        grid = lambda t: t.view(1, 3, 5, 2, 8).permute(0, 3, 1, 2, 4)  # noqa: E731
        out = pisa_attention(grid(attn.to_q(x)), grid(attn.to_k(x)), grid(attn.to_v(x)), m.coc, m.visibility,
                             m.window, scale=attn.scale)
        want = attn.to_out[0](out.permute(0, 2, 3, 1, 4).reshape(1, 15, 16))
    torch.testing.assert_close(got, want)


def test_bad_model_directories_are_refused(tiny, tmp_path):
    with pytest.raises(InputError, match="not a diffusers model directory"):
        load_one_step(tmp_path)
    with pytest.raises(InputError, match="LoRA weights not found"):
        load_one_step(tiny, lora=tmp_path)
    with pytest.raises(InputError, match="timestep"):
        load_one_step(tiny, options=OneStepOptions(timestep=5000))
    model = load_one_step(tiny)
    img, d = _scene(32, 32)
    with pytest.raises(InputError, match="disparity"):
        model.render(img, d[:16], BlurParams(4.0, 0.3))


def test_provider_grid_matching():
    pisa = PisaMaskProvider(np.zeros((2, 33, 50), np.float32), [0.1, 0.2], 4.0)
    assert pisa.grid_for_tokens(33 * 50) == (33, 50)
    assert pisa.grid_for_tokens(17 * 25) == (17, 25)
    with pytest.raises(ValueError, match="tokens"):
        pisa.grid_for_tokens(7)
    m = pisa.at(17, 25)
    assert m.coc.shape == (2, 17, 25, (2 * m.window + 1) ** 2)
