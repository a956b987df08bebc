"""The default focus on faces (bokehray.photo.faces): the eyes of the nearest sizeable face when the photo shows
faces, read at the eyes; the subject search, exactly as before, when it shows none."""

from __future__ import annotations

import numpy as np
import pytest
import skimage.data

import bokehray as br
from bokehray.app.cli import main
from bokehray.app.demo import build_demo_scene
from bokehray.colour import srgb_to_linear
from bokehray.photo import faces
from bokehray.photo import subject as subj

EYES = ((202, 101), (247, 102))  # the astronaut's eyes (pixels of the 512 x 512 photo), by eye
D_HEAD, D_CHEST = 0.839, 0.859


def _linear(codes: np.ndarray) -> np.ndarray:
    return srgb_to_linear(codes.astype(np.float32) / 255.0).astype(np.float32)


@pytest.fixture(scope="module")
def astronaut():
    return _linear(skimage.data.astronaut())


def _portrait_map() -> np.ndarray:
    """The head behind the chest, as a painted portrait map often has it (the subject search picks the chest)."""
    d = np.full((512, 512), 0.1, np.float32)
    d[200:, 20:370] = D_CHEST
    d[10:200, 150:305] = D_HEAD
    return d


def test_the_astronaut_has_one_face_and_its_two_eyes(astronaut):
    found = faces.detect_faces(astronaut)
    assert len(found) == 1
    (face,) = found
    assert face.x < 210 < face.x + face.w and face.y < 100 < face.y + face.h
    assert len(face.eyes) == 2
    for (x, y), (wx, wy) in zip(face.eyes, EYES):
        assert abs(x - wx) <= 8 and abs(y - wy) <= 8, face.eyes


def test_default_focus_is_the_eyes_not_the_nearer_chest(astronaut):
    d = _portrait_map()
    assert subj.subject_focus(d).d_f == pytest.approx(D_CHEST)  # what the subject search alone chooses
    focus = subj.default_focus(astronaut, d)
    assert isinstance(focus, faces.EyesFocus)
    assert focus.d_f == pytest.approx(D_HEAD)
    assert abs(focus.x - 224) <= 8 and abs(focus.y - 101) <= 8
    assert focus.describe().startswith(f"the eyes of the nearest face at ({focus.x}, {focus.y}), d_f = 0.839")


def test_the_depth_is_read_at_the_eyes_not_the_hairline_or_the_cheek(astronaut):
    d = np.full((512, 512), 0.1, np.float32)
    (face,) = faces.detect_faces(astronaut)
    d[face.y : face.y + face.h, face.x : face.x + face.w] = 0.70  # cheeks, nose, chin
    d[face.y : face.y + face.h // 4, face.x : face.x + face.w] = 0.95  # forehead and hairline
    for x, y in face.eyes:
        d[y - 4 : y + 5, x - 6 : x + 7] = 0.80  # the eyes
    assert subj.default_focus(astronaut, d).d_f == pytest.approx(0.80)


def test_the_nearest_of_two_faces_is_chosen(astronaut):
    pair = np.concatenate([astronaut, astronaut], axis=1)  # the same face twice, side by side
    d = np.full(pair.shape[:2], 0.1, np.float32)
    d[:, :512] = 0.6
    d[:, 512:] = 0.7  # the right face is nearer
    focus = subj.default_focus(pair, d)
    assert isinstance(focus, faces.EyesFocus) and focus.faces == 2
    assert focus.x > 512 and focus.d_f == pytest.approx(0.7)
    assert "(2 sizeable faces found)" in focus.describe()


def test_faces_are_found_on_a_downscaled_copy_at_any_size(astronaut):
    from PIL import Image

    big = _linear(np.asarray(Image.fromarray(skimage.data.astronaut()).resize((1600, 1600), Image.BICUBIC)))
    (face,) = faces.detect_faces(big)
    s = 1600 / 512
    for (x, y), (wx, wy) in zip(face.eyes, EYES):
        assert abs(x - wx * s) <= 8 * s and abs(y - wy * s) <= 8 * s, face.eyes


def test_a_small_face_is_not_sizeable(astronaut):
    """A face a tenth of the frame's side, far below ``FACE_MIN_SHARE``: the subject search decides."""
    frame = np.full((2048, 2048, 3), 0.2, np.float32)
    frame[900:1012, 900:1012] = astronaut[::4, ::4][:112, :112]
    d = np.full((2048, 2048), 0.3, np.float32)
    d[800:1200, 800:1200] = 0.7
    assert subj.default_focus(frame, d) == subj.subject_focus(d)


@pytest.mark.parametrize("name", ["chelsea", "coffee", "rocket", "camera", "demo", "noise"])
def test_photos_without_faces_fall_back_to_the_subject_search_exactly(name):
    if name == "demo":
        scene = build_demo_scene(width=384, height=256)
        img, d = scene.image, scene.disparity
    else:
        if name == "noise":
            img = np.random.default_rng(3).random((300, 400, 3)).astype(np.float32)
        else:
            codes = getattr(skimage.data, name)()
            img = _linear(codes if codes.ndim == 3 else np.repeat(codes[..., None], 3, axis=2))
        h, w = img.shape[:2]
        yy, xx = np.mgrid[:h, :w]
        d = (0.2 + 0.6 * np.exp(-((yy - h / 2) ** 2 + (xx - w / 2) ** 2) / (0.1 * h * w))).astype(np.float32)
    assert faces.detect_faces(img) == []
    assert subj.default_focus(img, d) == subj.subject_focus(d)
    assert subj.default_focus(None, d) == subj.subject_focus(d)


def test_render_says_it_focused_on_the_eyes(astronaut, tmp_path, capsys):
    img, disp = tmp_path / "a.png", tmp_path / "d.png"
    br.write_image(img, astronaut)
    br.write_disparity(disp, _portrait_map())
    code = main([str(a) for a in ("render", img, "--disparity", disp, "-o", tmp_path / "o.png", "--amount", 20)])
    out = capsys.readouterr().out
    assert code == 0
    line = next(x for x in out.splitlines() if x.startswith("focus:"))
    assert line.startswith("focus: the eyes of the nearest face at (") and "d_f = 0.839" in line, line
