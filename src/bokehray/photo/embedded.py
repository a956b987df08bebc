"""What a photo file carries besides its pixels: EXIF orientation, the ICC profile, EXIF to keep for the output.
Used by the readers (``bokehray.photo.read``); see docs/conventions.md (Light) and docs/usage.md.
"""

from __future__ import annotations

import os
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .._memory import on_cores
from ..errors import InputError

__all__ = ["Embedded", "apply_orientation", "embedded", "exif_for_output", "orientation_words", "to_srgb_codes"]

_ORIENTATION_WORDS = {
    1: "upright", 2: "mirrored left-right", 3: "rotated 180 degrees", 4: "mirrored top-bottom",
    5: "transposed", 6: "rotated 90 degrees clockwise", 7: "transversed", 8: "rotated 90 degrees counter-clockwise",
}  # fmt: skip
"""What displaying the stored pixels with each EXIF Orientation value does to them (the reader does the same)."""


@dataclass(frozen=True, slots=True)
class Embedded:
    """What a photo file carries besides its pixels: the EXIF Orientation (1 = upright), the ICC profile and
    its description, and the raw EXIF block (JPEG/PNG; ``None`` elsewhere)."""

    orientation: int = 1
    icc: bytes | None = None
    icc_name: str = ""
    exif: bytes | None = None

    @property
    def is_srgb(self) -> bool:
        """No profile, or one that describes sRGB itself: no conversion needed."""
        return self.icc is None or "srgb" in self.icc_name.lower().replace(" ", "").replace("-", "")


def _icc_name(icc: bytes | None) -> str:
    if not icc:
        return ""
    import io as _io

    from PIL import ImageCms

    try:
        return ImageCms.getProfileDescription(ImageCms.ImageCmsProfile(_io.BytesIO(icc))).strip()
    except (ImageCms.PyCMSError, OSError, ValueError, TypeError):
        return "unreadable profile"


def _png_chunk(path: Path, kind: bytes) -> bytes | None:
    """The data of the first chunk of type ``kind`` in a PNG file, read by walking the chunk headers (no pixel
    is decoded); ``None`` when there is none before IEND or the file is cut short."""
    with open(path, "rb") as f:
        if f.read(8) != b"\x89PNG\r\n\x1a\n":
            return None
        while True:
            head = f.read(8)
            if len(head) < 8:
                return None
            length, ctype = struct.unpack(">I4s", head)
            if ctype == kind:
                data = f.read(length)
                return data if len(data) == length else None
            if ctype == b"IEND":
                return None
            f.seek(length + 4, 1)  # the data and its CRC


def embedded(path: Path, fmt: str) -> Embedded:
    """Read the orientation, ICC profile and EXIF of a PNG, JPEG or TIFF file (headers only, no pixels)."""
    if fmt in ("PNG", "JPEG"):
        from PIL import Image

        try:
            with Image.open(path, formats=[fmt]) as im:
                if fmt == "PNG" and "exif" not in im.info:
                    # Pillow's PNG getexif() decodes every pixel to reach an eXIf chunk after the image data;
                    # the chunk is found by its header instead
                    raw_chunk = _png_chunk(path, b"eXIf")
                    if raw_chunk is not None:
                        im.info["exif"] = raw_chunk
                    exif = Image.Image.getexif(im)
                else:
                    exif = im.getexif()
                orientation = int(exif.get(0x0112, 1) or 1)
                icc = im.info.get("icc_profile") or None
                raw = exif.tobytes() if len(exif) else None
        except (OSError, ValueError, SyntaxError, struct.error):
            return Embedded()  # the pixel decoder reports what is wrong with the file
        return Embedded(orientation if orientation in _ORIENTATION_WORDS else 1, icc, _icc_name(icc), raw)
    if fmt == "TIFF":
        import tifffile

        from .._quiet import library_log

        try:
            with library_log("tifffile"), tifffile.TiffFile(path) as tf:  # damaged tags: its log, not stderr
                tags = tf.pages[0].tags
                orientation = int(tags["Orientation"].value) if "Orientation" in tags else 1
                icc = bytes(tags["InterColorProfile"].value) if "InterColorProfile" in tags else None
        except Exception:  # noqa: BLE001 - the pixel decoder reports what is wrong with the file
            return Embedded()
        return Embedded(orientation if orientation in _ORIENTATION_WORDS else 1, icc, _icc_name(icc), None)
    return Embedded()


def apply_orientation(a: np.ndarray, orientation: int) -> np.ndarray:
    """The stored pixels ``a`` (H x W or H x W x C, row 0 at the top) as displayed under EXIF ``orientation``."""
    if orientation == 2:
        a = a[:, ::-1]
    elif orientation == 3:
        a = a[::-1, ::-1]
    elif orientation == 4:
        a = a[::-1]
    elif orientation == 5:
        a = np.swapaxes(a, 0, 1)
    elif orientation == 6:
        a = np.swapaxes(a, 0, 1)[:, ::-1]
    elif orientation == 7:
        a = np.swapaxes(a, 0, 1)[::-1, ::-1]
    elif orientation == 8:
        a = np.swapaxes(a, 0, 1)[::-1]
    return np.ascontiguousarray(a)


def orientation_words(orientation: int) -> str:
    return _ORIENTATION_WORDS.get(orientation, "upright")


def to_srgb_codes(codes: np.ndarray, meta: Embedded, source: str) -> np.ndarray:
    """Convert integer RGB(A) codes encoded in the embedded profile's colour space to sRGB codes with littleCMS
    (Pillow's ImageCms; relative colorimetric intent, black-point compensation off). Colours outside the sRGB
    gamut are clipped to it. A profile of another colour space (CMYK, grey) is ignored. 16-bit codes are converted at 8-bit precision (littleCMS through Pillow takes
    8-bit RGB only), then scaled back to 16 bits. Grey images and images without a profile pass unchanged."""
    if meta.is_srgb or codes.ndim != 3 or codes.shape[2] < 3:
        return codes
    import io as _io

    from PIL import Image, ImageCms

    try:
        src = ImageCms.ImageCmsProfile(_io.BytesIO(meta.icc))
        if src.profile.xcolor_space.strip() != "RGB":
            return codes  # a CMYK or grey profile describes codes Pillow has already converted to RGB: keep them
        dst = ImageCms.ImageCmsProfile(ImageCms.createProfile("sRGB"))
        transform = ImageCms.buildTransform(src, dst, "RGB", "RGB",
                                            renderingIntent=ImageCms.Intent.RELATIVE_COLORIMETRIC)
    except (ImageCms.PyCMSError, OSError, ValueError, TypeError) as e:
        raise InputError(f"{source}: cannot use its embedded ICC profile ({meta.icc_name or 'unnamed'}): {e}") from None
    res = np.empty_like(codes)

    def part(y0: int, y1: int) -> None:  # a part of the rows: littleCMS converts each pixel on its own
        rgb = codes[y0:y1, :, :3]
        eight = rgb if rgb.dtype == np.uint8 else np.round(rgb / 257.0).astype(np.uint8)
        out = np.asarray(ImageCms.applyTransform(Image.fromarray(np.ascontiguousarray(eight), "RGB"), transform))
        res[y0:y1, :, :3] = out if codes.dtype == np.uint8 else out.astype(np.uint16) * 257
        res[y0:y1, :, 3:] = codes[y0:y1, :, 3:]

    h = codes.shape[0]
    n = max(1, min(os.cpu_count() or 1, h * codes.shape[1] // (1 << 18)))
    on_cores(part, [(h * j // n, h * (j + 1) // n) for j in range(n)])  # the parts on the CPU's cores
    return res


def exif_for_output(meta: Embedded) -> bytes | None:
    """The input's EXIF for a JPEG output, with Orientation reset to 1 (the pixels are written upright)."""
    if meta.exif is None:
        return None
    from PIL import Image

    exif = Image.Exif()
    exif.load(meta.exif)
    exif[0x0112] = 1
    return exif.tobytes()
