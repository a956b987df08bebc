"""Packaging rules of design.md: bokehray imports without torch; kernels never import bokehray."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import bokehray as br


@pytest.mark.slow
def test_import_and_render_without_torch():
    code = (
        "import sys; sys.modules['torch'] = None\n"
        "import numpy as np, bokehray as br\n"
        "out = br.render(np.ones((8, 8, 3), np.float32), np.zeros((8, 8), np.float32), br.BlurParams(2.0, 1.0))\n"
        "assert 'torch' not in [m for m in sys.modules if sys.modules[m] is not None]\n"
        "print(float(out.mean()))\n"
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    assert abs(float(res.stdout.split()[-1]) - 1.0) < 1e-5


def test_kernels_do_not_import_the_package_above_them():
    import bokehray_kernels

    folder = Path(bokehray_kernels.__file__).parent
    src = "\n".join(f.read_text() for f in sorted(folder.glob("*.py")))
    assert len(list(folder.glob("*.py"))) > 10  # every kernel module is read
    assert "import bokehray\n" not in src and "from bokehray " not in src and "import bokehray." not in src
    assert "from bokehray." not in src.replace("from bokehray_kernels", "")


def test_public_api_is_exported():
    for name in br.__all__:
        assert hasattr(br, name), name
    assert isinstance(br.render(np.zeros((2, 2, 3), np.float32), np.zeros((2, 2), np.float32),
                                br.BlurParams(0.0, 0.0)), np.ndarray)
