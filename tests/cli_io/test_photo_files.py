"""Real files carrying EXIF orientation and ICC profiles (written here with Pillow and tifffile): the readers show
the pixels as displayed and in sRGB; outputs are tagged sRGB; a JPEG output keeps the photo's EXIF upright."""

import io as pyio

import numpy as np
import pytest
import tifffile
from PIL import Image, ImageCms, ImageOps
from reference.icc_ref import matrix_trc_profile, p3_codes_to_linear_srgb

import bokehray as br
from bokehray import colour
from bokehray.app.cli import main
from bokehray.photo import embedded

P3 = matrix_trc_profile("Display P3 (test)")


def _exif(orientation: int, make: str | None = None) -> bytes:
    exif = Image.Exif()
    exif[0x0112] = orientation
    if make:
        exif[0x010F] = make
    return exif.tobytes()


@pytest.fixture
def codes():
    return np.random.default_rng(2).integers(0, 256, (5, 7, 3), dtype=np.uint8)


@pytest.mark.parametrize("orientation", range(1, 9))
def test_png_orientation_is_applied_like_pillow(tmp_path, codes, orientation):
    path = tmp_path / "o.png"
    Image.fromarray(codes).save(path, exif=_exif(orientation))
    with Image.open(path) as im:
        want = np.asarray(ImageOps.exif_transpose(im))  # Pillow's reading of the tag: the independent reference
    got = br.read_image(path)
    np.testing.assert_array_equal(got, colour.srgb_to_linear(want / 255.0))


@pytest.mark.parametrize("orientation", [3, 6, 8])
def test_png_exif_after_the_image_data_is_found_without_decoding(tmp_path, codes, orientation):
    """Phone exports and exiftool put the eXIf chunk after IDAT: the reader walks the chunk headers to it, and
    reads the orientation Pillow reads after decoding the whole file."""
    import struct
    import zlib

    plain = pyio.BytesIO()
    Image.fromarray(codes).save(plain, format="PNG")
    data = plain.getvalue()
    body = _exif(orientation, make="Test")
    chunk = struct.pack(">I", len(body)) + b"eXIf" + body + struct.pack(">I", zlib.crc32(b"eXIf" + body))
    end = data.rindex(b"IEND") - 4  # the IEND chunk's length field
    path = tmp_path / "late.png"
    path.write_bytes(data[:end] + chunk + data[end:])
    with Image.open(path) as im:
        assert "exif" not in im.info  # not seen before the pixels are decoded
        want = np.asarray(ImageOps.exif_transpose(im))
    meta = embedded.embedded(path, "PNG")
    assert meta.orientation == orientation and meta.exif is not None
    np.testing.assert_array_equal(br.read_image(path), colour.srgb_to_linear(want / 255.0))


def test_jpeg_orientation_6_is_upright(tmp_path):
    h, w = 24, 40
    img = np.zeros((h, w, 3), np.uint8)
    img[:8] = 255  # a white band along the stored top
    Image.fromarray(img).save(tmp_path / "p.jpg", exif=_exif(6), quality=95)
    got = br.read_image(tmp_path / "p.jpg")
    assert got.shape == (w, h, 3)  # rotated 90 degrees clockwise for display: the top band is now on the right
    assert got[:, -4:].mean() > 0.9 and got[:, :4].mean() < 0.05


def test_depth_maps_carry_orientation_too(tmp_path):
    d = np.zeros((6, 10), np.uint16)
    d[:, :3] = 65535  # near on the stored left
    Image.fromarray(d).save(tmp_path / "d.png", exif=_exif(8))  # 16-bit grey PNG, rotated 90 degrees ccw for display
    got = br.read_disparity(tmp_path / "d.png")
    assert got.shape == (10, 6) and got[-3:].min() == 1.0 and got[:-3].max() == 0.0
    tifffile.imwrite(tmp_path / "d.tif", d, extratags=[(274, "H", 1, 3, False)])  # Orientation = 3: 180 degrees
    np.testing.assert_array_equal(br.read_disparity(tmp_path / "d.tif"), d[::-1, ::-1] / 65535.0)


def test_display_p3_png_is_converted_to_linear_srgb(tmp_path):
    grid = np.stack(np.meshgrid(*[np.arange(8, 256, 40)] * 3, indexing="ij"), axis=-1)  # 7 x 7 x 7 colours
    codes = grid.astype(np.uint8).reshape(49, 7, 3)
    Image.fromarray(codes).save(tmp_path / "p3.png", icc_profile=P3)
    assert not embedded.embedded(tmp_path / "p3.png", "PNG").is_srgb
    got = br.read_image(tmp_path / "p3.png")
    want = p3_codes_to_linear_srgb(codes)
    enc = lambda x: colour.linear_to_srgb(x).astype(np.float64) * 255  # noqa: E731
    assert np.abs(enc(got) - enc(want)).max() <= 1.0 + 1e-6  # one 8-bit code: littleCMS's rounding
    naive = colour.srgb_to_linear(codes / 255.0)  # P3 read as sRGB: what the reader did before
    assert np.abs(enc(naive) - enc(want)).max() > 10


def test_display_p3_in_jpeg_and_tiff(tmp_path):
    codes = np.full((8, 8, 3), (200, 120, 80), np.uint8)
    Image.fromarray(codes).save(tmp_path / "p3.jpg", icc_profile=P3, quality=100)
    tifffile.imwrite(tmp_path / "p3.tif", codes, photometric="rgb", iccprofile=P3)
    want = colour.linear_to_srgb(p3_codes_to_linear_srgb(codes[:1, :1]))[0, 0] * 255  # (213, 115, 70)
    for name in ("p3.jpg", "p3.tif"):
        got = colour.linear_to_srgb(br.read_image(tmp_path / name)).mean(axis=(0, 1)) * 255
        assert np.abs(got - want).max() < 2.5, (name, got, want)
    codes12 = np.full((8, 8, 3), (200 * 4095 // 255, 120 * 4095 // 255, 80 * 4095 // 255), np.uint16)
    tifffile.imwrite(tmp_path / "p3-12.tif", codes12, photometric="rgb", iccprofile=P3, bitspersample=12)
    got = colour.linear_to_srgb(br.read_image(tmp_path / "p3-12.tif")).mean(axis=(0, 1)) * 255  # 12-bit: by 4095
    assert np.abs(got - want).max() < 2.5, ("p3-12.tif", got, want)


def test_srgb_profile_is_left_alone(tmp_path, codes):
    srgb = ImageCms.ImageCmsProfile(ImageCms.createProfile("sRGB")).tobytes()
    Image.fromarray(codes).save(tmp_path / "s.png", icc_profile=srgb)
    np.testing.assert_array_equal(br.read_image(tmp_path / "s.png"), colour.srgb_to_linear(codes / 255.0))


def _icc_name(icc: bytes) -> str:
    return ImageCms.getProfileDescription(ImageCms.ImageCmsProfile(pyio.BytesIO(icc)))


@pytest.mark.parametrize(("name", "bits"), [("o.png", 8), ("o16.png", 16), ("o.jpg", 8), ("o.tif", 16)])
def test_outputs_are_tagged_srgb(tmp_path, name, bits):
    ramp = np.linspace(0.05, 0.9, 16, dtype=np.float32)
    img = np.stack([np.tile(ramp, (16, 1)), np.tile(ramp[:, None], (1, 16)), np.full((16, 16), 0.3, np.float32)], -1)
    path = br.write_image(tmp_path / name, img, bit_depth=bits)
    if name.endswith(".tif"):
        with tifffile.TiffFile(path) as tf:
            icc = bytes(tf.pages[0].tags["InterColorProfile"].value)
    else:
        with Image.open(path) as im:
            im.load()
            icc = im.info["icc_profile"]
    assert "sRGB" in _icc_name(icc)
    back = br.read_image(path)  # and still reads back as before (the profile is sRGB: no conversion)
    assert np.abs(colour.linear_to_srgb(back) - colour.linear_to_srgb(img)).max() < (0.06 if name.endswith("jpg") else 0.003)


def test_exr_output_carries_srgb_chromaticities(tmp_path):
    import OpenEXR

    path = br.write_image(tmp_path / "o.exr", np.ones((4, 4, 3), np.float32))
    with OpenEXR.File(str(path), header_only=True) as f:
        np.testing.assert_allclose(f.header()["chromaticities"], colour.SRGB_CHROMATICITIES, atol=1e-6)


def test_jpeg_output_keeps_exif_upright_and_takes_quality(tmp_path, capsys):
    h, w = 48, 64
    rng = np.random.default_rng(1)
    stored = (rng.random((h, w, 3)) * 255).astype(np.uint8)
    Image.fromarray(stored).save(tmp_path / "phone.jpg", exif=_exif(6, make="TestCam"), quality=95)
    d = np.tile(np.linspace(0, 1, h, dtype=np.float32), (w, 1))  # made on the upright photo: W x H stored as H' x W'
    br.write_disparity(tmp_path / "d.png", d)
    sizes = {}
    for q in (30, 95):
        out = tmp_path / f"out{q}.jpg"
        code = main([str(a) for a in ("render", tmp_path / "phone.jpg", "--disparity", tmp_path / "d.png", "-o", out,
                                      "--jpeg-quality", q)])
        said = capsys.readouterr()
        assert code == 0, said.err
        assert "EXIF orientation 6 applied (rotated 90 degrees clockwise)" in said.out
        with Image.open(out) as im:
            exif = im.getexif()
            assert im.size == (h, w)  # written upright
            assert exif.get(0x0112) == 1 and exif.get(0x010F) == "TestCam"
            assert "sRGB" in _icc_name(im.info["icc_profile"])
        sizes[q] = out.stat().st_size
    assert sizes[30] < sizes[95]


def test_resizing_a_map_of_the_other_orientation_is_refused(tmp_path, capsys):
    Image.fromarray(np.zeros((40, 60, 3), np.uint8)).save(tmp_path / "phone.jpg", exif=_exif(6))
    br.write_disparity(tmp_path / "d.png", np.zeros((40, 60), np.float32))  # made on the stored, sideways pixels
    code = main([str(a) for a in ("render", tmp_path / "phone.jpg", "--disparity", tmp_path / "d.png", "-o",
                                  tmp_path / "o.png", "--resize-disparity", "--blur", 2, "--focus", 0.5)])
    err = capsys.readouterr().err
    assert code == 2 and "d.png" in err and "EXIF orientation 6" in err and "turn the map" in err
    assert "--resize-disparity" not in err  # resizing cannot fix a map in the unturned orientation
    assert not (tmp_path / "o.png").exists()


def test_a_profile_of_another_colour_space_is_ignored(tmp_path, codes):
    lab = ImageCms.ImageCmsProfile(ImageCms.createProfile("LAB")).tobytes()  # not RGB: nothing to convert from
    Image.fromarray(codes).save(tmp_path / "lab.png", icc_profile=lab)
    np.testing.assert_array_equal(br.read_image(tmp_path / "lab.png"), colour.srgb_to_linear(codes / 255.0))


def test_an_unreadable_profile_is_an_error_naming_the_file(tmp_path, codes):
    Image.fromarray(codes).save(tmp_path / "bad.png", icc_profile=b"not an icc profile at all" * 8)
    with pytest.raises(br.InputError, match="bad.png"):
        br.read_image(tmp_path / "bad.png")
