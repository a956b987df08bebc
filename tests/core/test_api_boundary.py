"""Reliability: the public API answers wrong types and huge shapes with the project's
errors, from the arguments alone, before any allocation; each case failed before its fix (a TypeError,
OverflowError or NumPy's raw MemoryError)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import bokehray as br
from bokehray.errors import InputError

_IMG = np.full((4, 4, 3), 0.5, np.float32)


class _BytesPath:
    def __fspath__(self):
        return b"x.png"


_WRONG_TYPES = {
    "read_image(None)": (lambda t: br.read_image(None), "path: expected a file path (str or os.PathLike), got NoneType"),
    "read_image(3)": (lambda t: br.read_image(3), "got int"),
    "read_image(b'...')": (lambda t: br.read_image(os.fsencode(t / "x.png")), "got bytes"),
    "read_disparity(b'...')": (lambda t: br.read_disparity(b"x.png"), "got bytes"),
    "read_depth(None)": (lambda t: br.read_depth(None), "got NoneType"),
    "read_size(1.5)": (lambda t: __import__("bokehray.photo.read").photo.read.read_size(1.5), "got float"),
    "write_image(None, img)": (lambda t: br.write_image(None, _IMG), "got NoneType"),
    "write_image(b'x.png', img)": (lambda t: br.write_image(b"x.png", _IMG), "got bytes"),
    "write_image(PathLike giving bytes)": (lambda t: br.write_image(_BytesPath(), _IMG), "_BytesPath giving bytes"),
    "write_disparity(None, d)": (lambda t: br.write_disparity(None, _IMG[..., 0]), "got NoneType"),
    "BlurParams(10**400, .5)": (lambda t: br.BlurParams(10**400, 0.5), "K (blur): expected a finite number, got an "
                                "integer of 401 digits"),
    "BlurParams(4, 10**400)": (lambda t: br.BlurParams(4, 10**400), "focus disparity: expected a finite number"),
    "Aperture(rotation_deg=10**400)": (lambda t: br.Aperture(rotation_deg=10**400), "aperture rotation: expected a "
                                       "finite number"),
    "Aperture(curvature=-10**400)": (lambda t: br.Aperture(curvature=-10**400), "aperture curvature"),
    "DepthNormalization(1, 10**400)": (lambda t: br.DepthNormalization(1, 10**400), "z_far: expected a number (inf "
                                       "allowed)"),
    "ThinLens(10**400, ...)": (lambda t: br.ThinLens(10**400, 2, 3), "focal_length_mm: expected a finite number"),
    "LayerOptions(max_layer_px=10**400)": (lambda t: br.LayerOptions(max_layer_px=10**400), "max_layer_px"),
    "MemoryOptions(memory_limit_mb=10**400)": (lambda t: br.MemoryOptions(memory_limit_mb=10**400),
                                               "memory_limit_mb"),
    "Aperture(blades=10**400)": (lambda t: br.Aperture(blades=10**400), "got an integer of 401 digits"),
    "RaytraceOptions(max_spp=10**400)": (lambda t: br.RaytraceOptions(max_spp=10**400), "max_spp"),
    # round four (item 12 and the questionable half="yes"): each was a wrong message, a raw NumPy/Python error or a
    # silent reading
    "render(None, d)": (lambda t: br.render(None, _IMG[..., 0], br.BlurParams(4, 0.5)),
                        "image: expected a NumPy array, got NoneType"),
    "render(ragged, d)": (lambda t: br.render([[0.5, 0.5], [0.5]], _IMG[..., 0], br.BlurParams(4, 0.5)),
                          "image: expected an array, got a ragged list"),
    "write_image(ragged)": (lambda t: br.write_image("x.png", [[0.5, 0.5], [0.5]]), "image: expected an array, got a "
                            "ragged list"),
    "write_image(quality='95')": (lambda t: br.write_image("x.jpg", _IMG, quality="95"),
                                  "expected JPEG quality in [1, 100] (an integer), got '95'"),
    "write_image(quality=95.0)": (lambda t: br.write_image("x.jpg", _IMG, quality=95.0), "got 95.0"),
    "write_image(half='yes')": (lambda t: br.write_image("x.exr", _IMG, half="yes"),
                                "half: expected True or False, got 'yes'"),
    "write_image(exclusive='no')": (lambda t: br.write_image("x.png", _IMG, exclusive="no"),
                                    "exclusive: expected True or False, got 'no'"),
    "write_image(bit_depth=16.0)": (lambda t: br.write_image("x.png", _IMG, bit_depth=16.0),
                                    "bit_depth expects None or an integer, got 16.0"),
    "BlurParams(4, 1.0000001)": (lambda t: br.BlurParams(4, 1.0000001), "expected a value in [0, 1] (1 = nearest), "
                                 "got 1.0000001"),
    "BlurParams(-1e-9, 0.5)": (lambda t: br.BlurParams(-1e-9, 0.5), "expected a value >= 0, got -1e-09"),
    "LayerOptions(tile_px=10**9)": (lambda t: br.LayerOptions(tile_px=10**9),
                                    "tile_px: expected an integer in [1, 1024], got 1000000000"),
}


@pytest.mark.parametrize("case", sorted(_WRONG_TYPES))
def test_wrong_types_and_huge_numbers_are_input_errors(case, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    call, message = _WRONG_TYPES[case]
    with pytest.raises(InputError) as e:
        call(tmp_path)
    assert message in str(e.value) and len(str(e.value)) < 300
    assert not list(tmp_path.iterdir())  # nothing written


def test_the_right_types_still_work(tmp_path):
    p = br.write_image(Path(tmp_path / "a.png"), _IMG)
    assert br.read_image(str(p)).shape == (4, 4, 3)
    assert br.BlurParams(4, 1).k_px == 4.0 and br.DepthNormalization(1, float("inf")).z_far_m == float("inf")
    assert br.Aperture(blades=5, rotation_deg=10**300).blades == 5  # a large but finite angle is a number
    assert br.write_image(tmp_path / "b.exr", _IMG, half=np.True_, exclusive=False).exists()
    assert br.write_image(tmp_path / "c.jpg", _IMG, quality=np.int64(90)).exists()
    inputs = br.pipeline.Handover(_IMG, _IMG[..., 0])
    br.pipeline.render_handed_over(inputs, br.BlurParams(2, 0.5))
    with pytest.raises(InputError, match="this Handover was already rendered"):
        br.pipeline.render_handed_over(inputs, br.BlurParams(2, 0.5))


def test_huge_broadcast_views_are_refused_from_their_shape():
    """Item 13: disparity_from_depth, write_image and write_disparity touched a 1e10-pixel broadcast view (NumPy's
    raw MemoryError, or the machine's swap); only render refused from the shape."""
    code = """
import resource
resource.setrlimit(resource.RLIMIT_AS, (8 << 30, 8 << 30))  # whatever happens, this process cannot take the machine
import numpy as np, bokehray as br
big = (100_000, 100_000)
calls = {
    "disparity_from_depth": lambda: br.disparity_from_depth(np.broadcast_to(np.float64(2.0), big)),
    "write_image": lambda: br.write_image("o.png", np.broadcast_to(np.float32(0.5), big + (3,))),
    "write_image exr": lambda: br.write_image("o.exr", np.broadcast_to(np.float32(0.5), big)),
    "write_disparity": lambda: br.write_disparity("o.png", np.broadcast_to(np.float32(0.5), big)),
}
for name, call in calls.items():
    try:
        call()
        print(name, "rendered")
    except br.ResourceError as e:
        print(name, "ResourceError", e)
    except BaseException as e:
        print(name, type(e).__name__, e)
"""
    paths = os.pathsep.join(dict.fromkeys(str(Path(m.__file__).resolve().parents[1])
                                          for m in (br, __import__("bokehray_kernels"))))
    env = {**os.environ, "PYTHONPATH": paths + os.pathsep + os.environ.get("PYTHONPATH", "")}
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=False,
                          timeout=300, cwd=Path(__file__).parent)
    lines = proc.stdout.splitlines()
    assert len(lines) == 4, proc.stdout + proc.stderr
    for line in lines:
        assert " ResourceError " in line and "100000 x 100000 px needs about" in line, line
    assert not (Path(__file__).parent / "o.png").exists()
