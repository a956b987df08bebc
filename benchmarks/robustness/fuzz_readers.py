"""Coverage-guided fuzzing of the file readers with atheris (libFuzzer for Python).

Each input is written to a file with the format's extension and handed to every reader
that takes the format (``read_image``, ``read_disparity``, ``read_depth``) and to the
header-only ``read_size``. The contract under test: a reader returns a finite float32 array
of the documented shape, whose height and width ``read_size`` reported, without a Python
warning, or raises ``InputError``/``ResourceError`` (one clear message naming the file); anything else
(another exception, NaN in the output, a hang, a crash of a native decoder) is a finding
and its input is saved by libFuzzer as ``crash-*``/``timeout-*``. Python code of bokehray,
Pillow and tifffile is instrumented for coverage; the native decoders (libpng, libjpeg,
libtiff codecs, OpenEXR) run uninstrumented.

To keep runs fast, the harness lowers ``MAX_PIXELS`` to 2 MP (the limit logic itself is
tested in tests/test_io.py). Seeds are small valid files of every variant we write
(8/16-bit PNG, JPEG, 8/16-bit and float TIFF, float and half EXR, NPY); found inputs are
kept under tests/data/fuzz/ and replayed by tests/test_fuzz_regressions.py (no atheris).

Usage (needs ``pip install atheris``; from the repository root)::

    python benchmarks/robustness/fuzz_readers.py --seconds 90            # every format, 90 s each
    python benchmarks/robustness/fuzz_readers.py --format png --seconds 60 --corpus /tmp/png-corpus
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import warnings
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
FORMATS = {  # format -> (extension, readers)
    "png": (".png", ("read_image", "read_disparity")),
    "jpeg": (".jpg", ("read_image",)),
    "tiff": (".tif", ("read_image", "read_disparity", "read_depth")),
    "exr": (".exr", ("read_image", "read_disparity", "read_depth")),
    "npy": (".npy", ("read_disparity", "read_depth")),
}
FUZZ_MAX_PIXELS = 2_000_000


def write_seeds(fmt: str, folder: Path) -> list[Path]:
    """Small valid files of ``fmt`` in every variant the writers produce."""
    import numpy as np

    import bokehray as br

    rng = np.random.default_rng(0)
    img = rng.random((5, 7, 4)).astype(np.float32)
    d = rng.random((5, 7)).astype(np.float32)
    folder.mkdir(parents=True, exist_ok=True)
    out = []
    if fmt == "png":
        out += [br.write_image(folder / "rgb8.png", img[..., :3]), br.write_image(folder / "rgba16.png", img, bit_depth=16),
                br.write_image(folder / "grey8.png", img[..., :1]), br.write_disparity(folder / "disp16.png", d)]
    elif fmt == "jpeg":
        out += [br.write_image(folder / "rgb.jpg", img[..., :3], quality=50), br.write_image(folder / "grey.jpg", img[..., :1])]
    elif fmt == "tiff":
        out += [br.write_image(folder / "rgb16.tif", img[..., :3]), br.write_image(folder / "rgba8.tif", img, bit_depth=8),
                br.write_image(folder / "float.tif", img[..., :3], bit_depth=32), br.write_disparity(folder / "disp.tif", d)]
    elif fmt == "exr":
        out += [br.write_image(folder / "rgba.exr", img), br.write_image(folder / "half.exr", img[..., :3], half=True),
                br.write_disparity(folder / "disp.exr", d)]
    else:
        out += [br.write_disparity(folder / "disp.npy", d)]
    out += _issue18_seeds(fmt, folder, img, d)
    return out


def _issue18_seeds(fmt: str, folder: Path, img, d) -> list[Path]:
    """Variants the readers refuse or handle specially, so the fuzzer explores those paths:
    CMYK JPEG, multi-page TIFF and one with a reduced-resolution page, alpha-only EXR, float64 NPY."""
    import numpy as np
    import OpenEXR
    import tifffile
    from PIL import Image

    out = []
    if fmt == "jpeg":
        Image.fromarray((img[..., :3] * 255).astype(np.uint8)).convert("CMYK").save(folder / "cmyk.jpg", quality=50)
        out.append(folder / "cmyk.jpg")
    elif fmt == "tiff":
        codes = (d * 65535).astype(np.uint16)
        tifffile.imwrite(folder / "pages.tif", np.stack([codes, codes[::-1]]), photometric="minisblack")
        with tifffile.TiffWriter(folder / "reduced.tif") as w:
            w.write(codes, photometric="minisblack")
            w.write(codes[::2, ::2], photometric="minisblack", subfiletype=1)
        out += [folder / "pages.tif", folder / "reduced.tif"]
    elif fmt == "exr":
        header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
        with OpenEXR.File(header, {"A": np.ascontiguousarray(d)}) as f:
            f.write(str(folder / "alpha.exr"))
        out.append(folder / "alpha.exr")
    elif fmt == "npy":
        np.save(folder / "float64.npy", d.astype(np.float64) * 1e300)
        np.save(folder / "float64-ok.npy", d.astype(np.float64))
        out += [folder / "float64.npy", folder / "float64-ok.npy"]
    return out


def fuzz_one(fmt: str, seconds: int, corpus: Path, artifacts: Path) -> int:
    """Fuzz one format in this process until ``seconds`` have passed (libFuzzer exits the process)."""
    import atheris

    with atheris.instrument_imports(include=["bokehray", "PIL", "tifffile"]):
        import numpy as np

        import bokehray as br
        from bokehray.errors import InputError, ResourceError
        from bokehray.photo import read as rd

    rd.MAX_PIXELS = FUZZ_MAX_PIXELS
    ext, names = FORMATS[fmt]
    readers = [getattr(br, n) for n in names]
    path = Path(tempfile.mkdtemp(prefix=f"bokehray-fuzz-{fmt}-")) / f"input{ext}"

    def one_input(data: bytes) -> None:
        path.write_bytes(data)
        try:  # the header-only size: must agree with every reader that decodes the file
            size = rd.read_size(path)
        except (InputError, ResourceError) as e:
            if str(path) not in str(e):
                raise AssertionError(f"read_size: error does not name the file: {e}") from None
            size = None
        for read in readers:
            try:
                with warnings.catch_warnings():
                    warnings.simplefilter("error")  # a RuntimeWarning (overflow in a cast) would reach stderr
                    a = read(path)
            except (InputError, ResourceError) as e:
                if str(path) not in str(e):
                    raise AssertionError(f"{read.__name__}: error does not name the file: {e}") from None
                continue
            if a.dtype != np.float32 or a.ndim not in (2, 3) or not np.isfinite(a).all():
                raise AssertionError(f"{read.__name__}: returned {a.dtype} {a.shape} finite={np.isfinite(a).all()}")
            if size != a.shape[:2]:
                raise AssertionError(f"{read.__name__}: decoded {a.shape[:2]}, but read_size said {size}")

    if not any(corpus.iterdir()) if corpus.exists() else True:
        write_seeds(fmt, corpus)
    artifacts.mkdir(parents=True, exist_ok=True)
    argv = [sys.argv[0], str(corpus), f"-max_total_time={seconds}", f"-artifact_prefix={artifacts}/{fmt}-",
            "-timeout=20", "-rss_limit_mb=6144", "-max_len=65536", "-print_final_stats=1"]
    atheris.Setup(argv, one_input)
    atheris.Fuzz()
    return 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--format", choices=sorted(FORMATS), help="one format (default: all, one process each)")
    ap.add_argument("--seconds", type=int, default=60, help="fuzzing time per format")
    ap.add_argument("--corpus", type=Path, help="corpus folder (default: a temporary one seeded with valid files)")
    ap.add_argument("--artifacts", type=Path, default=Path(tempfile.gettempdir()) / "bokehray-fuzz-artifacts",
                    help="where libFuzzer saves crashing inputs")
    args = ap.parse_args()
    if args.format:
        corpus = args.corpus or Path(tempfile.mkdtemp(prefix=f"bokehray-corpus-{args.format}-"))
        return fuzz_one(args.format, args.seconds, corpus, args.artifacts)
    status = 0
    for fmt in FORMATS:
        cmd = [sys.executable, __file__, "--format", fmt, "--seconds", str(args.seconds),
               "--artifacts", str(args.artifacts)]
        if args.corpus:
            cmd += ["--corpus", str(args.corpus / fmt)]
        print(f"== {fmt}", flush=True)
        rc = subprocess.run(cmd, env={**os.environ, "PYTHONWARNINGS": "ignore"}).returncode
        print(f"== {fmt}: exit code {rc}", flush=True)
        status = status or rc
    return status


if __name__ == "__main__":
    sys.exit(main())
