"""bokehray render on many inputs: pairing rules, resume, the failure summary, focal sweeps, local vs Dask."""

from __future__ import annotations

import argparse
import itertools
import json

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

import bokehray as br
from bokehray.app.batch import find_pairs, frame_labels, parse_sweep
from bokehray.app.cli import main
from bokehray.colour import linear_to_srgb
from bokehray.errors import InputError

H, W = 40, 56


def _photo(i: int):
    rng = np.random.default_rng(100 + i)
    img = (rng.random((H, W, 3)) * 0.8).astype(np.float32)
    d = np.tile(np.linspace(0.1 * i % 1, 1, W, dtype=np.float32), (H, 1))
    d[H // 3: 2 * H // 3, W // 3: 2 * W // 3] = 0.9  # a near square: a depth edge
    return img, d


@pytest.fixture
def shoot(tmp_path):
    """photos/ p0..p2 .png; maps/ p0..p2 .png (same stem); mixed/ p<i>.png + p<i>_disp.png (suffix)."""
    for i in range(3):
        img, d = _photo(i)
        br.write_image(tmp_path / "photos" / f"p{i}.png", img)
        br.write_disparity(tmp_path / "maps" / f"p{i}.png", d)
        br.write_image(tmp_path / "mixed" / f"p{i}.png", img)
        br.write_disparity(tmp_path / "mixed" / f"p{i}_disp.png", d)
    return tmp_path


def run(capsys, *args):
    try:
        code = main([str(a) for a in args])
    except SystemExit as e:  # argparse's own errors (the same one-line format, exit 2)
        code = e.code
    out = capsys.readouterr()
    return code, out.out, out.err


def _files(folder):
    return sorted(p.name for p in folder.iterdir())


def test_same_stem_suffix_and_glob_pairing_give_the_single_file_renders(shoot, capsys):
    code, out, err = run(capsys, "render", shoot / "photos", "--disparity", shoot / "maps", "-o", shoot / "o1",
                         "--blur", 6, "--focus", 0.5, "--workers", 1)
    assert code == 0, err
    assert "3 rendered, 0 skipped (complete), 0 failed" in out
    code, _, err = run(capsys, "render", shoot / "mixed", "--disparity", shoot / "mixed", "--map-suffix", "_disp",
                       "-o", shoot / "o2", "--blur", 6, "--focus", 0.5, "--workers", 1)
    assert code == 0, err
    code, _, err = run(capsys, "render", f"{shoot}/photos/p*.png", "--disparity", f"{shoot}/maps/*.png",
                       "-o", shoot / "o3", "--blur", 6, "--focus", 0.5, "--workers", 1, "--quiet")
    assert code == 0, err
    for i in range(3):  # one output per input, byte for byte the single-file render of that pair
        code, _, err = run(capsys, "render", shoot / "photos" / f"p{i}.png", "--disparity",
                           shoot / "maps" / f"p{i}.png", "-o", shoot / "single" / f"p{i}.png", "--blur", 6,
                           "--focus", 0.5, "--quiet")
        assert code == 0, err
        want = (shoot / "single" / f"p{i}.png").read_bytes()
        for o in ("o1", "o2", "o3"):
            assert (shoot / o / f"p{i}.png").read_bytes() == want, (o, i)
    assert _files(shoot / "o2") == ["bokehray-batch.json", "p0.png", "p1.png", "p2.png"]  # the maps are no photos


def test_manifest_csv_pairing(shoot, capsys):
    (shoot / "pairs.csv").write_text("image,disparity\np0.png,maps/p0.png\nphotos/p2.png,maps/p2.png\n"
                                     "elsewhere.png,maps/p1.png\n")
    code, out, err = run(capsys, "render", shoot / "photos", "--disparity", shoot / "pairs.csv", "-o",
                         shoot / "out", "--blur", 6, "--focus", 0.5, "--output-format", "exr", "--workers", 1)
    assert code == 2
    assert "2 rendered" in out and f"{shoot / 'photos' / 'p1.png'}: no disparity map listed in" in err
    assert _files(shoot / "out") == ["bokehray-batch.json", "p0.exr", "p2.exr"]
    (shoot / "bad.csv").write_text("photo,map\np0.png,maps/p0.png\n")
    code, _, err = run(capsys, "render", shoot / "photos", "--disparity", shoot / "bad.csv", "-o", shoot / "o2",
                       "--blur", 6, "--focus", 0.5)
    assert code == 2 and err.count("\n") == 1 and "needs the columns image and disparity" in err


@pytest.mark.parametrize(("text", "message"), [
    ("image,disparity\np0.png,maps/p0.png,extra\n", "line 2: expected at most 2 fields (the header's image,disparity), got 3"),
    ("image,disparity\n\np0.png,maps/p0.png\np1.png,maps/p1.png,x,y\n", "line 4: expected at most 2 fields"),
    ("image,disparity\np0.png\n", "line 2: expected an image and a disparity path"),
    ("image,disparity\n", "the manifest CSV has no rows"),
    ("image,disparity\np0.png,maps/p0\0.png\n", "line 2: a path holds a NUL byte"),
    ("image,disparity\np\x000.png,maps/p0.png\n", "line 2: a path holds a NUL byte"),
    ("", "the manifest CSV has no rows"),
])
def test_malformed_manifest_rows_are_one_line_errors(shoot, capsys, text, message):
    """Issue: a row with more fields than the header gave a traceback (AttributeError on None.strip)."""
    (shoot / "m.csv").write_text(text)
    code, _out, err = run(capsys, "render", shoot / "photos", "--disparity", shoot / "m.csv", "-o", shoot / "o",
                         "--blur", 6, "--focus", 0.5, "--workers", 1)
    assert code == 2 and err.count("\n") == 1 and message in err and str(shoot / "m.csv") in err, err
    assert not (shoot / "o").exists()


def test_pairing_problems_are_named(shoot, tmp_path):
    br.write_disparity(shoot / "maps" / "p1.exr", _photo(1)[1])  # two maps for p1
    pairs = {p.image.name: p for p in find_pairs(str(shoot / "photos"), str(shoot / "maps"))}
    assert pairs["p0.png"].map.name == "p0.png"
    assert pairs["p1.png"].map is None and "2 disparity maps match" in pairs["p1.png"].problem
    with pytest.raises(InputError, match="the maps are among the images.*--map-suffix"):
        find_pairs(str(shoot / "mixed"), str(shoot / "mixed"))
    with pytest.raises(InputError, match="no such image file or folder"):
        find_pairs(str(tmp_path / "nowhere"), str(shoot / "maps"))


def test_failures_are_summarised_and_never_stop_the_batch(shoot, capsys):
    (shoot / "photos" / "broken.png").write_bytes(b"not a png")
    (shoot / "maps" / "broken.png").write_bytes(b"x")
    br.write_image(shoot / "photos" / "lonely.png", _photo(0)[0])
    br.write_image(shoot / "photos" / "small.png", _photo(0)[0][:20])
    br.write_disparity(shoot / "maps" / "small.png", _photo(0)[1])
    code, out, err = run(capsys, "render", shoot / "photos", "--disparity", shoot / "maps", "-o", shoot / "out",
                         "--blur", 6, "--focus", 0.5, "--workers", 2)
    assert code == 2
    assert "3 rendered, 0 skipped (complete), 3 failed" in out
    lines = err.strip().splitlines()
    assert lines[-4] == "bokehray: 3 inputs failed:"
    assert any("broken.png: cannot read" in x for x in lines)
    assert any("lonely.png: no disparity map named lonely.*" in x for x in lines)
    assert any("small.png: map is 56x40" in x and "--resize-disparity" in x for x in lines)
    assert "Traceback" not in err
    assert _files(shoot / "out") == ["bokehray-batch.json", "p0.png", "p1.png", "p2.png"]  # nothing partial


def test_photos_that_are_no_regular_files_are_listed_as_failed(shoot, capsys):
    """A FIFO, a dangling symbolic link and a link loop named as photos were neither rendered nor listed as failed."""
    import os

    photos, maps = shoot / "photos", shoot / "maps"
    os.mkfifo(photos / "pipe.png")
    (photos / "gone.png").symlink_to(photos / "nowhere.png")
    (photos / "loop.png").symlink_to(photos / "loop.png")
    for name in ("pipe.png", "gone.png", "loop.png"):
        br.write_disparity(maps / name, _photo(0)[1])
    code, out, err = run(capsys, "render", photos, "--disparity", maps, "-o", shoot / "out", "--blur", 6, "--focus",
                         0.5, "--workers", 1)
    assert code == 2 and "3 rendered, 0 skipped (complete), 3 failed" in out, out + err
    lines = err.strip().splitlines()
    assert lines[-4] == "bokehray: 3 inputs failed:", err
    assert any("pipe.png: expected a regular file, got a named pipe (FIFO)" in x for x in lines), err
    assert any("gone.png: a dangling symbolic link (to " in x for x in lines), err
    assert any("loop.png: a loop of symbolic links" in x for x in lines), err
    pairs = {p.image.name: p for p in find_pairs(str(photos / "*.png"), str(maps))}  # a glob lists them too
    assert pairs["pipe.png"].map is None and "FIFO" in pairs["pipe.png"].problem
    assert pairs["gone.png"].map is None and pairs["loop.png"].map is None


def test_resume_skips_complete_outputs_and_refuses_other_settings(shoot, capsys):
    args = ["render", shoot / "photos", "--disparity", shoot / "maps", "-o", shoot / "out", "--blur", 6,
            "--focus", 0.5, "--workers", 1]
    assert run(capsys, *args)[0] == 0
    (shoot / "out" / "p1.png").unlink()  # as if the batch had been interrupted
    mtime = (shoot / "out" / "p0.png").stat().st_mtime_ns
    code, out, _ = run(capsys, *args)
    assert code == 0 and "1 rendered, 2 skipped (complete)" in out
    assert (shoot / "out" / "p0.png").stat().st_mtime_ns == mtime
    code, _, err = run(capsys, *args[:6], "--blur", 7, "--focus", 0.5)
    assert code == 2 and "made with other settings" in err and "--overwrite" in err
    code, out, _ = run(capsys, *args[:6], "--blur", 7, "--focus", 0.5, "--overwrite", "--workers", 1)
    assert code == 0 and "3 rendered" in out
    assert json.loads((shoot / "out" / "bokehray-batch.json").read_text())["outputs"] == 3
    br.write_image(shoot / "foreign" / "p0.png", _photo(0)[0])  # a file no batch wrote
    code, _, err = run(capsys, *args[:4], "-o", shoot / "foreign", "--blur", 6, "--focus", 0.5)
    assert code == 2 and "was not written by a bokehray batch" in err
    assert br.read_image(shoot / "foreign" / "p0.png").shape == (H, W, 3)


def test_focal_sweep_writes_a_stack_and_an_animated_gif(shoot, capsys):
    from PIL import Image

    img, d = shoot / "photos" / "p0.png", shoot / "maps" / "p0.png"
    code, out, err = run(capsys, "render", img, "--disparity", d, "-o", shoot / "sweep", "--blur", 8,
                         "--focus", "0.1:0.9:5", "--workers", 1)
    assert code == 0, err
    values = [0.1, 0.3, 0.5, 0.7, 0.9]
    frames = [shoot / "sweep" / f"p0_focus_{v:.3f}.png" for v in values]
    assert all(f.exists() for f in frames) and "1 sweep previews" in out
    for v, f in zip(values[::2], frames[::2]):  # each frame is the single render at that focus
        run(capsys, "render", img, "--disparity", d, "-o", shoot / "one.png", "--blur", 8, "--focus", v, "--quiet")
        assert f.read_bytes() == (shoot / "one.png").read_bytes()
    stack = [br.read_image(f) for f in frames]
    assert all(np.abs(a - b).max() > 0.01 for a, b in itertools.pairwise(stack))  # the focus moves
    gif = Image.open(shoot / "sweep" / "p0_focus_sweep.gif")
    assert gif.n_frames == 5 and gif.size == (W, H) and gif.info["loop"] == 0
    gif.seek(2)
    shown = np.asarray(gif.convert("RGB"), np.float64) / 255.0
    assert np.abs(shown - linear_to_srgb(np.clip(stack[2], 0, 1))).mean() < 0.03  # palette error only
    code, out, _ = run(capsys, "render", shoot / "photos", "--disparity", shoot / "maps", "-o", shoot / "kstack",
                       "--blur", "2,4", "--focus", 0.5, "--workers", 1)
    assert code == 0 and "6 rendered" in out and (shoot / "kstack" / "p2_blur_4.png").exists()
    assert len(list((shoot / "kstack").glob("*_blur_sweep.gif"))) == 3


def test_close_sweep_values_get_a_frame_each(shoot, capsys):
    """Issue: %.3f made --focus 0.1,0.1004 one file, reported as 2 rendered, and a 1-frame GIF."""
    from PIL import Image

    img, d = shoot / "photos" / "p0.png", shoot / "maps" / "p0.png"
    code, out, err = run(capsys, "render", img, "--disparity", d, "-o", shoot / "sweep", "--blur", 8,
                         "--focus", "0.1,0.1004", "--workers", 1)
    assert code == 0, err
    assert _files(shoot / "sweep") == ["bokehray-batch.json", "p0_focus_0.1000.png", "p0_focus_0.1004.png",
                                       "p0_focus_sweep.gif"]
    assert "2 rendered" in out and Image.open(shoot / "sweep" / "p0_focus_sweep.gif").n_frames == 2
    code, out, err = run(capsys, "render", img, "--disparity", d, "-o", shoot / "sweep", "--blur", 8,
                         "--focus", "0.1,0.1004", "--workers", 1)
    assert code == 0 and "0 rendered, 2 skipped" in out  # resume sees both frames


@pytest.mark.parametrize(("name", "text", "shown"), [
    ("focus", "0.1:0.9:1000", None),  # inside MAX_SWEEP: 801 names for 1000 frames with %.3f
    ("blur", "24,24.0000001", ["24", "24.0000001"]),  # %g: both "24"
    ("blur", "2.5,4", ["2.5", "4"]),
    ("focus", "0.1:0.9:5", ["0.100", "0.300", "0.500", "0.700", "0.900"]),  # the usual names stay
    ("blur", "2,4,16", ["2", "4", "16"]),
])
def test_every_sweep_value_names_its_own_frame(name, text, shown):
    values = parse_sweep(text)
    labels = frame_labels(name, values)
    assert len(set(labels)) == len(values) == len(labels)
    assert len({len(t) for t in labels}) == 1 or name == "blur"  # a focal stack's names sort in focus order
    assert all(abs(float(t) - v) <= 0.5 * 10.0 ** -6 * max(1.0, v) for t, v in zip(labels, values))
    if shown is not None:
        assert labels == shown


@given(st.lists(st.floats(0, 1), min_size=2, max_size=30, unique=True))
def test_frame_labels_are_distinct_or_refused(values):
    try:
        labels = frame_labels("focus", values)
    except InputError as e:
        assert "too close to tell apart" in str(e)
        return
    assert len(set(labels)) == len(values)


@pytest.mark.parametrize("args, message", [
    (["--blur", 4, "--focus", "0:2:3"], "--focus: expected every value of the sweep in [0, 1]"),
    (["--blur=-1,4", "--focus", 0.5], "--blur: expected every value of the sweep as K in [0, 100000], got -1"),
    (["--blur", "2,4", "--focus", "0.1,0.2"], "sweep one of --focus or --blur, not both"),
    (["--blur", 4, "--focus", "0.1,0.1"], "--focus: the values repeat"),
    (["--blur", 4, "--focus", "0.1:0.5:1"], "a range needs 2..1000 values"),
    (["--blur", 4, "--focus", "a,b"], "expected a number, a list A,B,C or a range"),
    # round four: empty items were dropped (a one-frame "sweep" with a GIF for 0.5,), values were rounded
    (["--blur", 4, "--focus", "0,,1"], "a list A,B,C has an empty value in '0,,1'"),
    (["--blur", 4, "--focus", "0,1,"], "a list A,B,C has an empty value in '0,1,'"),
    (["--blur", 4, "--focus", "0.5,"], "a list A,B,C has an empty value in '0.5,'"),
    (["--blur", 4, "--focus", "0:inf:3"], "a range needs finite ends, got '0:inf:3'"),
    (["--blur", 4, "--focus", "0,1.0000001"], "got 1.0000001 (value 2 of 2)"),
    (["--blur", 4, "--focus", "0.3,0.30000000001,0.3"], "the values repeat (0.3, 0.30000000001, 0.3)"),
    (["--blur", 4, "--focus", "0.1,0.5", "--stats"], "--stats: single-file renders only"),
    (["--blur", 4, "--focus", "0.1,0.5", "--executor", "local", "--scheduler", "tcp://127.0.0.1:1"],
     "--scheduler needs --executor dask"),
])
def test_bad_sweep_arguments(shoot, capsys, args, message):
    code, _, err = run(capsys, "render", shoot / "photos" / "p0.png", "--disparity", shoot / "maps" / "p0.png",
                       "-o", shoot / "sweep", *args)
    assert code == 2 and message in err and err.count("\n") == 1
    assert not (shoot / "sweep").exists() or not any((shoot / "sweep").glob("*.png"))


@pytest.mark.parametrize("inputs, args, message", [
    ("sweep", ["--blur", "2,4", "--jpeg-quality", 0], "--jpeg-quality: expected 1..100, got 0"),
    ("sweep", ["--focus", "0.2,0.4", "--focus-at", "3,3"], "--focus and --focus-at contradict each other"),
    ("sweep", ["--blur", "2,4", "--focal-length", 50, "--f-number", 2], "a physical lens"),
    ("folder", ["--blur", 4, "--focus", 0.5, "--focus-at", "3,3"], "--focus and --focus-at contradict each other"),
    ("folder", ["--amount", 200], "--amount: expected a number in [0, 100], got 200"),
])
def test_contradicting_flags_are_refused_once_before_the_batch_starts(shoot, capsys, inputs, args, message):
    """They were checked inside every render: the folder and its state file made, then the same line once per
    photo or frame in the failure summary."""
    photo, maps = ((shoot / "photos" / "p0.png", shoot / "maps" / "p0.png") if inputs == "sweep"
                   else (shoot / "photos", shoot / "maps"))
    code, _, err = run(capsys, "render", photo, "--disparity", maps, "-o", shoot / "out", "--workers", 1, *args)
    assert code == 2 and err.startswith(f"bokehray: error: {message}") and err.count("\n") == 1, err
    assert not (shoot / "out").exists()


def test_a_file_name_as_batch_output_is_refused(shoot, capsys):
    code, _, err = run(capsys, "render", shoot / "photos", "--disparity", shoot / "maps", "-o", shoot / "x.png",
                       "--blur", 4, "--focus", 0.5)
    assert code == 2 and "many outputs go into a folder" in err and not (shoot / "x.png").exists()


@given(st.floats(-2, 2), st.floats(-2, 2), st.integers(2, 40))
def test_a_range_has_its_count_and_ends(start, stop, count):
    v = parse_sweep(f"{start!r}:{stop!r}:{count}")
    assert len(v) == count and v[0] == start and v[-1] == pytest.approx(stop, abs=1e-12)
    steps = np.diff(v)
    assert np.all(steps >= -1e-12) or np.all(steps <= 1e-12)  # monotonic


def test_sweep_lists_and_single_values():
    assert parse_sweep("0.5") == 0.5
    assert parse_sweep("0.2,0.4") == (0.2, 0.4)
    with pytest.raises(argparse.ArgumentTypeError, match="empty value"):  # decided: no item is dropped silently
        parse_sweep("0.2,0.4,")
    with pytest.raises(argparse.ArgumentTypeError):
        parse_sweep("1:2")


def test_batch_and_synth_are_byte_identical_on_local_pool_and_dask(shoot, capsys):
    pytest.importorskip("distributed")
    outs = {}
    for ex in ("local", "dask"):
        code, _out, err = run(capsys, "render", shoot / "photos", "--disparity", shoot / "maps", "-o",
                             shoot / f"r_{ex}", "--blur", 6, "--focus", "0.2,0.8", "--executor", ex, "--workers", 2)
        assert code == 0, err
        code, _, err = run(capsys, "synth", "-n", 2, "-o", shoot / f"s_{ex}", "--size", 40, "--blur-levels", 5,
                           "--max-spp", 4, "--executor", ex, "--workers", 2, "--quiet", "--seed", 5)
        assert code == 0, err
        outs[ex] = {p.relative_to(shoot / f"r_{ex}").as_posix(): p.read_bytes()
                    for p in (shoot / f"r_{ex}").rglob("*") if p.is_file()}
        outs[ex].update({p.relative_to(shoot / f"s_{ex}").as_posix(): p.read_bytes()
                         for p in (shoot / f"s_{ex}").rglob("*") if p.is_file()})
    assert len(outs["local"]) == 1 + 6 + 3 + 2 * 9  # state, 6 frames, 3 GIFs, 2 scenes of 9 files
    assert outs["local"].keys() == outs["dask"].keys()
    assert [k for k in outs["local"] if outs["local"][k] != outs["dask"][k]] == []


@given(st.sets(st.from_regex(r"[A-Za-z0-9][A-Za-z0-9_-]{0,8}", fullmatch=True), min_size=1, max_size=6),
       st.sampled_from(["", "_disp", "-d"]), st.booleans())
def test_every_photo_pairs_with_its_own_map(stems, suffix, same_folder):
    import tempfile
    from pathlib import Path

    stems = {s for s in stems if not (suffix and s.endswith(suffix))}  # a photo named like a map is a map
    same_folder = same_folder and bool(suffix)  # without a suffix the maps must live apart (tested above)
    with tempfile.TemporaryDirectory() as tmp:
        photos = Path(tmp) / "photos"
        maps = photos if same_folder else Path(tmp) / "maps"
        photos.mkdir()
        maps.mkdir(exist_ok=True)
        for s in stems:
            (photos / f"{s}.jpg").write_bytes(b"")
            (maps / f"{s}{suffix}.png").write_bytes(b"")
        pairs = find_pairs(str(photos), str(maps), suffix=suffix)
        assert sorted(p.image.stem for p in pairs) == sorted(stems)
        assert all(p.map is not None and p.map.name == f"{p.image.stem}{suffix}.png" for p in pairs)


class _StopsInFlight:
    """An executor whose first task ends, then the signal comes while two more are in flight; they finish (write
    their output) while it closes, as a local pool's workers do."""

    workers = 3

    def __init__(self, signal_exc):
        self.signal_exc, self.tasks, self.fn = signal_exc, [], None

    def describe(self):
        return "stand-in"

    def map(self, fn, tasks):
        from bokehray.executor import Outcome

        self.fn, self.tasks = fn, tasks
        yield Outcome(0, fn(tasks[0]))
        raise self.signal_exc

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        for t in self.tasks[1:3]:
            self.fn(t)


@pytest.mark.parametrize(("exc", "code", "words"), [
    ("Terminated", 143, "terminated (SIGTERM)"), ("KeyboardInterrupt", 130, "interrupted")])
def test_a_signal_stops_the_batch_with_its_code_and_counts_the_outputs_on_disk(shoot, capsys, monkeypatch, exc,
                                                                               code, words):
    """Issue: SIGTERM exited 130 "interrupted" (not 143), and the count missed the renders that were in flight."""
    import bokehray.errors
    import bokehray.executor

    signal_exc = getattr(bokehray.errors, exc, None) or KeyboardInterrupt
    monkeypatch.setattr(bokehray.executor, "make_executor", lambda *a, **k: _StopsInFlight(signal_exc()))
    got, _, err = run(capsys, "render", shoot / "photos" / "p0.png", "--disparity", shoot / "maps" / "p0.png",
                      "-o", shoot / "s", "--blur", 6, "--focus", "0.2,0.4,0.6,0.8", "--quiet")
    assert got == code
    assert err.strip() == (f"bokehray: {words} after 3 of 4 renders; they are complete in {shoot / 's'}, run the "
                           "same command again to render the rest")
    assert len(list((shoot / "s").glob("p0_focus_*.png"))) == 3
    monkeypatch.undo()
    got, out, err = run(capsys, "render", shoot / "photos" / "p0.png", "--disparity", shoot / "maps" / "p0.png",
                        "-o", shoot / "s", "--blur", 6, "--focus", "0.2,0.4,0.6,0.8", "--workers", 1)
    assert got == 0 and "1 rendered, 3 skipped" in out, err
