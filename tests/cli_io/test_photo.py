"""Photos and depth maps as people have them (bokehray.photo and the render command's defaults): the blur amount,
the default focus on the subject, relative / reversed / integer / missing depth, and the CLI's messages."""

import json
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

import bokehray as br
from bokehray.app.cli import main
from bokehray.app.demo import build_demo_scene
from bokehray.photo import depth, highlights
from bokehray.photo import subject as subj

DEVSET = Path("/work/shared/data/pathtraced-dev")
if not DEVSET.exists():
    DEVSET = Path(__file__).resolve().parents[3] / "shared" / "data" / "pathtraced-dev"
DEV_SCENES = ("d1_wire_mesh", "d2_leafy_twig", "d3_lamps_ring_writing")


def run(capsys, *args):
    code = main([str(a) for a in args])
    out = capsys.readouterr()
    return code, out.out, out.err


@pytest.fixture(scope="module")
def demo():
    return build_demo_scene(width=384, height=256)


# --------------------------------------------------------------------------- blur amount


@pytest.mark.parametrize(("h", "w"), [(256, 384), (816, 1224), (3000, 4000)])
def test_amount_is_a_fraction_of_the_diagonal(h, w):
    assert subj.k_from_amount(0, h, w) == 0.0
    assert subj.k_from_amount(100, h, w) == pytest.approx(subj.AMOUNT_K_FRACTION * math.hypot(h, w))
    k = subj.k_from_amount(50, h, w)
    assert k / math.hypot(h, w) == pytest.approx(0.03)  # the same look at every resolution
    assert subj.amount_from_k(k, h, w) == pytest.approx(50)


@pytest.mark.parametrize("bad", [-1, 100.5, float("nan"), float("inf"), True, "50"])
def test_amount_out_of_range_is_refused(bad):
    with pytest.raises(br.InputError, match="amount"):
        subj.k_from_amount(bad, 10, 10)


# --------------------------------------------------------------------------- default focus


def test_default_focus_lands_on_the_demo_cat(demo):
    subject = subj.subject_focus(demo.disparity)
    assert 0.86 <= subject.d_f <= 0.92  # the cat: 0.92 at the centre, 0.86 at the rim; grass (0.95+) is skipped
    h, w = demo.disparity.shape
    assert w / 2 < subject.x < w and 0 < subject.y < h  # the cat sits right of centre
    assert abs(subject.d_f - demo.focus_near) * demo.k_px < 3.0  # within a few pixels of CoC of the demo's focus


@pytest.mark.skipif(not DEVSET.exists(), reason="the path-traced dev set is not here")
@pytest.mark.parametrize("name", DEV_SCENES)
def test_default_focus_lands_on_the_devset_subject(name):
    """The subject of each dev-set scene is its nearest layer (mesh, twig, ring: focus F0); the default focus must
    fall inside that layer's disparity range, not on the large layers behind it."""
    info = json.loads((DEVSET / name / "info.json").read_text())
    d = br.read_disparity(DEVSET / name / "disparity.exr")
    z = br.read_depth(DEVSET / name / "depth.exr")
    near = z <= 1.8  # every scene's front layer lies within 1.14 .. 1.71 scene units, the next beyond 2.5
    subject = subj.subject_focus(d)
    assert float(d[near].min()) - 1e-6 <= subject.d_f <= float(d[near].max()) + 1e-6
    assert abs(subject.d_f - info["focus_disparities"][0]) * 32 < 4.0  # < 4 px CoC from F0 at the largest K
    assert near[subject.y, subject.x] or subject.share < 0.2  # a sparse layer's centroid may fall in a gap


def painted_scene(h: int = 480, w: int = 640, brush: float = 10.0):
    """A hand-painted map: a person right of centre (near, a gentle dome of 0.82..0.86), props in the middle
    distance (0.5, 0.55) and a backdrop far (0.12..0.2), softened with a brush of ``brush`` px (a Gaussian): the
    brush's ramps fill every histogram bin between the surfaces. Returns the hard map, the soft one, the person."""
    from scipy import ndimage

    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    d = 0.12 + 0.08 * (yy / h)
    d[int(0.55 * h):, int(0.05 * w):int(0.3 * w)] = 0.5
    d[int(0.45 * h):int(0.8 * h), int(0.72 * w):int(0.95 * w)] = 0.55
    person = ((((xx - 0.55 * w) / (0.07 * w)) ** 2 + ((yy - 0.28 * h) / (0.1 * h)) ** 2 <= 1)
              | ((np.abs(xx - 0.55 * w) < 0.13 * w) & (yy > 0.36 * h)))
    d = np.where(person, 0.86 - 0.04 * np.clip(np.abs(xx - 0.55 * w) / (0.13 * w), 0, 1), d).astype(np.float32)
    return d, ndimage.gaussian_filter(d, brush).astype(np.float32), person


def _write_png8(path, d: np.ndarray) -> None:
    from PIL import Image

    Image.fromarray(np.round(np.clip(d, 0, 1) * 255).astype(np.uint8), "L").save(path)


def _encodings(soft: np.ndarray) -> dict[str, np.ndarray]:
    """The same soft map as people hand it over: float, 8/16-bit, dithered, a model's (blurred, estimated at 1/8
    of the size and upscaled, affine, noisy, then normalised) and a relative map of another range normalised."""
    from scipy import ndimage

    rng = np.random.default_rng(0)
    h, w = soft.shape
    small = ndimage.gaussian_filter(soft, 6)[::8, ::8]
    model = ndimage.zoom(small, (h / small.shape[0], w / small.shape[1]), order=1)[:h, :w]
    model = 0.3 + 0.5 * model + 0.02 * rng.standard_normal(model.shape)
    return {
        "float": soft,
        "8-bit": np.round(soft * 255) / 255,
        "16-bit": np.round(soft * 65535) / 65535,
        "dithered": np.clip(np.round(soft * 255 + rng.uniform(-1, 1, soft.shape)) / 255, 0, 1),
        "model": depth.normalize_relative(model),
        "normalized": depth.normalize_relative(soft * 3.7 + 11.0),
        "normalized 8-bit": depth.normalize_relative(np.round(soft * 255)),
    }


@pytest.mark.parametrize("encoding", ["hard", "float", "8-bit", "16-bit", "dithered", "model", "normalized",
                                      "normalized 8-bit"])
def test_default_focus_finds_the_painted_subject_in_every_encoding(encoding):
    """The issue's case: a soft painted map has no empty histogram bin, and the old search grew its region over the
    whole frame (focus on the backdrop). Every encoding of the same scene must focus on the person."""
    from scipy import ndimage

    hard, soft, person = painted_scene()
    d = (hard if encoding == "hard" else _encodings(soft)[encoding]).astype(np.float32)
    s = subj.subject_focus(d)
    core = ndimage.binary_erosion(person, iterations=20)  # the person away from the brush's ramps
    lo, hi = np.percentile(d[core], [1, 99])
    assert lo - 0.01 <= s.d_f <= hi + 0.01, (s, lo, hi)
    assert person[s.y, s.x]
    assert s.regions >= 2 and 0.1 < s.share < 0.5
    # the same subject: the focused pixels (within 2 % of the map's range of d_f) are mostly the person's
    focused = np.abs(d - s.d_f) < 0.02 * float(np.ptp(d))
    assert person[focused].mean() > 0.8


def test_default_focus_is_the_same_through_every_reader(tmp_path):
    """The painted map written as an 8-bit PNG, a 16-bit PNG, an EXR and an NPY and read as ``render`` reads it:
    one subject, the focus within 1/255 of the float map's."""
    from bokehray.app.render_job import read_map

    _, soft, person = painted_scene(240, 320, brush=5.0)
    image = np.zeros((240, 320, 3), np.float32)
    want = subj.subject_focus(soft)
    for name in ("d8.png", "d16.png", "d.exr", "d.npy"):
        path = tmp_path / name
        if name == "d8.png":
            _write_png8(path, soft)
        else:
            br.write_disparity(path, soft)
        d, _ = read_map(image, disparity=str(path))
        s = subj.subject_focus(d)
        assert abs(s.d_f - want.d_f) <= 1.5 / 255 and person[s.y, s.x], name


@pytest.mark.parametrize("side", [513, 1024, 2000])
@pytest.mark.parametrize("pattern", ["columns", "rows", "checker", "period 4"])
def test_default_focus_sees_every_phase_of_a_periodic_map(side, pattern):
    """The default focus subsampled maps above 512 px with a regular step, which saw one phase of a map of period 1-2
    px: a map half at 1 and half at 0 read as "100 % at d 0". The samples' offsets vary now: each half holds about
    half of the frame, and the nearer one is chosen."""
    from bokehray.photo.subject import subject_focus

    yy, xx = np.mgrid[:side, :side]
    d = {"columns": xx % 2, "rows": yy % 2, "checker": (xx + yy) % 2, "period 4": xx % 4 < 2}[pattern]
    s = subject_focus(d.astype(np.float32))
    assert s.d_f == 1.0 and 0.42 < s.share < 0.58, s


def test_render_says_the_painted_subject_it_chose(tmp_path, capsys):
    _, soft, _person = painted_scene(120, 160, brush=3.0)
    img, disp = tmp_path / "p.png", tmp_path / "d.png"
    br.write_image(img, np.full((120, 160, 3), 0.4, np.float32))
    _write_png8(disp, soft)
    code, out, err = run(capsys, "render", img, "--disparity", disp, "-o", tmp_path / "o.png")
    assert code == 0 and err == ""
    line = next(x for x in out.splitlines() if x.startswith("focus: on the subject"))
    d_f = float(line.split("d_f = ")[1].split(":")[0])
    assert 0.79 <= d_f <= 0.87 and "the nearest depth region holding 3% or more" in line
    assert "depth: read disparity" in out  # the range the map holds


@given(hnp.arrays(np.float32, st.tuples(st.integers(1, 40), st.integers(1, 40)),
                  elements=st.floats(0, 1, width=32)))
def test_default_focus_is_a_disparity_of_the_map(d):
    subject = subj.subject_focus(d)
    assert float(d.min()) <= subject.d_f <= float(d.max())
    assert subject.d_f in d
    assert 0 <= subject.x < d.shape[1] + 1 and 0 <= subject.y < d.shape[0] + 1
    assert 0 < subject.share <= 1 + 1e-9


def test_empty_stretches_of_the_histogram_are_not_regions():
    """A flat map said "2 regions found": the smoothed histogram falls to 0 beyond the one value and its first 0 was
    a cut, so the 249 empty bins after it made a second region. Empty stretches join a neighbour; the focus stays."""
    for v in (0.0, 0.4, 1.0):
        s = subj.subject_focus(np.full((48, 64), v, np.float32))
        assert (s.regions, s.d_f, s.share) == (1, float(np.float32(v)), pytest.approx(1.0)), s
        assert "1 region found" in s.describe()
    hist = np.zeros(256)
    hist[[3, 60, 61, 200]] = [0.5, 0.2, 0.1, 0.2]  # three surfaces, empty bins before, between and after them
    regions = subj.depth_regions(hist)
    assert len(regions) == 3 and all(hist[lo : hi + 1].sum() > 0 for lo, hi in regions)
    assert regions[0][0] == 0 and regions[-1][1] == 255  # still from the first bin to the last
    assert subj.depth_regions(np.zeros(256)) == [(0, 255)]


# --------------------------------------------------------------------------- depth conventions


@given(hnp.arrays(np.float64, st.tuples(st.integers(2, 30), st.integers(2, 30)),
                  elements=st.floats(-1e4, 1e4, allow_nan=False)),
       st.booleans())
def test_normalize_is_in_range_and_keeps_the_order(v, invert):
    if v.max() == v.min():
        with pytest.raises(br.InputError, match="constant"):
            depth.normalize_relative(v)
        return
    d = depth.normalize_relative(v, invert=invert)
    assert d.dtype == np.float32 and d.min() >= 0 and d.max() <= 1
    flat_v, flat_d = v.ravel(), d.ravel().astype(np.float64)
    order = np.argsort(flat_v, kind="stable")
    steps = np.diff(flat_d[order])
    assert (steps <= 1e-6).all() if invert else (steps >= -1e-6).all()


_MAP_DTYPES = st.sampled_from([np.float32, np.float64, np.uint8, np.uint16, np.int32])


@given(st.data(), _MAP_DTYPES, st.tuples(st.integers(1, 40), st.integers(1, 40)),
       st.lists(st.floats(0, 100), min_size=1, max_size=3))
def test_percentiles_are_numpys_bit_for_bit(data, dtype, shape, q):
    """The partition in the map's own dtype gives np.percentile's float64 result exactly (ties, few values, any q)."""
    elements = st.floats(-1e4, 1e4, width=32) if np.dtype(dtype).kind == "f" else st.integers(0, 9)
    v = data.draw(hnp.arrays(dtype, shape, elements=elements))
    assert depth.percentiles(v, tuple(q)) == tuple(float(x) for x in np.percentile(np.asarray(v, np.float64), q))


@given(st.data(), _MAP_DTYPES, st.tuples(st.integers(1, 700), st.integers(1, 600)), st.booleans())
def test_normalize_is_the_float64_expression_bit_for_bit(data, dtype, shape, invert):
    """Bands on threads, percentiles by partition: the values of the whole-frame float64 expression it replaced."""
    elements = st.floats(-1e4, 1e4, width=32) if np.dtype(dtype).kind == "f" else st.integers(0, 9)
    v = data.draw(hnp.arrays(dtype, shape, elements=elements))
    w = np.asarray(v, np.float64)
    lo, hi = (float(x) for x in np.percentile(w, depth.NORMALIZE_PERCENTILES))
    if not hi > lo:
        lo, hi = float(w.min()), float(w.max())
    if not hi > lo:
        return
    d = np.clip((w - lo) / (hi - lo), 0.0, 1.0)
    want = (1.0 - d if invert else d).astype(np.float32)
    got, (glo, ghi, _) = depth.normalize_relative(v, invert=invert, with_bounds=True)
    assert (glo, ghi) == (lo, hi) and got.dtype == np.float32 and np.array_equal(got, want)


def test_normalize_uses_robust_percentiles():
    rng = np.random.default_rng(0)
    v = rng.uniform(0.39, 6.87, (200, 200))  # a raw relative inverse-depth map
    v[0, 0] = 1e6  # one wild outlier does not squash the rest
    d = depth.normalize_relative(v)
    assert d[0, 0] == 1.0
    assert 0.45 < float(np.median(d)) < 0.55


def test_normalize_refuses_a_single_value_as_a_constant_map():
    """A 0-d map is one depth: refused with the constant map's message (the banded passes index rows)."""
    with pytest.raises(br.InputError, match="constant"):
        depth.normalize_relative(np.float32(3.0))


def test_reversed_map_is_flagged_and_the_right_one_is_not(demo):
    assert depth.looks_reversed(demo.disparity) == (False, "")
    flagged, why = depth.looks_reversed(1.0 - demo.disparity)
    assert flagged and "border" in why


@pytest.mark.skipif(not DEVSET.exists(), reason="the path-traced dev set is not here")
@pytest.mark.parametrize("name", DEV_SCENES)
def test_reversed_heuristic_on_the_devset(name):
    d = br.read_disparity(DEVSET / name / "disparity.exr")
    assert not depth.looks_reversed(d)[0]
    assert depth.looks_reversed(1.0 - d)[0]


def test_missing_depth_is_infinitely_far():
    z = np.full((8, 10), 2.0)
    z[:, :5] = 4.0
    z[0, 0], z[1, 1], z[2, 2] = 0.0, -3.0, np.inf
    d, norm = br.disparity_from_depth(z, source="z.npy")
    assert depth.missing_depth_share(z) == pytest.approx(3 / 80)
    assert d[0, 0] == d[1, 1] == d[2, 2] == 0.0
    assert norm.z_near_m == 2.0 and math.isinf(norm.z_far_m)
    z[3, 3] = np.nan
    with pytest.raises(br.InputError, match=r"z\.npy: .*NaN at \(y, x\) = \(3, 3\)"):
        br.disparity_from_depth(z, source="z.npy")
    with pytest.raises(br.InputError, match="no pixel has a depth"):
        br.disparity_from_depth(np.zeros((3, 3)), source="z.npy")


def test_integer_depth_needs_a_scale(tmp_path):
    from PIL import Image

    mm = np.full((6, 8), 1500, np.uint16)
    mm[:, 4:] = 3000
    Image.fromarray(mm).save(tmp_path / "mm.png")
    with pytest.raises(br.InputError, match=r"mm\.png: holds integer codes .*--depth-scale"):
        depth.read_depth(tmp_path / "mm.png")
    z = depth.read_depth(tmp_path / "mm.png", scale=0.001)
    np.testing.assert_allclose(z, mm * 0.001)
    with pytest.raises(br.InputError, match="--depth-scale"):
        depth.read_depth(tmp_path / "mm.png", scale=0.0)


# --------------------------------------------------------------------------- the command line


@pytest.fixture
def files(tmp_path, demo):
    return {
        "img": br.write_image(tmp_path / "in.png", demo.image),
        "disp": br.write_disparity(tmp_path / "d.png", demo.disparity),
        "rev": br.write_disparity(tmp_path / "rev.png", 1.0 - demo.disparity),
    }


def test_image_and_map_alone_render_with_defaults_said(files, tmp_path, capsys, demo):
    code, out, err = run(capsys, "render", files["img"], "--disparity", files["disp"], "-o", tmp_path / "o.png")
    assert code == 0, err
    assert "blur: --amount 50 -> K = 13.8 px (3.0% of the 462-px diagonal) (the default)" in out
    assert "focus: on the subject" in out and err == ""
    d_f = float(out.split("d_f = ")[1].split(" ")[0].rstrip(":"))
    assert 0.86 <= d_f <= 0.92
    assert br.read_image(tmp_path / "o.png").shape == demo.image.shape


def test_amount_is_the_same_look_at_two_resolutions(tmp_path, capsys):
    small, big = build_demo_scene(width=192, height=128), build_demo_scene(width=384, height=256)
    ks = []
    for s, name in ((small, "s"), (big, "b")):
        img, disp = br.write_image(tmp_path / f"{name}.png", s.image), br.write_disparity(tmp_path / f"{name}d.png",
                                                                                          s.disparity)
        code, out, err = run(capsys, "render", img, "--disparity", disp, "-o", tmp_path / f"{name}o.png",
                             "--amount", 40, "--focus", 0.5)
        assert code == 0, err
        ks.append(float(out.split("(K = ")[1].split(" ")[0]))
    assert ks[1] == pytest.approx(2 * ks[0], rel=1e-3)  # twice the pixels across: twice K, the same look


def test_reversed_map_warns_and_invert_renders_the_same(files, tmp_path, capsys):
    code, _out, err = run(capsys, "render", files["img"], "--disparity", files["rev"], "-o", tmp_path / "r.png",
                         "--blur", 8, "--focus", 0.5)
    assert code == 0
    assert err.startswith("bokehray: warning:") and "rev.png" in err and "--invert" in err and err.count("\n") == 1
    code, _, err = run(capsys, "render", files["img"], "--disparity", files["rev"], "-o", tmp_path / "i.png",
                       "--blur", 8, "--focus", 0.5, "--invert")
    assert code == 0 and err == ""
    code, _, err = run(capsys, "render", files["img"], "--disparity", files["disp"], "-o", tmp_path / "n.png",
                       "--blur", 8, "--focus", 0.5)
    a, b = br.read_image(tmp_path / "i.png"), br.read_image(tmp_path / "n.png")
    assert np.abs(a - b).max() < 2e-2  # 1 - (1 - d) through 16-bit codes: the same render up to rounding


def test_relative_map_of_any_range_with_normalize(files, tmp_path, capsys, demo):
    raw = (0.39 + 6.48 * demo.disparity).astype(np.float32)  # a raw relative inverse-depth map, 0.39 .. 6.87
    np.save(tmp_path / "rel.npy", raw)
    code, _, err = run(capsys, "render", files["img"], "--disparity", tmp_path / "rel.npy", "-o", tmp_path / "o.png")
    assert code == 2 and "rel.npy" in err and "--normalize" in err
    code, out, err = run(capsys, "render", files["img"], "--disparity", tmp_path / "rel.npy", "-o", tmp_path / "o.png",
                         "--normalize")
    assert code == 0, err
    assert "normalised from [" in out and "percentiles" in out


def test_millimetre_png_with_depth_scale_and_a_lens(tmp_path, capsys, files):
    from PIL import Image

    h, w = 256, 384
    mm = np.full((h, w), 4000, np.uint16)
    mm[60:200, 200:330] = 1200  # a subject at 1.2 m before a wall at 4 m
    mm[:20] = 0  # no measurement: sky
    Image.fromarray(mm).save(tmp_path / "mm.png")
    code, _, err = run(capsys, "render", files["img"], "--depth", tmp_path / "mm.png", "-o", tmp_path / "o.png")
    assert code == 2 and "mm.png" in err and "--depth-scale" in err
    code, out, err = run(capsys, "render", files["img"], "--depth", tmp_path / "mm.png", "-o", tmp_path / "o.png",
                         "--depth-scale", 0.001, "--focal-length", 50, "--f-number", 2, "--focus-distance", 1.2)
    assert code == 0, err
    assert "7.8% of" in out and "infinitely far (sky)" in out
    assert "d_f = 1.0000" in out  # focused on the subject, the nearest depth
    assert "depth: read " in out and ": 1.2 .. 4 m (nearest .. farthest" in out  # the range it read, in metres
    assert "focus: at 1.2 m (--focus-distance)" in out
    # the default focus on metric depth says where it lies in metres
    code, out, err = run(capsys, "render", files["img"], "--depth", tmp_path / "mm.png", "-o", tmp_path / "o.png",
                         "--depth-scale", 0.001)
    assert code == 0, err
    line = next(x for x in out.splitlines() if x.startswith("focus: on the subject"))
    assert "(1.2 m away)" in line


# --------------------------------------------------------------------------- clipped highlights


def _lamp_scene():
    """A dark frame with a warm lamp of radiance (6, 3, 1.5) of radius 4 px, stored clipped in 8 bits."""
    h = w = 40
    yy, xx = np.mgrid[:h, :w]
    cover = np.clip(4.5 - np.hypot(yy - 20, xx - 20), 0, 1)[..., None]  # antialiased rim: partial coverage
    hdr = 0.02 + cover * np.array([6.0, 3.0, 1.5])
    codes = np.round(br.colour.linear_to_srgb(np.clip(hdr, 0, 1)) * 255)
    return hdr.astype(np.float32), br.colour.srgb_to_linear(codes / 255.0)


def test_a_clipped_lamp_is_re_inflated_with_its_rim_colour():
    hdr, img8 = _lamp_scene()
    out, found = highlights.reconstruct_highlights(img8)
    assert found == 1
    clipped = img8 >= highlights.CLIP_LEVEL
    np.testing.assert_array_equal(out[~clipped], img8[~clipped])  # unclipped channels are exact: kept
    assert (out[clipped] >= 1.0).all()
    centre = out[20, 20]
    assert centre.max() == pytest.approx(highlights.HIGHLIGHT_GAIN)
    assert centre[0] > centre[1] > centre[2] - 1e-6  # warm, as the rim shows
    # the light's energy comes back much closer to the truth than the clipped file has it
    assert abs(out.sum() - hdr.sum()) < 0.5 * abs(img8.sum() - hdr.sum())


def test_reconstruction_leaves_unclipped_and_one_channel_clipped_images_alone():
    rng = np.random.default_rng(0)
    img = (rng.random((30, 30, 3)) * 0.9).astype(np.float32)
    assert highlights.reconstruct_highlights(img)[1] == 0
    red = img.copy()
    red[5:12, 5:12, 0] = 1.0  # a saturated red clipped in one channel: no white core, not a light
    out, found = highlights.reconstruct_highlights(red)
    assert found == 0 and np.array_equal(out, red)


def test_reconstruction_in_place_equals_the_copy_with_neighbouring_highlights():
    """Lamps a few pixels apart (their boxes, rims and rings overlap): written into the photo itself
    (``overwrite=True``) the result is the copy's, bit for bit, and by default the photo is not written to."""
    _hdr, lamp = _lamp_scene()
    img = np.concatenate([lamp[:, :28], lamp[:, 14:], lamp[:, 12:30]], axis=1)  # three lamps 10-12 px apart
    img = np.concatenate([img, img[:, ::-1] * np.float32(0.995)], axis=0).astype(np.float32)
    img[3, 3] = img[3, 60] = (1.0, 1.0, 0.2)  # two clipped pixels without a white core
    before = img.copy()
    out, found = highlights.reconstruct_highlights(img)
    assert found == 6 and np.array_equal(img, before)
    same, found_in_place = highlights.reconstruct_highlights(img, overwrite=True)
    assert same is img and found_in_place == found
    np.testing.assert_array_equal(same.view(np.uint32), out.view(np.uint32))


def test_render_reconstructs_for_8_bit_but_never_for_exr(tmp_path, capsys):
    _hdr, img8 = _lamp_scene()
    d = np.full(img8.shape[:2], 0.5, np.float32)
    br.write_disparity(tmp_path / "d.png", d)
    png, exr = br.write_image(tmp_path / "l.png", img8), br.write_image(tmp_path / "l.exr", img8)
    common = ["--disparity", tmp_path / "d.png", "--blur", 10, "--focus", 0.0]
    code, out, _ = run(capsys, "render", png, *common, "-o", tmp_path / "a.exr")
    assert code == 0 and "1 clipped highlight reconstructed" in out
    code, out, _ = run(capsys, "render", png, *common, "-o", tmp_path / "b.exr", "--no-highlight-reconstruction")
    assert code == 0 and "highlight" not in out
    code, out, _ = run(capsys, "render", exr, *common, "-o", tmp_path / "c.exr")
    assert code == 0 and "highlight" not in out
    a, b, c = (br.read_image(tmp_path / f"{n}.exr") for n in "abc")
    assert a.sum() > 2 * b.sum() and np.allclose(b, c, atol=1e-6)


def test_progress_bar_covers_every_stage_on_a_terminal(files, tmp_path, capsys, monkeypatch):
    import sys

    monkeypatch.setattr(sys.stderr, "isatty", lambda: True, raising=False)
    for quality in ("preview",):
        code = main([str(a) for a in ("render", files["img"], "--disparity", files["disp"], "-o",
                                      tmp_path / "o.png", "--blur", 6, "--focus", 0.5, "--quality", quality)])
        err = capsys.readouterr().err
        assert code == 0
        for stage in ("read", "render", "write"):
            assert stage in err, (quality, stage, err)
        if quality == "preview":  # the preview reports its layers: the bar reaches the end of the render stage
            assert " 93%" in err  # read 5 + render 60 of 70 = 93 %: every layer was counted


# --------------------------------------------------------------------------- the highlight reconstruction's image ops


@st.composite
def _masks(draw):
    h, w = draw(st.integers(1, 24)), draw(st.integers(1, 24))
    seed = draw(st.integers(0, 2**32 - 1))
    return np.random.default_rng(seed).random((h, w)) < draw(st.floats(0.0, 1.0))


@given(mask=_masks())
def test_label8_is_scipys_8_connected_labelling(mask):
    from scipy import ndimage

    labels, boxes = highlights.label8(mask)
    want, n = ndimage.label(mask, structure=np.ones((3, 3), bool))
    np.testing.assert_array_equal(labels, want)
    assert boxes == [(s[0].start, s[0].stop, s[1].start, s[1].stop) for s in ndimage.find_objects(want)]
    assert len(boxes) == n


@given(mask=_masks(), steps=st.integers(1, 5))
def test_dilate8_is_scipys_square_dilation(mask, steps):
    from scipy import ndimage

    np.testing.assert_array_equal(highlights.dilate8(mask, steps), ndimage.binary_dilation(mask, np.ones((3, 3)), steps))


@given(mask=_masks(), cap=st.floats(0.5, 4.0))
def test_edge_distance_is_scipys_distance_transform_capped(mask, cap):
    from scipy import ndimage

    want = np.minimum(ndimage.distance_transform_edt(np.pad(mask, 1))[1:-1, 1:-1], cap)
    np.testing.assert_allclose(highlights.edge_distance(mask, cap), want, rtol=1e-12, atol=1e-12)


@pytest.mark.slow
def test_the_highlight_reconstruction_does_not_import_scipy_ndimage():
    """A render's start-up budget: scipy.ndimage alone costs about 0.2 s to import."""
    import subprocess
    import sys

    code = ("import sys, numpy as np; from bokehray.photo import highlights; img = np.full((20, 20, 3), 0.2, np.float32); "
            "img[8:11, 8:11] = 1.0; assert highlights.reconstruct_highlights(img)[1] == 1; "
            "print('scipy.ndimage' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"



@given(seed=st.integers(0, 2**31 - 1), k=st.floats(0.0, 500.0), d_f=st.floats(0.0, 1.0), wide=st.booleans())
def test_the_clis_max_coc_from_the_maps_ends_is_the_frames(seed, k, d_f, wide):
    """The CLI's max CoC from the nearest and farthest disparity equals the largest CoC radius of the frame."""
    from bokehray.app.render_job import max_coc_px

    rng = np.random.default_rng(seed)
    d = rng.random((13, 17)) ** rng.uniform(0.2, 5.0)
    d = d.astype(np.float64 if wide else np.float32)
    blur = br.BlurParams(k, d_f)
    assert max_coc_px(blur, d) == float(blur.coc_radius(d).max())
    assert max_coc_px(blur, np.zeros((0, 3), np.float32)) == 0.0


# --------------------------------------------------------------------------- lights, not white surfaces


def _white_shirt(side=256, cast=(1.0, 0.94, 0.86)):
    """A clipped white fabric (radiance 1.0-1.9 in folds, a warm cast) over a grey backdrop, stored in 8 bits."""
    yy, xx = np.mgrid[:side, :side] / side
    shirt = (np.abs(xx - 0.5) < 0.28) & (yy > 0.3)
    folds = 1.45 + 0.45 * np.sin(18 * xx + 4 * yy) * np.cos(7 * yy)
    hdr = np.where(shirt[..., None], folds[..., None] * np.array(cast), 0.18)
    codes = np.round(br.colour.linear_to_srgb(np.clip(hdr, 0, 1)) * 255)
    return br.colour.srgb_to_linear(codes / 255.0).astype(np.float32)


def test_a_clipped_white_surface_keeps_its_value():
    """A white shirt clipped in a photo took a gain of 5 (it glowed when blurred, and its rim took the colour of its
    edge): a large clipped plateau whose surroundings do not rise towards it is not a light."""
    img = _white_shirt()
    out, found = highlights.reconstruct_highlights(img)
    assert found == 0 and np.array_equal(out, img)


def test_a_large_light_with_a_glow_is_still_reconstructed():
    """A lamp too large to count as small (3 % of the frame) whose surroundings rise towards it (a glow)."""
    side = 200
    yy, xx = np.mgrid[:side, :side]
    r = np.hypot(yy - 100, xx - 100)
    hdr = np.where(r < 20, 4.0, 0.02 + 3.0 * (20.0 / np.maximum(r, 20.0)) ** 3)[..., None] * np.ones(3)
    codes = np.round(br.colour.linear_to_srgb(np.clip(hdr, 0, 1)) * 255)
    img = br.colour.srgb_to_linear(codes / 255.0).astype(np.float32)
    assert (img[..., 0] >= highlights.CLIP_LEVEL).sum() > highlights.LIGHT_MAX_PX
    out, found = highlights.reconstruct_highlights(img)
    assert found == 1 and out[100, 100].max() == pytest.approx(highlights.HIGHLIGHT_GAIN)
    plateau = np.where(r < 20, 4.0, 0.02)[..., None] * np.ones(3)  # the same disc, sharp-edged: a white surface
    flat = br.colour.srgb_to_linear(np.round(br.colour.linear_to_srgb(np.clip(plateau, 0, 1)) * 255) / 255.0)
    assert highlights.reconstruct_highlights(flat.astype(np.float32))[1] == 0


def test_small_clipped_regions_are_lights_at_every_frame_size():
    for side in (40, 400, 4000):
        img = np.full((side, side, 3), 0.05, np.float32)
        n = int(max(highlights.LIGHT_MAX_PX, highlights.LIGHT_MAX_SHARE * side * side) ** 0.5)
        img[10 : 10 + n, 10 : 10 + n] = 1.0  # a square as large as a light may be
        assert highlights.reconstruct_highlights(img)[1] == 1, side


@pytest.mark.skipif(not DEVSET.exists(), reason="the path-traced dev set is not here")
def test_the_dev_set_lamps_are_all_still_lights(tmp_path):
    """The lamps of d3 (7 white-cored clipped regions, 0.04-0.10 % of the frame each) are reconstructed exactly as
    when every clipped region with a white core was taken for a light."""
    hdr = br.read_image(DEVSET / "d3_lamps_ring_writing" / "image.exr")
    img8 = br.read_image(br.write_image(tmp_path / "d3.png", np.clip(hdr, 0, 1)))
    out, found = highlights.reconstruct_highlights(img8)
    share = highlights.LIGHT_MAX_SHARE
    try:
        highlights.LIGHT_MAX_SHARE = 1.0
        every, found_every = highlights.reconstruct_highlights(img8)
    finally:
        highlights.LIGHT_MAX_SHARE = share
    assert found == found_every == 7
    np.testing.assert_array_equal(out, every)
