"""An adversarial pass over depth ranges, map channels and early refusals (docs/robustness.md, "Reading files"
and "The command line"): each case is refused in one line naming the file and the flag, before any
output or folder is made, or handled as documented there."""

from __future__ import annotations

import numpy as np
import OpenEXR
import pytest
from PIL import Image

import bokehray as br
from bokehray.app.cli import main


def run(capsys, *args):
    code = main([str(a) for a in args])
    out = capsys.readouterr()
    return code, out.out, out.err


def _one_line(err: str) -> str:
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("bokehray: error: "), err
    return lines[0]


def _write_exr(path, channels: dict[str, np.ndarray]):
    channels = {k: np.ascontiguousarray(v, np.float32) for k, v in channels.items()}
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}, channels) as f:
        f.write(str(path))
    return path


@pytest.fixture
def photo(tmp_path):
    rng = np.random.default_rng(5)
    img = (rng.random((24, 32, 3)) * 0.8).astype(np.float32)
    z = np.tile(np.linspace(1.0, 10.0, 32), (24, 1))  # metres: 1 .. 10
    np.save(tmp_path / "z.npy", z)
    return br.write_image(tmp_path / "p.png", img), tmp_path / "z.npy", z


LENS = ("--focal-length", 50, "--f-number", 1.4)


# --------------------------------------------------------------------------- 1. --z-near / --z-far


@pytest.mark.parametrize("flags,said", [
    (("--z-near", 1.4), "depth reaches 1 m, nearer than --z-near 1.4 m; lower --z-near or leave it out"),
    (("--z-far", 5), "depth reaches 10 m, farther than --z-far 5 m; raise --z-far (inf allowed) or leave it out"),
])
def test_a_normalisation_narrower_than_the_depth_map_is_refused(photo, tmp_path, capsys, flags, said):
    """--z-near 1.4 on a 1..10 m map clipped the 1..1.4 m pixels to 1.4 m (rendered 7x too sharp), exit 0."""
    p, z, _ = photo
    code, out, err = run(capsys, "render", p, "--depth", z, "-o", tmp_path / "o.png", *LENS,
                         "--focus-distance", 1.5, *flags)
    assert code == 2 and out == ""
    assert f"{z}: {said}" in _one_line(err)
    assert not (tmp_path / "o.png").exists()


def test_a_normalisation_as_wide_as_the_map_or_wider_is_taken(photo, tmp_path, capsys):
    p, z, _ = photo
    for flags in (("--z-near", 0.5, "--z-far", "inf"), ("--z-near", 1, "--z-far", 10)):
        code, _, err = run(capsys, "render", p, "--depth", z, "-o", tmp_path / "o.png", *LENS, "--focus-distance", 2,
                           *flags)
        assert code == 0, err
    # a float32 map's 1.4 is 1.39999998: --z-near 1.4 must take it
    d, _ = br.disparity_from_depth(np.float32([[1.4, 3.0]]), br.DepthNormalization(1.4, 3.0))
    assert d.tolist() == [[1.0, 0.0]]


def test_the_api_refuses_a_normalisation_narrower_than_the_map(photo):
    _, _, z = photo
    with pytest.raises(br.InputError, match=r"z\.npy: depth reaches 1 m, nearer than z_near 1\.4 m"):
        br.disparity_from_depth(z, br.DepthNormalization(1.4, 10.0), source="z.npy")
    with pytest.raises(br.InputError, match=r"depth reaches 10 m, farther than z_far 5 m"):
        br.disparity_from_depth(z, br.DepthNormalization(1.0, 5.0))
    # no depth (0, inf) is infinitely far: the far end, whatever z_far is
    d, _ = br.disparity_from_depth(np.array([[0.0, 1.0, np.inf, 5.0]]), br.DepthNormalization(1.0, 5.0))
    assert d.tolist() == [[0.0, 1.0, 0.0, 0.0]]


# --------------------------------------------------------------------------- 2. multi-channel EXR maps


def test_an_exr_map_of_channels_that_differ_is_refused_naming_them(tmp_path, capsys):
    """dRGB_diff.exr (R = d, G = 1 - d) rendered from its R channel, silently."""
    d = np.tile(np.linspace(0, 1, 32, dtype=np.float32), (24, 1))
    diff = _write_exr(tmp_path / "diff.exr", {"R": d, "G": 1 - d, "B": d})
    for read, what in ((br.read_disparity, "disparity"), (br.read_depth, "depth")):
        with pytest.raises(br.InputError, match=rf"diff\.exr: expected a single-channel {what} map, got 3 EXR "
                                                r"channels \(B,G,R\) that differ"):
            read(diff)
    p = br.write_image(tmp_path / "p.png", np.full((24, 32, 3), 0.5, np.float32))
    code, out, err = run(capsys, "render", p, "--disparity", diff, "-o", tmp_path / "o.png", "--blur", 4, "--focus", 0.5)
    assert code == 2 and out == "" and "got 3 EXR channels (B,G,R) that differ" in _one_line(err)
    # equal channels are one map; a lone channel of any name is the map
    same = _write_exr(tmp_path / "same.exr", {"R": d, "G": d, "B": d})
    np.testing.assert_array_equal(br.read_disparity(same), d)
    np.testing.assert_array_equal(br.read_disparity(_write_exr(tmp_path / "foo.exr", {"foo": d})), d)
    grey_rgba = _write_exr(tmp_path / "rgba.exr", {"R": d, "G": d, "B": d, "A": np.ones_like(d)})  # coverage aside
    np.testing.assert_array_equal(br.read_disparity(grey_rgba), d)


def test_an_exr_depth_map_is_read_from_its_z_channel_whatever_else_it_holds(tmp_path):
    rgb = np.random.default_rng(1).random((3, 24, 32)).astype(np.float32)
    z = np.tile(np.linspace(1, 10, 32, dtype=np.float32), (24, 1))
    f = _write_exr(tmp_path / "rgbaz.exr", {"R": rgb[0], "G": rgb[1], "B": rgb[2], "A": np.ones_like(z), "Z": z})
    np.testing.assert_array_equal(br.read_depth(f), z)
    with pytest.raises(br.InputError, match=r"got 4 EXR channels \(B,G,R,Z\) that differ"):  # the alpha aside
        br.read_disparity(f)  # a disparity map has no standard channel


# --------------------------------------------------------------------------- 3. EXR colour that is not RGB


@pytest.mark.parametrize("names,words", [
    (("Y", "RY", "BY"), r"luminance/chroma channels \(Y, RY, BY\)"),
    (("X", "Y", "Z"), "CIE X, Y, Z channels"),
])
def test_an_exr_photo_of_luminance_chroma_or_xyz_is_refused(tmp_path, capsys, names, words):
    """Read as the grey of its Y channel: a colour photo rendered grey, exit 0."""
    a = np.random.default_rng(2).random((3, 24, 32)).astype(np.float32)
    f = _write_exr(tmp_path / "c.exr", dict(zip(names, a)))
    with pytest.raises(br.InputError, match=rf"c\.exr: holds {words}, not R, G, B"):
        br.read_image(f)
    d = br.write_disparity(tmp_path / "d.png", np.full((24, 32), 0.5, np.float32))
    code, out, err = run(capsys, "render", f, "--disparity", d, "-o", tmp_path / "o.exr", "--blur", 4, "--focus", 0.5)
    assert code == 2 and out == "" and "not R, G, B" in _one_line(err)
    assert br.read_image(_write_exr(tmp_path / "ya.exr", {"Y": a[0], "A": np.ones_like(a[0])})).shape == (24, 32, 4)


# --------------------------------------------------------------------------- 4. --focus-distance beyond the range


def test_a_focus_distance_beyond_the_depth_range_names_the_flag_and_the_way_out(photo, tmp_path, capsys):
    p, z, _ = photo
    code, out, err = run(capsys, "render", p, "--depth", z, "-o", tmp_path / "o.png", *LENS, "--focus-distance", 100)
    line = _one_line(err)
    assert code == 2 and out == "", out  # no "depth:" or "focus:" line before the refusal
    assert "--focus-distance: 100 m lies beyond the depth range [1, 10] m" in line and "--z-far inf" in line
    code, out, err = run(capsys, "render", p, "--depth", z, "-o", tmp_path / "o.png", *LENS, "--focus-distance", 0.5)
    assert code == 2 and out == "" and "a --z-near of at most 0.5" in _one_line(err)
    code, _, err = run(capsys, "render", p, "--depth", z, "-o", tmp_path / "o.png", *LENS, "--focus-distance", 100,
                       "--z-far", "inf")
    assert code == 0, err
    with pytest.raises(br.InputError, match="focus_distance_m: 100 m lies beyond .* z_far inf"):
        br.ThinLens(50, 1.4, 100).blur_params(br.DepthNormalization(1, 10), 100)


# --------------------------------------------------------------------------- 5. alpha and a JPEG output


def test_a_transparent_photo_into_a_jpeg_is_refused_before_the_render(tmp_path, capsys, monkeypatch):
    """Refused by the writer, after the whole render ("expected an image without alpha for JPEG")."""
    import bokehray.pipeline as pipeline

    rgba = np.full((24, 32, 4), 200, np.uint8)
    rgba[0, 0, 3] = 10
    Image.fromarray(rgba).save(tmp_path / "t.png")
    d = br.write_disparity(tmp_path / "d.png", np.full((24, 32), 0.5, np.float32))
    monkeypatch.setattr(pipeline, "render_handed_over", lambda *a, **k: pytest.fail("rendered before refusing"))
    code, out, err = run(capsys, "render", tmp_path / "t.png", "--disparity", d, "-o", tmp_path / "o.jpg",
                         "--blur", 4, "--focus", 0.5)
    assert code == 2 and out == ""
    assert f"{tmp_path / 't.png'}: has transparent pixels (alpha below 1)" in _one_line(err)
    assert not (tmp_path / "o.jpg").exists()


def test_an_opaque_alpha_is_dropped_for_a_jpeg(tmp_path, capsys):
    rgba = np.full((24, 32, 4), 255, np.uint8)
    rgba[..., :3] = np.random.default_rng(4).integers(0, 256, (24, 32, 3))
    Image.fromarray(rgba).save(tmp_path / "o4.png")
    Image.fromarray(np.stack([rgba[..., 0], rgba[..., 3]], -1)).save(tmp_path / "la.png")
    d = br.write_disparity(tmp_path / "d.png", np.full((24, 32), 0.5, np.float32))
    for name in ("o4.png", "la.png"):
        code, _, err = run(capsys, "render", tmp_path / name, "--disparity", d, "-o", tmp_path / f"{name}.jpg",
                           "--blur", 4, "--focus", 0.5)
        assert code == 0, err
        assert br.read_image(tmp_path / f"{name}.jpg").shape == (24, 32, 3)


# --------------------------------------------------------------------------- 6. train-refiner's arguments


@pytest.mark.parametrize("args,said", [
    (("--data", "nope"), "--data nope: expected a BLB-layout training folder"),
    (("--data", "{empty}"), "no BLB scenes under"),
    (("--data", "{empty}", "--crop", 60), "--crop: expected a positive multiple of 8 (the refiner's latent grid), got 60"),
    (("--data", "{empty}", "--steps", -1), "--steps: expected >= 1, got -1"),
])
def test_train_refiner_refuses_before_making_its_folder(tmp_path, capsys, args, said):
    """--data nope left an empty --out folder; --crop 60 / --steps -1 named neither flag nor value."""
    pytest.importorskip("torch")
    (tmp_path / "empty").mkdir()
    args = [str(a).format(empty=tmp_path / "empty") for a in args]
    code, _, err = run(capsys, "train-refiner", *args, "--out", tmp_path / "run")
    assert code == 2 and said in _one_line(err)
    assert not (tmp_path / "run").exists()


# --------------------------------------------------------------------------- 7. EXIF-turned photo, stored map


@pytest.mark.parametrize("resize", [(), ("--resize-disparity",)])
def test_a_map_of_an_exif_turned_photo_is_named_as_that(tmp_path, capsys, resize):
    """The advice was --resize-disparity, which then refused for the aspect ratio."""
    im = Image.fromarray(np.full((24, 32, 3), 128, np.uint8))
    exif = im.getexif()
    exif[0x0112] = 6
    im.save(tmp_path / "rot6.jpg", exif=exif)
    d = br.write_disparity(tmp_path / "d.png", np.full((24, 32), 0.5, np.float32))  # the stored 32 x 24
    code, _, err = run(capsys, "render", tmp_path / "rot6.jpg", "--disparity", d, "-o", tmp_path / "o.png",
                         "--blur", 4, "--focus", 0.5, *resize)
    line = _one_line(err)
    assert code == 2 and "map is 32x24, image is 24x32 as displayed" in line
    assert "EXIF orientation 6" in line and "--resize-disparity" not in line


# --------------------------------------------------------------------------- 8. --normalize says what it used


def test_normalize_says_the_bounds_it_used(tmp_path, capsys):
    """A map mostly at 3 fell back to min..max [3, 10], but the line said "[3, 3] (0.5th..99.5th percentiles)"."""
    raw = np.full((24, 32), 3.0, np.float32)
    raw[0, 0] = 10.0
    np.save(tmp_path / "d.npy", raw)
    p = br.write_image(tmp_path / "p.png", np.full((24, 32, 3), 0.5, np.float32))
    code, out, err = run(capsys, "render", p, "--disparity", tmp_path / "d.npy", "--normalize", "-o",
                         tmp_path / "o.png", "--blur", 4, "--focus", 0.5)
    assert code == 0, err
    assert "normalised from [3, 10] (min..max: the percentiles are equal)" in out


# --------------------------------------------------------------------------- 9. one map file for a folder


def test_a_folder_of_photos_with_one_map_file_is_refused_before_the_batch(tmp_path, capsys):
    (tmp_path / "ci").mkdir()
    for name in ("a.png", "b.png"):
        br.write_image(tmp_path / "ci" / name, np.full((24, 32, 3), 0.5, np.float32))
    d = br.write_disparity(tmp_path / "d.png", np.full((24, 32), 0.5, np.float32))
    code, out, err = run(capsys, "render", tmp_path / "ci", "--disparity", d, "-o", tmp_path / "co", "--blur", 4,
                         "--focus", 0.5)
    assert code == 2 and out == ""
    assert f"--disparity {d}: one map file for the 2 photos of {tmp_path / 'ci'}" in _one_line(err)
    assert not (tmp_path / "co").exists()


def test_a_photo_taken_by_refine_as_its_weights_is_named(tmp_path, capsys):
    """``--refine`` has an optional WEIGHTS value: ``... --refine p.png`` takes the photo as the weights."""
    with pytest.raises(SystemExit) as e:
        main(["render", "--disparity", "d.png", "-o", str(tmp_path / "o.png"), "--blur", "8", "--focus", "0.5",
              "--refine", "p.png"])
    err = capsys.readouterr().err
    assert e.value.code == 2 and err.count("\n") == 1
    assert "required: image" in err and "--refine took p.png as its WEIGHTS" in err
    assert not (tmp_path / "o.png").exists()


@pytest.mark.parametrize("flags,named", [(["--blades", "5"], "--blades shapes a polygonal aperture"),
                                         (["--curvature", "0.5", "--rotation", "10"], "--rotation/--curvature shape"),
                                         (["--sensor-width", "10"], "--sensor-width sizes the sensor")])
def test_flags_that_would_change_nothing_are_refused(tmp_path, capsys, flags, named):
    """Polygon flags with the default disc aperture, a sensor width without a physical lens: they used to be
    ignored (the output byte for byte the same), as other flags without effect are not."""
    Image.fromarray(np.zeros((16, 16, 3), np.uint8)).save(tmp_path / "p.png")
    br.write_disparity(tmp_path / "d.png", np.zeros((16, 16), np.float32))
    code = main(["render", str(tmp_path / "p.png"), "--disparity", str(tmp_path / "d.png"), "-o",
                 str(tmp_path / "o.png"), "--blur", "4", "--focus", "0.5", *flags])
    err = capsys.readouterr().err
    assert code == 2 and named in err and err.count("\n") == 1
    assert not (tmp_path / "o.png").exists()


def test_polygon_flags_with_a_polygon_aperture_take_their_defaults_when_left_out():
    import argparse

    from bokehray.app.render_job import aperture_of

    a = aperture_of(argparse.Namespace(aperture="polygon", blades=None, rotation=None, curvature=0.3))
    assert (a.blades, a.rotation_deg, a.curvature) == (6, 0.0, 0.3)


def test_a_jpeg_quality_for_an_output_that_is_not_a_jpeg_is_refused(tmp_path, capsys):
    """``--jpeg-quality 10`` with a PNG output was ignored (the file byte for byte the default's)."""
    Image.fromarray(np.zeros((16, 16, 3), np.uint8)).save(tmp_path / "p.png")
    br.write_disparity(tmp_path / "d.png", np.zeros((16, 16), np.float32))
    base = ["render", str(tmp_path / "p.png"), "--disparity", str(tmp_path / "d.png"), "--blur", "4", "--focus", "0.5"]
    assert main([*base, "-o", str(tmp_path / "o.png"), "--jpeg-quality", "10"]) == 2
    err = capsys.readouterr().err
    assert "--jpeg-quality sets the quality of a JPEG output" in err and err.count("\n") == 1
    assert not (tmp_path / "o.png").exists()
    assert main([*base, "-o", str(tmp_path / "o.jpg"), "--jpeg-quality", "10"]) == 0 and (tmp_path / "o.jpg").is_file()


@pytest.mark.parametrize("out,flags,said", [
    ("o.png", ["--half"], "o.png: --half writes half floats, which only EXR stores, and this is a PNG file (name it "
                          ".exr, or leave --half out)"),
    ("o.exr", ["--half", "--bit-depth", "32"], "o.exr: --half writes 16-bit half floats, and --bit-depth 32 asks for "
                                               "32-bit ones (leave one of them out)"),
    ("o.jpg", ["--bit-depth", "16"], "o.jpg: JPEG takes --bit-depth 8, not 16"),
])
def test_output_options_that_do_not_fit_the_output_are_refused_by_their_flags(tmp_path, capsys, out, flags, said):
    """``--half`` with a PNG output was refused in the API's words (``half=True needs an .exr path and bit_depth None
    or 16, got PNG with None``); the command line names its own flags, before any work."""
    Image.fromarray(np.zeros((16, 16, 3), np.uint8)).save(tmp_path / "p.png")
    br.write_disparity(tmp_path / "d.png", np.zeros((16, 16), np.float32))
    args = ["render", str(tmp_path / "p.png"), "--disparity", str(tmp_path / "d.png"), "--blur", "4", "--focus", "0.5"]
    assert main([*args, "-o", str(tmp_path / out), *flags]) == 2
    captured = capsys.readouterr()
    assert said in captured.err and captured.err.count("\n") == 1 and "half=True" not in captured.err
    assert captured.out == "" and not (tmp_path / out).exists()


# --------------------------------------------------------------------------- 13. a batch's options on one render


_A_BATCH = "a batch (a folder, a glob or a manifest of photos, or a focal sweep)"
_A_SWEEP = "a focal sweep (--focus or --blur with a list A,B,C or a range START:STOP:COUNT)"


@pytest.mark.parametrize("flags,said", [
    (["--workers", 2], f"--workers sets the number of processes of {_A_BATCH}"),
    (["--workers", 0], f"--workers sets the number of processes of {_A_BATCH}"),  # 0 == False: still given
    (["--executor", "local"], f"--executor chooses where the renders of {_A_BATCH} run"),
    (["--executor", "dask", "--scheduler", "tcp://127.0.0.1:8786"],
     f"--executor chooses where the renders of {_A_BATCH} run"),
    (["--map-suffix", "_disp"], "--map-suffix pairs the photos of a batch (a folder or a glob of photos) with their "
                                "maps by name"),
    (["--overwrite"], f"--overwrite renders again the outputs that {_A_BATCH} would skip as done"),
    (["--gif-width", 320], f"--gif-width sets the width of the animated preview of {_A_SWEEP}"),
    (["--fps", 12], f"--fps sets the frame rate of the animated preview of {_A_SWEEP}"),
])
def test_a_batch_option_on_a_single_render_is_refused(tmp_path, capsys, flags, said):
    """``--workers``, ``--fps``, ``--gif-width``, ``--map-suffix``, ``--scheduler`` (and ``--executor``,
    ``--overwrite``) on one photo with one focus were accepted and changed nothing, exit 0."""
    p = br.write_image(tmp_path / "p.png", np.full((16, 16, 3), 0.5, np.float32))
    d = br.write_disparity(tmp_path / "d.png", np.zeros((16, 16), np.float32))
    code, out, err = run(capsys, "render", p, "--disparity", d, "-o", tmp_path / "o.png", "--blur", 4,
                         "--focus", 0.5, *flags)
    assert code == 2 and out == ""
    line = _one_line(err)
    flag = flags[0]
    assert line == f"bokehray: error: {said}; this is a single render (one photo, one focus)" + (
        ", which replaces its -o file whether it exists or not" if flag == "--overwrite" else "") + \
        f": leave {flag} out", line
    assert not (tmp_path / "o.png").exists()


def test_a_focal_sweep_of_one_photo_takes_the_batch_options(tmp_path, capsys):
    """The same flags on a sweep of the same photo are its own: taken, and used (an 8 px wide GIF)."""
    rng = np.random.default_rng(3)
    p = br.write_image(tmp_path / "p.png", rng.random((16, 16, 3)).astype(np.float32))
    d = br.write_disparity(tmp_path / "d.png", np.tile(np.linspace(0, 1, 16, dtype=np.float32), (16, 1)))
    code, _, err = run(capsys, "render", p, "--disparity", d, "-o", tmp_path / "out", "--blur", 4,
                       "--focus", "0.2,0.8", "--workers", 1, "--executor", "local", "--map-suffix", "",
                       "--overwrite", "--gif-width", 8, "--fps", 10, "--quiet")
    assert code == 0, err
    with Image.open(tmp_path / "out" / "p_focus_sweep.gif") as gif:
        assert gif.width == 8 and gif.n_frames == 2 and gif.info["duration"] == 100


# --------------------------------------------------------------------------- 14. an animated PNG


@pytest.mark.parametrize("as_map", [False, True])
@pytest.mark.parametrize("bits", [8, 16])
def test_an_animated_png_is_refused_as_a_multi_page_tiff_is(tmp_path, capsys, as_map, bits):
    """An APNG rendered its first frame, silently (Pillow and libpng decode only that one)."""
    if bits == 8:
        frames = [Image.fromarray(np.full((16, 16, 3), v, np.uint8)) for v in (20, 200, 90)]
    else:
        frames = [Image.fromarray(np.full((16, 16), v, np.uint16)) for v in (2000, 60000, 9000)]
    apng = tmp_path / "anim.png"
    frames[0].save(apng, save_all=True, append_images=frames[1:])
    with Image.open(apng) as im:
        assert im.is_animated and im.n_frames == 3
    p = br.write_image(tmp_path / "p.png", np.full((16, 16, 3), 0.5, np.float32))
    d = br.write_disparity(tmp_path / "d.png", np.zeros((16, 16), np.float32))
    photo, disparity = (p, apng) if as_map else (apng, d)
    code, out, err = run(capsys, "render", photo, "--disparity", disparity, "-o", tmp_path / "o.png", "--blur", 4,
                         "--focus", 0.5)
    assert code == 2 and out == ""
    assert _one_line(err) == (f"bokehray: error: {apng}: expected one image, got an animated PNG (APNG) with 3 frames; "
                              "save the frame to use as its own file")
    assert not (tmp_path / "o.png").exists()
    with pytest.raises(br.InputError, match="animated PNG"):
        (br.read_disparity if as_map else br.read_image)(apng)
    # a one-frame APNG is one picture: read as before
    frames[0].save(apng, save_all=True, append_images=[])
    assert (br.read_disparity if as_map else br.read_image)(apng).shape[:2] == (16, 16)
