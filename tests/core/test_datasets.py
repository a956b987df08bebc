"""Tests for bokehray.data.datasets: BLB write/read round trip, atomic writes, EBB pairing, error paths."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from bokehray.data import datasets as ds
from bokehray.data.datasets import BLBDataset, EBBDataset, Sample, write_blb_scene
from bokehray.errors import InputError, OutputError
from bokehray.output.write import write_disparity, write_image

H, W = 16, 20
KS = [4.0, 12.5]
DFS = [0.25, 0.8]


def _scene(seed: int = 0, *, nk: int = 2, nf: int = 2):
    rng = np.random.default_rng(seed)
    image = rng.uniform(0.0, 3.0, (H, W, 3)).astype(np.float32)  # HDR: values above 1 survive EXR
    disparity = rng.uniform(0.0, 1.0, (H, W)).astype(np.float32)
    disparity[0, :3] = [0.0, 1.0, 0.5]  # the ends of the range: d = 0 is written as depth 1e9
    renders = [
        {"k_index": k, "f_index": f, "image": rng.uniform(0.0, 2.0, (H, W, 3)).astype(np.float32)}
        for k in range(nk)
        for f in range(nf)
    ]
    info = {"blur_parameters": KS[:nk], "focus_disparities": DFS[:nf], "seed": seed, "aperture": {"blades": 6}}
    return image, disparity, renders, info


def _listing(parent: Path) -> list[str]:
    return sorted(p.name for p in parent.iterdir())


def test_round_trip(tmp_path):
    image, disparity, renders, info = _scene()
    folder = write_blb_scene(tmp_path / "scene_0000", image, disparity, renders, info)
    assert folder == tmp_path / "scene_0000"
    assert _listing(tmp_path) == ["scene_0000"]  # no temporary folder left behind
    files = set(_listing(folder))
    assert {"image.exr", "depth.exr", "info.json", "image.png", "disparity.png", "bokeh_1_0.png"} <= files
    written = json.loads((folder / "info.json").read_text())
    assert written["seed"] == 0 and written["focus_distances"] == pytest.approx([4.0, 1.25])

    data = BLBDataset(tmp_path)
    assert len(data) == 4
    assert [s.name for s in data] == [f"scene_0000/bokeh_{k}_{f}" for k in range(2) for f in range(2)]
    for s, r in zip(data, renders):
        assert isinstance(s, Sample)
        assert s.image.dtype == np.float32 and s.image.shape == (H, W, 3)
        np.testing.assert_array_equal(s.image, image)
        np.testing.assert_array_equal(s.target, r["image"])
        assert s.disparity.dtype == np.float32 and s.disparity.shape == (H, W)
        np.testing.assert_allclose(s.disparity, disparity, rtol=1e-6, atol=1e-8)
        assert s.disparity[0, 0] == pytest.approx(0.0, abs=1e-8) and s.disparity[0, 1] == 1.0
        assert s.k_px == KS[r["k_index"]]
        assert s.focus_disparity == pytest.approx(DFS[r["f_index"]], rel=1e-12)
        assert s.meta["aperture"] == {"blades": 6}
        assert s.meta["paths"]["target"].endswith(f"bokeh_{r['k_index']}_{r['f_index']}.exr")


def test_focus_at_infinity_and_no_previews(tmp_path):
    image, disparity, renders, info = _scene(nk=1, nf=1)
    info["focus_disparities"] = [0.0]
    write_blb_scene(tmp_path / "s", image, disparity, renders, info, previews=False)
    assert not any(p.suffix == ".png" for p in (tmp_path / "s").iterdir())
    assert json.loads((tmp_path / "s" / "info.json").read_text())["focus_distances"] == [ds.FAR_DEPTH]
    assert BLBDataset(tmp_path)[0].focus_disparity == pytest.approx(0.0, abs=1e-8)


def test_level_focus_filter_and_order(tmp_path):
    for i in (10, 2, 0):  # written out of order; read in natural order
        write_blb_scene(tmp_path / f"scene_{i}", *_scene(i))
    (tmp_path / "notes").mkdir()  # a folder without info.json is not a scene
    (tmp_path / "README.txt").write_text("hello")
    all_names = [s.name for s in BLBDataset(tmp_path)]
    assert all_names[:4] == [f"scene_0/bokeh_{k}_{f}" for k in range(2) for f in range(2)]
    assert [n.split("/")[0] for n in all_names[::4]] == ["scene_0", "scene_2", "scene_10"]
    assert all_names == [s.name for s in BLBDataset(tmp_path)]  # deterministic

    lvl = BLBDataset(tmp_path, level=1)
    assert [s.name for s in lvl] == [f"scene_{i}/bokeh_1_{f}" for i in (0, 2, 10) for f in range(2)]
    assert {s.k_px for s in lvl} == {KS[1]}
    both = BLBDataset(tmp_path, level=0, focus=1)
    assert len(both) == 3 and both[-1].name == "scene_10/bokeh_0_1"
    assert both[1].focus_disparity == pytest.approx(DFS[1])
    with pytest.raises(IndexError):
        both[3]
    with pytest.raises(InputError, match="no bokeh_<k>_<f>.exr files"):
        BLBDataset(tmp_path, level=5)


def test_lazy_and_ignores_unknown_fields_and_files(tmp_path, monkeypatch):
    folder = write_blb_scene(tmp_path / "a", *_scene())
    info = json.loads((folder / "info.json").read_text())
    info["lens"] = {"name": "unknown", "extra": [1, 2]}
    del info["focus_disparities"]  # BokehMe's own files do not have it
    (folder / "info.json").write_text(json.dumps(info))
    (folder / "bokeh_0_0.jpg").write_bytes(b"junk")
    (folder / "bokeh_x_1.exr").write_bytes(b"junk")
    (folder / "depth_preview.png").write_bytes(b"junk")
    calls = []
    monkeypatch.setattr(ds, "read_image", lambda p: calls.append(p) or np.zeros((H, W, 3), np.float32))
    data = BLBDataset(tmp_path)
    assert len(data) == 4 and calls == []  # __init__ reads no pixels
    data[2]
    assert len(calls) == 2


def test_atomic_write_failure_leaves_nothing(tmp_path, monkeypatch):
    real = ds.write_image
    count = {"n": 0}

    def flaky(path, img, **kw):
        if Path(path).name.startswith("bokeh_") and Path(path).suffix == ".exr":
            count["n"] += 1
            if count["n"] == 2:
                raise OSError("disk full")
        return real(path, img, **kw)

    monkeypatch.setattr(ds, "write_image", flaky)
    with pytest.raises(OSError, match="disk full"):
        write_blb_scene(tmp_path / "scene", *_scene())
    assert _listing(tmp_path) == []  # neither the scene nor a temporary folder

    monkeypatch.setattr(ds, "write_image", real)
    good = _scene(1)
    write_blb_scene(tmp_path / "scene", *good)
    before = {p.name: p.read_bytes() for p in (tmp_path / "scene").iterdir()}
    count["n"] = 0
    monkeypatch.setattr(ds, "write_image", flaky)
    with pytest.raises(OSError, match="disk full"):
        write_blb_scene(tmp_path / "scene", *_scene(2), overwrite=True)
    assert _listing(tmp_path) == ["scene"]
    assert {p.name: p.read_bytes() for p in (tmp_path / "scene").iterdir()} == before

    monkeypatch.setattr(ds, "write_image", real)
    write_blb_scene(tmp_path / "scene", *_scene(3, nk=1, nf=1), overwrite=True)  # replaces, no leftovers
    assert _listing(tmp_path) == ["scene"]
    assert [s.name for s in BLBDataset(tmp_path)] == ["scene/bokeh_0_0"]


def test_write_into_existing_empty_folder(tmp_path):
    (tmp_path / "s").mkdir()
    write_blb_scene(tmp_path / "s", *_scene(), previews=False)
    assert len(BLBDataset(tmp_path)) == 4


@pytest.mark.parametrize(
    ("edit", "fragment"),
    [
        (lambda a: a[0].__setitem__((1, 2, 0), np.nan), "image: expected finite"),
        (lambda a: a[1].__setitem__((3, 4), 1.5), r"disparity: expected finite values in \[0, 1\]"),
        (lambda a: a[1].__setitem__((3, 4), -0.1), r"disparity: expected finite values in \[0, 1\]"),
        (lambda a: a[2][1].__setitem__("k_index", 2), r"renders\[1\]: k_index 2 / f_index 1 out of range"),
        (lambda a: a[2][0].__setitem__("f_index", -1), "out of range"),
        (lambda a: a[2][3].__setitem__("f_index", 0), "duplicate render"),
        (lambda a: a[2][0].__setitem__("image", np.zeros((H, W + 1, 3), np.float32)), r"renders\[0\] image"),
        (lambda a: a[2][0]["image"].__setitem__((0, 0, 0), np.inf), r"renders\[0\] image: expected finite"),
        (lambda a: a.__setitem__(1, np.zeros((H + 1, W), np.float32)), "disparity: expected a real"),
        (lambda a: a[3].pop("blur_parameters"), "blur_parameters"),
        (lambda a: a[3].__setitem__("focus_disparities", [0.5, 1.2]), r"focus_disparities in \[0, 1\]"),
        (lambda a: a[3].__setitem__("blur_parameters", [1.0, -2.0]), "K >= 0"),
        (lambda a: a[3].__setitem__("when", object()), "JSON-serialisable"),
        (lambda a: a[2].__setitem__(0, (0, 0, None)), r"renders\[0\]: expected a dict"),
        (lambda a: a[2][0].__setitem__("k_index", 0.0), "expected integer k_index"),
    ],
)
def test_writer_rejects_bad_inputs(tmp_path, edit, fragment):
    args = list(_scene())
    edit(args)
    with pytest.raises(InputError, match=fragment):
        write_blb_scene(tmp_path / "scene", *args)
    assert _listing(tmp_path) == []


def test_writer_refuses_non_empty_folder(tmp_path):
    (tmp_path / "scene").mkdir()
    (tmp_path / "scene" / "keep.txt").write_text("mine")
    with pytest.raises(InputError, match="already exists and is not empty; pass overwrite=True"):
        write_blb_scene(tmp_path / "scene", *_scene())
    assert _listing(tmp_path / "scene") == ["keep.txt"]
    (tmp_path / "file").write_text("x")
    with pytest.raises(InputError, match="got an existing file"):
        write_blb_scene(tmp_path / "file", *_scene())


def test_blb_reader_errors(tmp_path):
    with pytest.raises(InputError, match="BLB root does not exist"):
        BLBDataset(tmp_path / "nope")
    (tmp_path / "f.txt").write_text("x")
    with pytest.raises(InputError, match="to be a directory"):
        BLBDataset(tmp_path / "f.txt")
    (tmp_path / "empty_scene").mkdir()
    with pytest.raises(InputError, match="no BLB scenes under"):
        BLBDataset(tmp_path)

    folder = write_blb_scene(tmp_path / "s", *_scene())
    info_path = folder / "info.json"
    good = info_path.read_text()
    info_path.write_text("{not json")
    with pytest.raises(InputError, match="cannot read info.json"):
        BLBDataset(tmp_path)
    info = json.loads(good)
    info.pop("focus_distances")
    info_path.write_text(json.dumps(info))
    with pytest.raises(InputError, match="focus_distances"):
        BLBDataset(tmp_path)
    info_path.write_text(json.dumps({**json.loads(good), "blur_parameters": [4.0]}))
    with pytest.raises(InputError, match=r"bokeh_1_0.exr: index out of range for 1 blur_parameters"):
        BLBDataset(tmp_path)
    info_path.write_text(json.dumps({**json.loads(good), "blur_parameters": [4.0, float("nan")]}))
    with pytest.raises(InputError, match="expected finite blur_parameters"):
        BLBDataset(tmp_path)
    info_path.write_text(json.dumps({**json.loads(good), "focus_distances": [0.5, 2.0]}))
    with pytest.raises(InputError, match="expected focus_distances >= 1"):
        BLBDataset(tmp_path)
    info_path.write_text(good)
    hidden = tmp_path / ".s.tmp-123-abc"  # an unfinished write is not a scene
    hidden.mkdir()
    (hidden / "info.json").write_text("{broken")
    assert len(BLBDataset(tmp_path)) == 4
    (folder / "image.exr").unlink()
    data = BLBDataset(tmp_path)  # lazy: the missing file shows only when read
    with pytest.raises(InputError, match="image.exr: file does not exist"):
        data[0]


# --------------------------------------------------------------------------- EBB


def _ebb(root: Path, stems=("1", "2", "10"), *, h: int = 12, w: int = 10) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(5)
    disps = {}
    for s in stems:
        write_image(root / "input" / f"{s}.png", rng.uniform(0, 1, (h, w, 3)).astype(np.float32))
        write_image(root / "target" / f"{s}.jpg", rng.uniform(0, 1, (h, w, 3)).astype(np.float32))
        disps[s] = rng.uniform(0, 1, (h, w)).astype(np.float32)
        write_disparity(root / "disparity" / f"{s}.npy", disps[s])
    return disps


def test_ebb_reads_pairs(tmp_path):
    disps = _ebb(tmp_path)
    (tmp_path / "target" / "99.png").write_bytes(b"a target without input is ignored")
    (tmp_path / "input" / "notes.txt").write_text("ignored")
    data = EBBDataset(tmp_path)
    assert [s.name for s in data] == ["1", "2", "10"]
    s = data[2]
    assert s.image.shape == (12, 10, 3) and s.image.dtype == np.float32
    assert s.target.shape == (12, 10, 3)
    np.testing.assert_array_equal(s.disparity, disps["10"])
    assert s.k_px is None and s.focus_disparity is None
    assert s.meta["paths"]["disparity"].endswith("10.npy")


def test_ebb_errors(tmp_path):
    with pytest.raises(InputError, match="EBB root does not exist"):
        EBBDataset(tmp_path / "missing")
    with pytest.raises(InputError, match="EBB input folder does not exist"):
        EBBDataset(tmp_path)

    _ebb(tmp_path, stems=[str(i) for i in range(8)])
    for i in range(7):
        (tmp_path / "disparity" / f"{i}.npy").unlink()
    with pytest.raises(InputError, match=r"missing stems 0, 1, 2, 3, 4 and 2 more"):
        EBBDataset(tmp_path)
    (tmp_path / "target" / "7.jpg").unlink()
    with pytest.raises(InputError, match=r"target for every input, missing stems .*7"):
        EBBDataset(tmp_path, disparity_dir="input")

    other = tmp_path / "other"
    _ebb(other, stems=["a", "b"])
    write_disparity(other / "disparity" / "b.npy", np.zeros((6, 5), np.float32))
    data = EBBDataset(other)
    assert data[0].name == "a"
    with pytest.raises(InputError, match="expected 10 x 12 pixels like b.png, got 5 x 6"):
        data[1]
    write_disparity(other / "disparity" / "b.npy", np.full((12, 10), 2.0, np.float32))
    with pytest.raises(InputError, match=r"expected disparity in \[0, 1\]"):
        data[1]
    write_disparity(other / "disparity" / "b.tif", np.zeros((12, 10), np.float32))
    with pytest.raises(InputError, match="two files for stem 'b'"):
        EBBDataset(other)
    empty = tmp_path / "empty"
    for sub in ("input", "target", "disparity"):
        (empty / sub).mkdir(parents=True)
    with pytest.raises(InputError, match="expected input images"):
        EBBDataset(empty)


def test_a_write_failure_names_the_scene_folder_not_its_hidden_temporary(tmp_path, monkeypatch):
    """A full disk during a scene's write named ``.scene_0000.tmp-<pid>-<random>/bokeh_0_1.exr``, a folder the user
    never sees (it is removed); the message names the scene's folder, and nothing is left."""
    import errno
    import os

    real = ds.write_image

    def full_at_the_third(path, *a, **k):
        if Path(path).name == "bokeh_0_1.exr":
            from bokehray.output.atomic import atomic_write

            def enospc(tmp):
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

            return atomic_write(Path(path), enospc)
        return real(path, *a, **k)

    monkeypatch.setattr(ds, "write_image", full_at_the_third)
    folder = tmp_path / "scene_0000"
    with pytest.raises(OutputError) as e:
        write_blb_scene(folder, *_scene(), previews=False)
    assert str(e.value) == f"cannot write {folder / 'bokeh_0_1.exr'}: No space left on device"
    assert _listing(tmp_path) == []
