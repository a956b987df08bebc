"""The command line: every path a user takes, and every error path (exit 2, one line, no output file)."""

import contextlib
import json
import math

import numpy as np
import pytest

import bokehray as br
from bokehray.app.batch import parse_sweep
from bokehray.app.cli import main


@pytest.fixture
def scene(tmp_path):
    rng = np.random.default_rng(3)
    h, w = 48, 64
    img = rng.random((h, w, 3)).astype(np.float32) * 0.8
    d = np.tile(np.linspace(0, 1, w, dtype=np.float32), (h, 1))
    depth = (1.0 / (0.2 + 0.8 * d)).astype(np.float32)  # metres: 1.25 .. 5
    paths = {
        "png": br.write_image(tmp_path / "in.png", img),
        "exr": br.write_image(tmp_path / "in.exr", img),
        "disp_png": br.write_disparity(tmp_path / "d.png", d),
        "disp_npy": br.write_disparity(tmp_path / "d.npy", d),
        "depth": tmp_path / "z.npy",
    }
    np.save(paths["depth"], depth)
    return paths, img, d


def run(capsys, *args):
    code = main([str(a) for a in args])
    out = capsys.readouterr()
    return code, out.out, out.err


@pytest.mark.parametrize("out_name", ["o.png", "o.jpg", "o.tif", "o.exr"])
def test_render_writes_every_output_format(scene, tmp_path, capsys, out_name):
    p, _, _ = scene
    code, out, err = run(capsys, "render", p["png"], "--disparity", p["disp_png"], "-o", tmp_path / out_name,
                         "--blur", 6, "--focus", 0.5)
    assert code == 0, err
    assert (tmp_path / out_name).exists() and "wrote" in out
    assert br.read_image(tmp_path / out_name).shape == (48, 64, 3)


def test_render_matches_the_python_api(scene, tmp_path, capsys):
    p, _img, d = scene
    code, _, err = run(capsys, "render", p["exr"], "--disparity", p["disp_npy"], "-o", tmp_path / "o.exr",
                       "--blur", 8, "--focus", 0.3, "--aperture", "polygon", "--blades", 5, "--rotation", 10,
                       "--curvature", 0.3)
    assert code == 0, err
    want = br.render(br.read_image(p["exr"]), d, br.BlurParams(8, 0.3), br.Aperture(5, 10, 0.3))
    np.testing.assert_allclose(br.read_image(tmp_path / "o.exr"), want, atol=1e-6)


def test_focus_at_and_stats(scene, tmp_path, capsys):
    p, _, d = scene
    code, out, err = run(capsys, "render", p["png"], "--disparity", p["disp_png"], "-o", tmp_path / "o.png",
                         "--blur", 6, "--focus-at", "32,10", "--stats")
    assert code == 0, err
    stats = json.loads(out[out.index("{"):])
    assert stats["blur"]["focus_disparity"] == pytest.approx(float(np.median(d[6:15, 28:37])), abs=1e-4)
    stages = stats["stage_seconds"]
    assert {"read", "depth", "focus", "warp start", "checks", "soft maps", "edges", "plan", "layers", "output",
            "write", "total"} <= set(stages)
    # every stage of the command is on the clock: they sum to its total (laps of one clock; no bound on the time)
    assert sum(v for k, v in stages.items() if k != "total") == pytest.approx(stages["total"], rel=0.05, abs=0.01)
    assert stats["tiles_total"] > 0 and "max_coc_px" in stats


def test_the_printed_time_is_the_stats_total(scene, tmp_path, capsys):
    p, _, _ = scene
    code, out, err = run(capsys, "render", p["png"], "--disparity", p["disp_png"], "-o", tmp_path / "o.png",
                         "--blur", 6, "--stats")
    assert code == 0, err
    total = json.loads(out[out.index("{"):])["stage_seconds"]["total"]
    printed = float(out.split(" s)")[0].rsplit(", ", 1)[1])
    assert printed == pytest.approx(total, abs=0.006)


@pytest.mark.parametrize("blur", [("--blur", "-0"), ("--amount", "-0")])
def test_negative_zero_blur_and_focus_are_said_as_zero(scene, tmp_path, capsys, blur):
    """``--blur -0 --focus -0`` printed ``K = -0.000 px, d_f = -0.0000`` and ``"K_px": -0.0`` in --stats."""
    p, _, _ = scene
    code, out, err = run(capsys, "render", p["png"], "--disparity", p["disp_png"], "-o", tmp_path / "o.png",
                         *blur, "--focus", "-0", "--stats")
    assert code == 0, err
    assert "(K = 0.000 px, d_f = 0.0000, max CoC 0.0 px" in out
    if blur[0] == "--amount":
        assert "blur: --amount 0 -> K = 0.0 px (0.0% of" in out
    stats = out[out.index("{"):]
    values = json.loads(stats)
    assert "-0.0" not in stats and "-0," not in stats
    for v in (values["blur"]["K_px"], values["blur"]["focus_disparity"], values["max_coc_px"]):
        assert v == 0.0 and math.copysign(1.0, v) == 1.0
    for given in (br.BlurParams(-0.0, -0.0), br.BlurParams(np.float32(-0.0), -0)):  # the API alike
        assert math.copysign(1.0, given.k_px) == math.copysign(1.0, given.focus_disparity) == 1.0
    for v in (parse_sweep("-0"), *parse_sweep("-0,0.5"), *parse_sweep("-0:1:3")):
        assert math.copysign(1.0, v) == 1.0


def test_physical_lens_with_metric_depth(scene, tmp_path, capsys):
    p, _img, _ = scene
    code, out, err = run(capsys, "render", p["png"], "--depth", p["depth"], "-o", tmp_path / "o.exr",
                         "--focal-length", 50, "--f-number", 2.0, "--focus-distance", 2.0, "--sensor-width", 36,
                         "--no-grain")  # the render itself: the grain step is a finishing step after it
    assert code == 0, err
    z = np.load(p["depth"])
    d, norm = br.disparity_from_depth(z)
    blur = br.ThinLens(50, 2.0, 2.0, 36).blur_params(norm, 64)
    want = br.render(br.read_image(p["png"]), d, blur)
    np.testing.assert_allclose(br.read_image(tmp_path / "o.exr"), want, atol=1e-6)
    assert f"K = {blur.k_px:.3f}" in out


def test_resize_disparity(tmp_path, scene, capsys):
    p, _, d = scene
    small = br.write_disparity(tmp_path / "small.npy", d[::2, ::2].copy())
    code, _, err = run(capsys, "render", p["png"], "--disparity", small, "-o", tmp_path / "o.png", "--blur", 4,
                       "--focus", 0.5)
    assert code == 2 and "--resize-disparity" in err and not (tmp_path / "o.png").exists()
    code, _, err = run(capsys, "render", p["png"], "--disparity", small, "-o", tmp_path / "o.png", "--blur", 4,
                       "--focus", 0.5, "--resize-disparity")
    assert code == 0, err


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--disparity", "missing.png", "--blur", 4, "--focus", 0.5], "does not exist"),
        (["--disparity", "{disp_png}", "--blur", -1, "--focus", 0.5], "K >= 0"),
        (["--disparity", "{disp_png}", "--blur", 4, "--focus", 1.5], r"\[0, 1\]"),
        (["--disparity", "{disp_png}", "--blur", 4, "--focus", 0.5, "--focus-at", "3,4"], "contradict"),
        (["--depth", "{depth}", "--focal-length", 50, "--f-number", 2, "--focus-distance", 2, "--focus-at", "3,4"],
         "--focus-at and --focus-distance contradict"),
        (["--disparity", "{disp_png}", "--amount", 130], r"\[0, 100\]"),
        (["--disparity", "{bad_disp}"], "--normalize"),
        (["--depth", "{depth}", "--normalize"], "relative --disparity"),
        (["--disparity", "{disp_png}", "--depth-scale", 0.001], "needs --depth"),
        (["--disparity", "{disp_png}", "--jpeg-quality", 0], "--jpeg-quality"),
        (["--disparity", "{disp_png}", "--focal-length", 50, "--f-number", 2, "--focus-distance", 2],
         "needs metric depth.*--depth.*--depth-scale"),
        (["--depth", "{depth}", "--focal-length", 50, "--focus-distance", 2], "--f-number"),
        (["--disparity", "{bad_disp}", "--blur", 4, "--focus", 0.5], r"\[0, 1\]"),
        (["--disparity", "{nan_disp}", "--blur", 4, "--focus", 0.5], "NaN"),
        (["--disparity", "{disp_png}", "--blur", 4, "--focus", 0.5, "--device", "cuda:7"], "device"),
        (["--disparity", "{disp_png}", "--blur", 4, "--focus", 0.5, "--bit-depth", 32], "PNG takes --bit-depth 8 or 16, not 32"),
    ],
)
def test_bad_input_exits_2_with_one_line_and_no_output(scene, tmp_path, capsys, args, message):
    p, _, d = scene
    np.save(tmp_path / "bad.npy", d * 2)
    nan = d.copy()
    nan[3, 4] = np.nan
    np.save(tmp_path / "nan.npy", nan)
    fmt = {k: str(v) for k, v in p.items()} | {"bad_disp": tmp_path / "bad.npy", "nan_disp": tmp_path / "nan.npy"}
    args = [str(a).format(**fmt) for a in args]
    target = tmp_path / "out.png"
    code, _out, err = run(capsys, "render", p["png"], *args, "-o", target)
    assert code == 2
    assert err.startswith("bokehray: error:") and err.count("\n") == 1, err
    assert pytest.importorskip("re").search(message, err), err
    assert not target.exists()


def test_corrupt_image_and_unsupported_output(tmp_path, scene, capsys):
    p, _, _ = scene
    (tmp_path / "broken.png").write_bytes(p["png"].read_bytes()[:100])
    code, _, err = run(capsys, "render", tmp_path / "broken.png", "--disparity", p["disp_png"], "-o",
                       tmp_path / "o.png", "--blur", 4, "--focus", 0.5)
    assert code == 2 and "broken.png" in err
    code, _, err = run(capsys, "render", p["png"], "--disparity", p["disp_png"], "-o", tmp_path / "o.gif",
                       "--blur", 4, "--focus", 0.5)
    assert code == 2 and "unsupported extension" in err


def test_existing_output_survives_a_failed_render(tmp_path, scene, capsys):
    p, _, _ = scene
    target = tmp_path / "keep.png"
    target.write_bytes(b"good")
    code, _, _ = run(capsys, "render", p["png"], "--disparity", p["disp_png"], "-o", target, "--blur", 4,
                     "--focus", 3.0)
    assert code == 2 and target.read_bytes() == b"good"


def test_debug_shows_the_traceback(scene, tmp_path):
    p, _, _ = scene
    with pytest.raises(br.InputError):
        main(["render", str(p["png"]), "--disparity", str(p["disp_png"]), "-o", str(tmp_path / "o.png"),
              "--blur", "4", "--focus", "2", "--debug"])


def test_demo_writes_everything_it_announces(tmp_path, capsys):
    code, out, err = run(capsys, "demo", "-o", tmp_path / "demo", "--size", "192,128")
    assert code == 0, err
    names = {"input.png", "input.exr", "disparity.png", "render_focus_near.png", "render_focus_far.png",
             "focal_stack.png", "render_focus_near.exr", "render_focus_far.exr"}
    assert names <= {f.name for f in (tmp_path / "demo").iterdir()}
    for name in names:
        assert str(tmp_path / "demo" / name) in out
    near = br.read_image(tmp_path / "demo" / "render_focus_near.exr")
    far = br.read_image(tmp_path / "demo" / "render_focus_far.exr")
    assert near.shape == (128, 192, 3) and not np.allclose(near, far)


def test_version(capsys):
    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0 and "bokehray" in capsys.readouterr().out


def test_physical_lens_focus_at_a_pixel(scene, tmp_path, capsys):
    p, _, _ = scene
    code, out, err = run(capsys, "render", p["png"], "--depth", p["depth"], "-o", tmp_path / "o.png",
                         "--focal-length", 35, "--f-number", 1.8, "--focus-at", "40,20", "--stats")
    assert code == 0, err
    z = np.load(p["depth"])
    d, _norm = br.disparity_from_depth(z)
    stats = json.loads(out[out.index("{"):])
    assert stats["blur"]["focus_disparity"] == pytest.approx(br.focus_at(d, 40, 20), abs=1e-4)


def test_render_does_not_offer_the_ray_tracer_for_photos(scene, tmp_path, capsys):
    """On photos the ray tracer is slower than the preview and not more accurate (docs/raytracer.md): one line
    points to the preview, before anything is read; --help lists the preview alone."""
    p, _, _ = scene
    code, _out, err = run(capsys, "render", p["png"], "--disparity", p["disp_png"], "-o", tmp_path / "o.exr",
                         "--blur", 6, "--focus", 0.5, "--quality", "raytrace")
    assert code == 2 and err.count("\n") == 1 and not (tmp_path / "o.exr").exists()
    assert err.startswith("bokehray: error: --quality raytrace: on photos the ray tracer is slower than the preview")
    code, _, err = run(capsys, "render", p["png"], "--disparity", p["disp_png"], "-o", tmp_path / "o.exr",
                       "--quality", "fast")
    assert code == 2 and "--quality: expected one of preview, got 'fast'" in err
    with pytest.raises(SystemExit) as exit_:
        main(["render", "--help"])
    assert exit_.value.code == 0 and "--quality {preview}" in capsys.readouterr().out


@pytest.mark.parametrize(
    "argv",
    [
        ["render", "x.png", "--disparity", "d.png"],  # no -o
        ["render", "x.png", "-o", "o.png"],  # neither --disparity nor --depth
        ["render", "x.png", "--disparity", "d.png", "-o", "o.png", "--focus-at", "5"],
        ["render", "x.png", "--disparity", "d.png", "-o", "o.png", "--blur", "4", "--amount", "30"],
        ["frobnicate"],
    ],
)
def test_usage_errors_are_one_line_with_exit_2(argv, capsys):
    with pytest.raises(SystemExit) as e:
        main(argv)
    err = capsys.readouterr().err
    assert e.value.code == 2
    assert err.startswith("bokehray: error:") and err.count("\n") == 1, err


@pytest.mark.parametrize(
    "argv,message",
    [
        (["demo", "--size", "-5,10"], "demo size: expected width and height >= 64, got -5 x 10"),
        (["render", "{png}", "--disparity", "{disp}", "-o", "{out}", "--blur", "4", "--focus-at", "-1,0"],
         "focus point: expected 0 <= x < 64 and 0 <= y < 48, got (-1, 0)"),
        (["render", "{png}", "--disparity", "{disp}", "-o", "{out}", "--blur", "4", "--focus-at", "-3,-2"],
         "got (-3, -2)"),
    ],
)
def test_negative_number_pairs_are_values_not_options(scene, tmp_path, capsys, argv, message):
    """Regression: argparse took ``--focus-at -1,0`` for an option ("expected one argument")."""
    p, _, _ = scene
    argv = [a.format(png=p["png"], disp=p["disp_png"], out=tmp_path / "o.png") for a in argv]
    code, _, err = run(capsys, *argv)
    assert code == 2 and err.count("\n") == 1 and message in err, err
    assert not (tmp_path / "o.png").exists()


def test_a_demo_size_beyond_memory_is_one_line(tmp_path, capsys, monkeypatch):
    """``demo --size 100000,100000`` allocated its coordinate grids first: NumPy's raw MemoryError, a traceback."""
    import bokehray.validate

    monkeypatch.setattr(bokehray.validate, "available_bytes", lambda: 1 << 30)
    code, _, err = run(capsys, "demo", "-o", tmp_path / "demo", "--size", "100000,100000", "--quiet")
    assert code == 2 and err.count("\n") == 1, err
    assert err.startswith("bokehray: error: demo size: 100000 x 100000 px needs about"), err
    assert not (tmp_path / "demo").exists()


def _fill_disk_at(monkeypatch, name: str) -> None:
    """The disk fills up when the demo writes ``name`` (the earlier files are written whole)."""
    import errno
    import os

    from bokehray.output import write as wr

    real = wr.encode_pil

    def encode(tmp, codes, fmt, **options):
        if f".{name}." in os.path.basename(tmp):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        real(tmp, codes, fmt, **options)

    monkeypatch.setattr(wr, "encode_pil", encode)


def test_a_demo_that_fails_removes_the_folder_it_made(tmp_path, capsys, monkeypatch):
    """A full disk left the demo's folder behind (empty, or holding the files written before the disk filled); the
    folder the demo made, and any parent it made, are removed now, and the error is still one line."""
    _fill_disk_at(monkeypatch, "render_focus_near.png")
    out = tmp_path / "new" / "demo"
    code, stdout, err = run(capsys, "demo", "-o", out, "--size", "96,64")
    assert code == 2 and err == f"bokehray: error: cannot write {out / 'render_focus_near.png'}: No space left on device\n"
    assert stdout == "" and list(tmp_path.iterdir()) == []


def test_a_demo_that_fails_in_a_folder_that_was_there_leaves_the_folder(tmp_path, capsys, monkeypatch):
    """The user's own folder is not the demo's to remove: it stays, with what was in it."""
    _fill_disk_at(monkeypatch, "input.png")
    (tmp_path / "notes.txt").write_text("mine")
    code, _, err = run(capsys, "demo", "-o", tmp_path, "--size", "96,64")
    assert code == 2 and err.count("\n") == 1 and "No space left on device" in err, err
    assert [f.name for f in tmp_path.iterdir()] == ["notes.txt"]


@pytest.mark.parametrize("which, what", [("png", "photo"), ("disp_png", "map")])
def test_an_output_that_is_an_input_is_refused_and_the_input_kept(scene, tmp_path, capsys, which, what):
    """``-o`` naming the photo or its map replaced it with the render (a map then no longer reads as one)."""
    p, _, _ = scene
    before = p[which].read_bytes()
    out = tmp_path / "." / p[which].name  # another spelling of the same file
    code, _, err = run(capsys, "render", p["png"], "--disparity", p["disp_png"], "-o", out, "--blur", 4, "--focus", 0.5)
    assert code == 2 and err.count("\n") == 1 and f"is the {what} being rendered" in err, err
    assert p[which].read_bytes() == before


def test_a_batch_into_its_own_folder_keeps_the_photos_even_with_overwrite(scene, tmp_path, capsys):
    p, _, _ = scene
    for folder, name in (("photos", "png"), ("maps", "disp_png")):
        (tmp_path / folder).mkdir()
        (tmp_path / folder / "in.png").write_bytes(p[name].read_bytes())
    before = p["png"].read_bytes()
    code, _, err = run(capsys, "render", tmp_path / "photos", "--disparity", tmp_path / "maps", "-o",
                       tmp_path / "photos", "--blur", 4, "--focus", 0.5, "--workers", 1, "--overwrite", "--quiet")
    assert code == 2 and "is the photo being rendered" in err, err
    assert (tmp_path / "photos" / "in.png").read_bytes() == before


def test_an_output_format_that_contradicts_the_output_name_is_refused(scene, tmp_path, capsys):
    """``-o o.png --output-format jpg`` wrote a PNG without a word: the flag only acts on a batch's outputs."""
    p, _, _ = scene
    code, _, err = run(capsys, "render", p["png"], "--disparity", p["disp_png"], "-o", tmp_path / "o.png",
                       "--output-format", "jpg", "--blur", 4, "--focus", 0.5)
    assert code == 2 and err.count("\n") == 1 and "--output-format jpg" in err and "name it .jpg" in err, err
    assert not (tmp_path / "o.png").exists()
    code, _, err = run(capsys, "render", p["png"], "--disparity", p["disp_png"], "-o", tmp_path / "o.JPEG",
                       "--output-format", "jpg", "--blur", 4, "--focus", 0.5, "--quiet")
    assert code == 0 and (tmp_path / "o.JPEG").exists(), err


def test_unwritable_output_is_refused_before_rendering(scene, tmp_path, capsys):
    p, _, _ = scene
    (tmp_path / "a_file").write_text("not a folder")
    code, _, err = run(capsys, "render", p["png"], "--disparity", p["disp_png"], "-o", tmp_path / "a_file" / "o.png",
                       "--blur", 4, "--focus", 0.5)
    assert code == 2 and "cannot write there" in err and err.count("\n") == 1
    # a folder that cannot be created at write time is one line too, not a traceback
    code, _, err = run(capsys, "render", p["png"], "--disparity", p["disp_png"], "-o", "/proc/nope/o.png",
                       "--blur", 4, "--focus", 0.5)
    assert code == 2 and err.startswith("bokehray: error:") and err.count("\n") == 1


def test_bad_numbers_for_rays_and_workers(scene, tmp_path, capsys):
    p, _, _ = scene
    code, _, err = run(capsys, "synth", "-n", 1, "-o", tmp_path / "s", "--max-spp", 0, "--quiet")
    assert code == 2 and "rays per pixel" in err
    code, _, err = run(capsys, "render", p["png"], "--disparity", p["disp_png"], "-o", tmp_path / "o.png",
                       "--blur", 1e30, "--focus", 0.5)
    assert code == 2 and "at most" in err
    code, _, err = run(capsys, "synth", "-n", 1, "-o", tmp_path / "s", "--workers", 0, "--quiet")
    assert code == 2 and "--workers" in err


def test_a_negative_synth_seed_names_the_flag_before_the_folder_is_made(tmp_path, capsys):
    """It used to fail inside the first scene (``scene_00000: ValueError: expected non-negative integer``),
    after the output folder had been created."""
    code, _, err = run(capsys, "synth", "-n", 1, "-o", tmp_path / "s", "--seed", -1, "--workers", 1, "--quiet")
    assert code == 2 and err == "bokehray: error: --seed: expected an integer >= 0, got -1\n", err
    assert not (tmp_path / "s").exists()


def test_focus_at_the_sky_is_a_clear_error(tmp_path, capsys):
    img = br.write_image(tmp_path / "i.png", np.full((16, 16, 3), 0.5, np.float32))
    z = np.full((16, 16), 3.0, np.float32)
    z[:8] = np.inf  # sky in the top half
    np.save(tmp_path / "z.npy", z)
    code, _, err = run(capsys, "render", img, "--depth", tmp_path / "z.npy", "-o", tmp_path / "o.png",
                       "--focal-length", 50, "--f-number", 2, "--focus-at", "4,2")
    assert code == 2 and "infinity" in err and err.count("\n") == 1


def test_resized_depth_with_sky_stays_finite(tmp_path, capsys):
    img = br.write_image(tmp_path / "i.png", np.full((16, 16, 3), 0.5, np.float32))
    z = np.full((8, 8), 2.0, np.float32)
    z[:3] = np.inf  # sky
    np.save(tmp_path / "z.npy", z)
    code, _, err = run(capsys, "render", img, "--depth", tmp_path / "z.npy", "-o", tmp_path / "o.exr",
                       "--focal-length", 50, "--f-number", 2, "--focus-distance", 2, "--resize-disparity")
    assert code == 0, err
    assert np.isfinite(br.read_image(tmp_path / "o.exr")).all()


def test_a_closed_stdout_is_not_an_error(scene, tmp_path, capsys, monkeypatch):
    """``bokehray render ... | head -0``: BrokenPipeError is an OSError, and the OSError branch caught it first
    (an error line and exit 2 after the output had been written)."""
    import sys

    class Closed:
        def write(self, text):
            raise BrokenPipeError(32, "Broken pipe")

        def flush(self):
            pass

    p, _, _ = scene
    monkeypatch.setattr(sys, "stdout", Closed())
    code = main(["render", str(p["png"]), "--disparity", str(p["disp_png"]), "-o", str(tmp_path / "o.png"),
                 "--blur", "4", "--focus", "0.5"])
    assert code == 0 and (tmp_path / "o.png").exists()
    assert capsys.readouterr().err == ""



@pytest.mark.parametrize("which", ["photo", "map"])
def test_a_named_pipe_as_input_is_refused_not_waited_on(scene, tmp_path, capsys, which):
    """``render fifo.png ...``: opening a FIFO waits for a writer, so the command hung until killed. A FIFO (a device
    or a socket too) is refused before it is opened; here a writer stands by with a valid file, each time the pipe is
    opened, so that the old behaviour shows as a render, not as a hang."""
    import os
    import threading

    p, _, _ = scene
    fifo = tmp_path / "pipe.png"
    os.mkfifo(fifo)
    data = (p["png"] if which == "photo" else p["disp_png"]).read_bytes()
    done = threading.Event()

    def feed():
        while not done.is_set():
            with contextlib.suppress(BrokenPipeError), open(fifo, "wb") as w:  # waits for a reader to open the pipe
                w.write(data)

    writer = threading.Thread(target=feed, daemon=True)
    writer.start()
    args = [fifo, "--disparity", p["disp_png"]] if which == "photo" else [p["png"], "--disparity", fifo]
    try:
        code, _, err = run(capsys, "render", *args, "-o", tmp_path / "o.png", "--blur", "4", "--focus", "0.5")
    finally:
        done.set()
        fd = os.open(fifo, os.O_RDONLY | os.O_NONBLOCK)  # the writer's open returns: nothing is left blocked
        try:
            while writer.is_alive():
                with contextlib.suppress(BlockingIOError):
                    os.read(fd, 1 << 16)
                writer.join(0.01)
        finally:
            os.close(fd)
    assert code == 2 and err == f"bokehray: error: {fifo}: expected a regular file, got a named pipe (FIFO)\n", err
    assert not (tmp_path / "o.png").exists()

@pytest.mark.parametrize("fails", [False, True])
def test_warnings_are_one_line_on_success_and_dropped_on_error(monkeypatch, capsys, fails):
    """A Python warning during a command never turns the one-line error into several."""
    import sys
    import warnings

    from bokehray.app import cli
    from bokehray.errors import InputError

    def cmd(args):
        warnings.warn("overflow encountered in multiply", RuntimeWarning, stacklevel=1)
        warnings.warn("overflow encountered in multiply", RuntimeWarning, stacklevel=1)  # shown once
        if fails:
            raise InputError("x.png: expected something else")
        return 0

    monkeypatch.setattr(cli, "cmd_render", cmd)
    argv = ["render", "x.png", "--disparity", "d.png", "-o", "o.png"]
    with warnings.catch_warnings():  # outside pytest a warning is printed to stderr: do that here too
        warnings.simplefilter("default")
        warnings.showwarning = lambda msg, cat, fn, ln, file=None, line=None: print(
            warnings.formatwarning(msg, cat, fn, ln), file=sys.stderr, end="")
        code = main(argv)
    err = capsys.readouterr().err
    if fails:
        assert code == 2 and err == "bokehray: error: x.png: expected something else\n"
    else:
        assert code == 0 and err.count("\n") == 1
        assert err.startswith("bokehray: warning: overflow encountered in multiply (test_cli.py:"), err
        assert main([*argv, "--quiet"]) == 0 and capsys.readouterr().err == ""
