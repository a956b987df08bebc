"""Batches and sweeps for photographers: each sweep frame's focus drawn small in the GIF (--gif-labels), and a
batch's workers lowered to what the memory available holds."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

import bokehray as br
from bokehray.app import batch
from bokehray.app.cli import main

H, W = 120, 200


def _shoot(tmp_path, n=1):
    rng = np.random.default_rng(3)
    for i in range(n):
        d = np.tile(np.linspace(0.1, 1, W, dtype=np.float32), (H, 1))
        br.write_image(tmp_path / "photos" / f"p{i}.png", (rng.random((H, W, 3)) * 0.5 + 0.3).astype(np.float32))
        br.write_disparity(tmp_path / "maps" / f"p{i}.png", d)
    return tmp_path / "photos", tmp_path / "maps"


def _corner(gif_path, frame):
    from PIL import Image

    gif = Image.open(gif_path)
    gif.seek(frame)
    return np.asarray(gif.convert("RGB"))[:14, :90].astype(np.int64)


def test_gif_labels_draw_each_frames_focus_small_in_its_corner(tmp_path, capsys):
    photos, maps = _shoot(tmp_path)
    common = [str(photos / "p0.png"), "--disparity", str(maps / "p0.png"), "--blur", "6", "--focus", "0.2,0.8",
              "--workers", "1", "--no-grain"]
    assert main(["render", *common, "-o", str(tmp_path / "plain")]) == 0
    assert main(["render", *common, "-o", str(tmp_path / "labelled"), "--gif-labels"]) == 0
    capsys.readouterr()
    for frame in (0, 1):
        plain = _corner(tmp_path / "plain" / "p0_focus_sweep.gif", frame)
        labelled = _corner(tmp_path / "labelled" / "p0_focus_sweep.gif", frame)
        text = (labelled.min(axis=2) > 200).sum()  # white letters
        box = (labelled.max(axis=2) < 40).sum()  # on a black box
        assert text > 20 and box > 200, (frame, text, box)
        assert (plain.max(axis=2) < 40).sum() < 20  # the photo has no black corner of its own
    a, b = _corner(tmp_path / "labelled" / "p0_focus_sweep.gif", 0), _corner(tmp_path / "labelled" /
                                                                          "p0_focus_sweep.gif", 1)
    assert not np.array_equal(a > 200, b > 200)  # 0.200 and 0.800: different captions
    # the frames themselves carry no caption: they are the single renders
    assert (np.asarray(br.read_image(tmp_path / "labelled" / "p0_focus_0.200.png"))
            == br.read_image(tmp_path / "plain" / "p0_focus_0.200.png")).all()


def test_frame_captions():
    assert batch.frame_caption("focus", "0.600") == "focus 0.600"
    assert batch.frame_caption("focus", "0.600", {"focus_m": 2.4}) == "focus 0.600, 2.4 m"
    assert batch.frame_caption("focus", "0.000", {"focus_m": float("inf")}) == "focus 0.000"
    assert batch.frame_caption("blur", "12") == "blur K 12 px"


def test_gif_labels_on_a_single_render_is_refused(tmp_path, capsys):
    photos, maps = _shoot(tmp_path)
    code = main(["render", str(photos / "p0.png"), "--disparity", str(maps / "p0.png"), "-o", str(tmp_path / "o.png"),
                 "--gif-labels"])
    assert code == 2 and "--gif-labels" in capsys.readouterr().err


@given(st.integers(1, 64), st.integers(0, 200_000_000), st.integers(0, 1 << 40))
def test_fit_workers_keeps_the_planned_peak_within_the_available_share(requested, pixels, available):
    n = batch.fit_workers(requested, pixels, available)
    assert 1 <= n <= requested
    if n > 1:
        assert n * batch.render_peak_bytes(pixels) <= batch.MEMORY_SHARE * available


def test_the_12_mp_model_is_the_measured_peak():
    """1.64 GB peak RSS measured for a 12 MP JPEG rendered at the defaults (grain, highlights, eyes)."""
    assert batch.render_peak_bytes(12_000_000) / 2**30 == pytest.approx(1.53, abs=0.1)


def test_a_batch_lowers_its_workers_to_fit_the_memory_available(tmp_path, capsys, monkeypatch):
    photos, maps = _shoot(tmp_path, n=2)
    peak = batch.render_peak_bytes(H * W)
    monkeypatch.setattr("bokehray._memory.available_bytes", lambda: int(1.5 * peak / batch.MEMORY_SHARE))
    code = main(["render", str(photos), "--disparity", str(maps), "-o", str(tmp_path / "out"), "--blur", "4",
                 "--focus", "0.5", "--workers", "2"])
    err = capsys.readouterr().err
    assert code == 0
    assert "workers: 1 instead of 2, to fit the memory available" in err
    assert "on inline" in err or "1 worker" in err, err
    monkeypatch.setattr("bokehray._memory.available_bytes", lambda: 1 << 40)
    code = main(["render", str(photos), "--disparity", str(maps), "-o", str(tmp_path / "out2"), "--blur", "4",
                 "--focus", "0.5", "--workers", "2"])
    err = capsys.readouterr().err
    assert code == 0 and "instead of" not in err and "2 workers" in err, err


def test_a_resumed_sweep_s_captions_do_not_mix_metres_and_none(tmp_path):
    """A resumed run knows the distances of the frames it rendered only: every caption drops them, not some."""
    frames = [tmp_path / "a_focus_0.2.png", tmp_path / "a_focus_0.8.png"]
    labels = {str(frames[0]): "0.200", str(frames[1]): "0.800"}
    both = {str(frames[0]): {"focus_m": 3.0}, str(frames[1]): {"focus_m": 1.5}}
    assert batch._captions("focus", frames, labels, both) == ["focus 0.200, 3 m", "focus 0.800, 1.5 m"]
    one = {str(frames[1]): {"focus_m": 1.5}}  # the first frame was skipped as already written
    assert batch._captions("focus", frames, labels, one) == ["focus 0.200", "focus 0.800"]
