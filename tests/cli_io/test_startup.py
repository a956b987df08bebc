"""A fast start: the sRGB transfer without colour-science, lazy package exports, Warp quiet and
imported only when a render starts. The timings themselves are measured by benchmarks/scale/bench_startup.py."""

import subprocess
import sys

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from bokehray import colour as srgb


def _grid() -> np.ndarray:
    rng = np.random.default_rng(5)
    return np.concatenate([
        np.linspace(-0.25, 1.5, 400_001, dtype=np.float32),
        rng.random(100_000, dtype=np.float32) * 40.0,
        np.float32([0.0, 1.0, 0.04045, 0.0031308, srgb.SRGB_KNEE, np.inf, -np.inf, np.nan]),
        np.nextafter(np.float32(srgb.SRGB_KNEE), np.float32([-1, 2])),
        np.nextafter(np.float32(0.0031308), np.float32([-1, 2])),
    ])


@pytest.mark.parametrize(("ours", "theirs"), [("srgb_to_linear", "eotf_sRGB"),
                                              ("linear_to_srgb", "eotf_inverse_sRGB")])
def test_srgb_transfer_matches_colour_science_to_float32_rounding(ours, theirs):
    colour = pytest.importorskip("colour")
    x = _grid()
    with np.errstate(invalid="ignore"):
        want = np.asarray(getattr(colour.models, theirs)(x), np.float32)
    got = getattr(srgb, ours)(x)
    assert got.dtype == np.float32
    np.testing.assert_array_equal(got, want)  # bit for bit, NaN where NaN


@given(hnp.arrays(np.float32, st.integers(1, 64), elements=st.floats(0, 100, width=32)))
def test_srgb_transfer_matches_colour_science_everywhere(x):
    colour = pytest.importorskip("colour")
    np.testing.assert_array_equal(srgb.srgb_to_linear(x), np.asarray(colour.models.eotf_sRGB(x), np.float32))
    np.testing.assert_array_equal(srgb.linear_to_srgb(x), np.asarray(colour.models.eotf_inverse_sRGB(x), np.float32))


def _modules_after(code: str) -> set[str]:
    res = subprocess.run([sys.executable, "-c", code + "\nimport sys; print(' '.join(sys.modules))"],
                         capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    return set(res.stdout.split())


def test_import_bokehray_imports_no_warp_codec_or_colour_science():
    mods = _modules_after("import bokehray")
    assert not {"warp", "colour", "PIL", "OpenEXR", "tifffile", "scipy", "skimage", "matplotlib", "cv2"} & mods


def test_help_and_argument_errors_import_no_warp_or_colour_science():
    code = ("from bokehray.app.cli import main\nimport contextlib, io\n"
            "for argv in (['--help'], ['render', '--help'], ['render', 'x.png', '-o', 'y.png'],\n"
            "             ['render', 'x.png', '--disparity', 'd.png', '-o', 'y.png', '--focus', '0.5',\n"
            "              '--focus-at', '1,2']):\n"
            "    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):\n"
            "        try:\n            code = main(argv)\n        except SystemExit as e:\n            code = e.code\n"
            "    assert code in (0, 2), (argv, code)")
    mods = _modules_after(code)
    assert not {"warp", "colour", "scipy", "matplotlib", "OpenEXR", "cv2"} & mods


@pytest.mark.slow
def test_warp_is_quiet_whoever_imports_it():
    res = subprocess.run([sys.executable, "-c", "import bokehray, warp; print(warp.config.log_level == "
                          "warp.LOG_WARNING)"], capture_output=True, text=True)
    assert res.returncode == 0 and res.stdout.split()[-1] == "True", res.stderr


def test_lazy_exports_resolve_to_the_defining_modules():
    import bokehray as br
    from bokehray import lens, pipeline

    assert br.render is pipeline.render and br.BlurParams is lens.BlurParams
    assert br.lens.disparity_from_depth is br.disparity_from_depth  # a submodule as an attribute
    assert set(br.__all__) <= set(dir(br))
    with pytest.raises(AttributeError, match="no attribute 'nonexistent'"):
        br.nonexistent  # noqa: B018


def test_level_registry_reads_each_level_module():
    from bokehray.levels import LEVELS, preview, raytrace

    assert LEVELS["preview"].whole_image_bytes() == preview.WHOLE_IMAGE_B
    assert LEVELS["raytrace"].whole_image_bytes() == raytrace.WHOLE_IMAGE_B


def test_all_lists_exactly_the_lazy_exports():
    import bokehray as br

    assert set(br.__all__) == set(br._EXPORTS) | {"__version__"}


def test_the_render_s_imports_beside_the_reading_load_what_a_render_needs_and_swallow_nothing_else():
    """prefetch_imports loads the renderer's modules on its thread (a fresh interpreter: none loaded before), and a
    module that cannot be imported stops the thread quietly (the import that needs it raises, not this one)."""
    code = (
        "import sys\n"
        "from bokehray.app.render_job import RENDER_MODULES, prefetch_imports\n"
        "assert not any(m in sys.modules for m in RENDER_MODULES)\n"
        "prefetch_imports().join()\n"
        "assert all(m in sys.modules for m in RENDER_MODULES), [m for m in RENDER_MODULES if m not in sys.modules]\n"
        "t = prefetch_imports(('bokehray_no_such_module', 'json'))\n"
        "t.join()\n"
        "assert not t.is_alive()\n"
        "print('ok')\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr
