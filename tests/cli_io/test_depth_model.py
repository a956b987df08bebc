"""--depth-model: Depth Anything and DPT checkpoints from a local folder, tested on tiny random models of the same
architectures that the test builds and saves itself (never a download), and the polarity of their outputs."""

import json

import numpy as np
import pytest

torch = pytest.importorskip("torch")
transformers = pytest.importorskip("transformers")

import bokehray as br  # noqa: E402
from bokehray.app.cli import main  # noqa: E402
from bokehray.photo import depth_model  # noqa: E402
from bokehray.photo.depth import normalize_relative  # noqa: E402

PRE = {"size": {"height": 56, "width": 56}, "keep_aspect_ratio": True, "ensure_multiple_of": 14,
       "image_mean": [0.485, 0.456, 0.406], "image_std": [0.229, 0.224, 0.225]}


def _save(model, folder, pre=None):
    transformers.utils.logging.disable_progress_bar()
    model.save_pretrained(folder)
    if pre is not None:
        (folder / "preprocessor_config.json").write_text(json.dumps(pre))
    return folder


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    root = tmp_path_factory.mktemp("depth-models")
    torch.manual_seed(0)
    cfg, dpt_cfg = depth_model.tiny_configs()
    da = _save(transformers.DepthAnythingForDepthEstimation(cfg).eval(), root / "da", PRE)
    metric_cfg = transformers.DepthAnythingConfig(**{**cfg.to_dict(), "depth_estimation_type": "metric",
                                                     "max_depth": 20})
    metric_model = transformers.DepthAnythingForDepthEstimation(metric_cfg).eval()
    last = [m for m in metric_model.head.modules() if isinstance(m, torch.nn.Conv2d)][-1]
    with torch.no_grad():  # a random head's sigmoid sits at 0.5 everywhere: spread it so depth varies
        last.weight *= 300.0
        last.bias.zero_()
    metric = _save(metric_model, root / "da-metric", PRE)
    dpt = _save(transformers.DPTForDepthEstimation(dpt_cfg).eval(), root / "dpt")
    return {"da": da, "metric": metric, "dpt": dpt}


@pytest.fixture(scope="module")
def photo():
    rng = np.random.default_rng(0)
    img = np.zeros((40, 60, 3), np.float32)
    img[:] = np.linspace(0, 1, 60, dtype=np.float32)[None, :, None]
    img[10:30, 20:40] = rng.random((20, 20, 3))
    return img


def _raw(folder, img):
    cfg = json.loads((folder / "config.json").read_text())
    cls = (transformers.DepthAnythingForDepthEstimation if cfg["model_type"] == "depth_anything"
           else transformers.DPTForDepthEstimation)
    th, tw, mean, std = depth_model.input_size(folder, cfg, *img.shape[:2])
    return depth_model.predict(cls.from_pretrained(str(folder), local_files_only=True).eval(), img, (th, tw), mean, std)


def _rank_corr(a, b):
    ra, rb = np.argsort(np.argsort(a.ravel())), np.argsort(np.argsort(b.ravel()))
    return float(np.corrcoef(ra, rb)[0, 1])


@pytest.mark.parametrize("name", ["da", "dpt"])
def test_relative_models_near_is_large(models, photo, name):
    """Relative models predict inverse depth: the larger the prediction, the nearer, so disparity follows it."""
    d, info = depth_model.estimate_disparity(photo, models[name])
    assert d.shape == photo.shape[:2] and d.dtype == np.float32 and d.min() >= 0 and d.max() <= 1
    assert info["kind"] == "relative"
    raw = _raw(models[name], photo)
    inside = (d > 0) & (d < 1)  # outside the percentile clip, ties
    assert _rank_corr(raw[inside], d[inside]) > 0.999
    np.testing.assert_allclose(d, normalize_relative(raw), atol=1e-6)


def test_metric_model_near_is_small(models, photo):
    """A metric model predicts metres: the larger the prediction, the farther, so disparity runs against it."""
    d, info = depth_model.estimate_disparity(photo, models["metric"])
    assert info["kind"] == "metric" and "1/z" in info["what"]
    raw = _raw(models["metric"], photo)
    assert _rank_corr(raw, d) < -0.999
    assert d[np.unravel_index(np.argmin(raw), raw.shape)] == pytest.approx(1.0)  # the nearest point is nearest


def test_input_size_follows_the_processor():
    cfg = {"model_type": "depth_anything"}
    from pathlib import Path

    nowhere = Path("/nonexistent-folder")
    assert depth_model.input_size(nowhere, cfg, 3000, 4000)[:2] == (518, 686)  # short side 518, multiple of 14
    assert depth_model.input_size(nowhere, {"model_type": "dpt", "image_size": 384}, 3000, 4000)[:2] == (384, 384)


@pytest.mark.parametrize(("setup", "message"), [
    (lambda p: None, "no depth model there|there is none"),
    (lambda p: p.mkdir(), "no config.json"),
    (lambda p: (p.mkdir(), (p / "config.json").write_text('{"model_type": "bert"}')), "'bert' is not a supported"),
    (lambda p: (p.mkdir(), (p / "config.json").write_text('{"model_type": "dpt"}')), "cannot load"),
])
def test_bad_model_folders_are_one_line_errors(tmp_path, photo, setup, message):
    folder = tmp_path / "model"
    setup(folder)
    with pytest.raises(br.InputError, match=message):
        depth_model.estimate_disparity(photo, folder)


def test_a_hub_name_is_not_downloaded(photo, monkeypatch):
    monkeypatch.chdir("/tmp")
    with pytest.raises(br.InputError, match="there is none"):
        depth_model.estimate_disparity(photo, "depth-anything/Depth-Anything-V2-Small-hf")


def test_cli_depth_model_renders_and_saves_the_map(models, photo, tmp_path, capsys):
    img = br.write_image(tmp_path / "p.png", photo)
    code = main(["render", str(img), "--depth-model", str(models["da"]), "-o", str(tmp_path / "o.jpg"),
                 "--save-depth"])
    out = capsys.readouterr()
    assert code == 0, out.err
    assert "depth: estimated by the Depth Anything (V1/V2) model" in out.out and "Loading" not in out.err
    saved = tmp_path / "o-disparity.png"
    assert f"saved to {saved}" in out.out
    want, _ = depth_model.estimate_disparity(br.read_image(img), models["da"])
    np.testing.assert_allclose(br.read_disparity(saved), want, atol=1 / 65535 + 1e-6)
    code = main(["render", str(img), "--depth-model", str(models["da"]), "-o", str(tmp_path / "x.png"),
                 "--normalize"])
    assert code == 2 and "--normalize" in capsys.readouterr().err


def test_view_estimates_the_map_as_render_does_and_exports_the_same_image(models, photo, tmp_path, capsys):
    """bokehray view --depth-model: the page's map is render's map, and its export is what the shown command writes."""
    pytest.importorskip("starlette")
    import shlex

    from bokehray.app.view.session import ViewSession, parse_params

    img = br.write_image(tmp_path / "p.png", photo)
    session = ViewSession.from_files(str(img), depth_model=str(models["da"]), export_dir=tmp_path)
    want, _ = depth_model.estimate_disparity(br.read_image(img), models["da"])
    np.testing.assert_array_equal(session.disparity, want)
    p = parse_params({"blur": 6.0, "focus": 0.5}, session.disparity)
    written, command = session.export(p, "png", None)
    argv = shlex.split(command)
    assert argv[argv.index("--depth-model") + 1] == str(models["da"].resolve())
    argv[argv.index("-o") + 1] = str(tmp_path / "again.png")
    assert main(argv[1:]) == 0, capsys.readouterr().err
    assert (tmp_path / "again.png").read_bytes() == written.read_bytes()


def _variant(models, tmp_path, name, edit=None, pre=None):
    """A copy of the tiny checkpoint ``name`` with its config.json edited and/or a preprocessor_config.json."""
    import shutil

    folder = tmp_path / f"{name}-variant"
    shutil.copytree(models[name], folder)
    if edit is not None:
        cfg = json.loads((folder / "config.json").read_text())
        edit(cfg)
        (folder / "config.json").write_text(json.dumps(cfg))
    if pre is not None:
        (folder / "preprocessor_config.json").write_text(json.dumps(pre))
    return folder


_BAD_CHECKPOINTS = {  # reliability findings: (checkpoint, config edit, preprocessor, message)
    "weights of another model_type": ("da", lambda c: c.update(model_type="dpt"), None,
                                      "the weights do not fit the DPT model its config.json describes: 14 missing"),
    "a processor config that is a list": ("da", None, [56, 56], "expected a JSON object"),
    "size as a string": ("da", None, {"size": "56"}, "size: expected a positive integer, got '56'"),
    "size of -1": ("da", None, {"size": {"height": -1, "width": 56}}, "size.height: expected a positive integer"),
    "image_mean of length 1": ("da", None, {"image_mean": [0.5]}, "image_mean: expected three finite numbers"),
    "image_std of 0": ("da", None, {"image_std": [0, 1, 1]}, "image_std: expected three finite numbers > 0"),
    "ensure_multiple_of 0": ("da", None, {"ensure_multiple_of": 0}, "ensure_multiple_of: expected a positive"),
    "a 100000 px input": ("da", None, {"size": {"height": 100000, "width": 100000}}, "size: expected at most 8192 px"),
    "100000 backbone layers": ("da", lambda c: c["backbone_config"].update(num_hidden_layers=100000), None,
                               "declares 100000 layers 32 wide (at least 409,600,000 parameters), but the weights"),
    "100000 DPT layers": ("dpt", lambda c: c.update(num_hidden_layers=100000), None, "declares 100000 layers"),
    "layers as a string": ("dpt", lambda c: c.update(num_hidden_layers="4"), None,
                           "num_hidden_layers: expected a positive integer, got '4'"),
    # round four, item 13: the library's two-line message was embedded
    "max_depth NaN": ("metric", lambda c: c.update(max_depth=float("nan")), None,
                      "config.json: max_depth: expected a positive integer, got nan"),
}


@pytest.mark.parametrize("case", sorted(_BAD_CHECKPOINTS))
def test_checkpoints_that_do_not_fit_are_refused_naming_the_file(models, photo, tmp_path, case):
    """Each was a traceback, a silent render from random layers, torch's raw allocation error or minutes of
    building a model that cannot be loaded."""
    name, edit, pre, message = _BAD_CHECKPOINTS[case]
    folder = _variant(models, tmp_path, name, edit, pre)
    with pytest.raises(br.InputError) as e:
        depth_model.estimate_disparity(photo, folder)
    assert message in str(e.value) and str(folder) in str(e.value) and "\n" not in str(e.value)


def test_an_input_beyond_memory_is_refused_from_the_declared_size(models, photo, tmp_path, monkeypatch):
    import bokehray._memory

    folder = _variant(models, tmp_path, "da", pre={"size": {"height": 4000, "width": 4000}})
    monkeypatch.setattr(bokehray._memory, "available_bytes", lambda: 1 << 30)
    with pytest.raises(br.ResourceError, match=r"the model at an input of \d+ x \d+ px needs about .* MB, but only "
                       "1,024 MB"):
        depth_model.estimate_disparity(photo, folder)


def test_cli_refuses_mismatched_weights_in_one_line(models, photo, tmp_path, capsys):
    folder = _variant(models, tmp_path, "da", lambda c: c.update(model_type="dpt"))
    img = br.write_image(tmp_path / "p.png", photo)
    code = main(["render", str(img), "--depth-model", str(folder), "-o", str(tmp_path / "o.png")])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and err.startswith(f"bokehray: error: {folder}: the weights do not fit")
    assert not (tmp_path / "o.png").exists()


def test_a_multi_line_loading_error_is_one_line(models, photo, monkeypatch):
    """The library's validation messages span lines (``Validation error for field ...:\\n    TypeError: ...``): they
    are joined, so the command line's refusal stays one line."""

    def failing(*args, **kwargs):
        raise ValueError("Validation error for field 'x':\n    TypeError: Field 'x' with value nan doesn't match")

    monkeypatch.setattr(transformers.DepthAnythingForDepthEstimation, "from_pretrained", failing)
    with pytest.raises(br.InputError) as e:
        depth_model.estimate_disparity(photo, models["da"])
    assert "\n" not in str(e.value) and "Validation error for field 'x': TypeError: Field 'x'" in str(e.value)
