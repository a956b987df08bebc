"""Faces and their eyes, for the default focus: a photographer (and a phone) focuses a portrait on the eyes.

OpenCV's Haar cascades (``haarcascade_frontalface_default.xml``, ``haarcascade_eye.xml``) ship inside the
opencv-python-headless wheel (``cv2.data.haarcascades``): nothing is downloaded, and they run on a CPU. Faces are
found on a copy of the photo at most :data:`DETECT_SIDE` pixels on its longer side (about 0.06 s, whatever the
photo's size); the eyes inside each face's upper half, on a crop of the full photo scaled so the face is
:data:`EYE_FACE_PX` pixels wide. A face counts only when it is *sizeable* (at least :data:`FACE_MIN_SHARE` of the
frame's shorter side across) and the eye cascade finds an eye in it (a patch of texture the face cascade mistakes
for a face has no eye). The focus depth is read at the eyes themselves (:func:`eye_disparity`), not at the face
box's centre (a cheek, the nose) or its top (the hairline).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cache

import numpy as np

from ..colour import linear_to_srgb

__all__ = ["DETECT_SIDE", "EYE_FACE_PX", "FACE_MIN_SHARE", "EyesFocus", "Face", "detect_faces", "eye_disparity",
           "eyes_focus"]

DETECT_SIDE = 640
"""Faces are looked for on a copy of the photo this many pixels on its longer side (or the photo, if smaller)."""

FACE_MIN_SHARE = 0.06
"""A face narrower than this share of the frame's shorter side is not sizeable: a face in a crowd, on a poster."""

EYE_FACE_PX = 200
"""Eyes are looked for on the face's upper half scaled so the face is this many pixels wide."""

_EYE_WINDOW = 0.06  # the depth at an eye is the median of a square this share of the face's width across (>= 3 px)


@dataclass(frozen=True, slots=True)
class Face:
    """A face's box (``x``, ``y``, ``w``, ``h``, full-resolution pixels) and its eyes' centres (one or two)."""

    x: int
    y: int
    w: int
    h: int
    eyes: tuple[tuple[int, int], ...]


@dataclass(frozen=True, slots=True)
class EyesFocus:
    """The default focus on a face: disparity ``d_f`` read at its eyes, the eyes' midpoint (``x``, ``y``), the face
    and how many sizeable faces the photo shows."""

    d_f: float
    x: int
    y: int
    face: Face
    faces: int = 1

    def describe(self) -> str:
        """What was chosen, in words (``bokehray render`` prints it after ``focus:``)."""
        return (f"{self.words()} at ({self.x}, {self.y}), d_f = {self.d_f:.3f} ({self.faces} sizeable "
                f"face{'s' * (self.faces > 1)} found)")

    def words(self) -> str:
        """The choice said shortest, for the page: ``the eyes of the nearest face``."""
        return f"the {'eyes' if len(self.face.eyes) > 1 else 'eye'} of the nearest face"


@cache
def _cascade(name: str):
    """A bundled cascade, loaded once per process (parsing the face cascade's XML takes about 30 ms)."""
    import cv2

    path = cv2.data.haarcascades + name
    cascade = cv2.CascadeClassifier(path)
    if cascade.empty():  # a broken install: say so rather than find no face
        raise RuntimeError(f"OpenCV could not load its bundled cascade {path}")
    return cascade


def _grey8(image: np.ndarray, side: int) -> tuple[np.ndarray, float]:
    """The photo as 8-bit sRGB luma, at most ``side`` pixels on its longer side (area-averaged in linear light),
    histogram-equalised; and the factor from its pixels to the photo's."""
    import cv2

    a = np.asarray(image, np.float32)
    if a.ndim == 3:  # the luma first (linear: the same as the luma of the average), one plane to resize
        a = a[..., 0] if a.shape[2] < 3 else a[..., :3] @ np.array([0.2126, 0.7152, 0.0722], np.float32)
    h, w = a.shape
    f = max(h, w) / side if max(h, w) > side else 1.0
    lum = np.ascontiguousarray(a)
    if f > 1.0:
        lum = cv2.resize(lum, (max(1, round(w / f)), max(1, round(h / f))), interpolation=cv2.INTER_AREA)
    codes = np.round(linear_to_srgb(np.clip(lum, 0.0, 1.0)) * 255.0).astype(np.uint8)
    return cv2.equalizeHist(codes), f


def _eyes(image: np.ndarray, box: tuple[int, int, int, int], eye_cascade) -> tuple[tuple[int, int], ...]:
    """The centres of at most two eyes in the upper half of a face ``box`` (full-resolution pixels), left first."""
    x, y, w, h = box
    crop = image[y : y + int(h * 0.6), x : x + w]
    grey, f = _grey8(crop, EYE_FACE_PX)
    s = max(6, grey.shape[1] // 10)
    found = eye_cascade.detectMultiScale(grey, scaleFactor=1.1, minNeighbors=3, minSize=(s, s),
                                         maxSize=(grey.shape[1] // 2, grey.shape[1] // 2))
    eyes = sorted(((ex + ew / 2.0, ey + eh / 2.0, ew) for ex, ey, ew, eh in found), key=lambda e: -e[2])[:2]
    return tuple(sorted((x + round(cx * f), y + round(cy * f)) for cx, cy, _ in eyes))


def detect_faces(image: np.ndarray) -> list[Face]:
    """The sizeable frontal faces with at least one eye found in them (linear RGB, any size), largest first."""
    h, w = image.shape[:2]
    grey, f = _grey8(image, DETECT_SIDE)
    least = max(24, math.ceil(FACE_MIN_SHARE * min(grey.shape)))
    boxes = _cascade("haarcascade_frontalface_default.xml").detectMultiScale(
        grey, scaleFactor=1.1, minNeighbors=5, minSize=(least, least))
    eye_cascade = _cascade("haarcascade_eye.xml")
    faces = []
    for bx, by, bw, bh in sorted((tuple(int(v) for v in b) for b in boxes), key=lambda b: -b[2]):
        x0, y0 = min(w - 1, round(bx * f)), min(h - 1, round(by * f))
        box = (x0, y0, max(1, min(w - x0, round(bw * f))), max(1, min(h - y0, round(bh * f))))
        eyes = _eyes(image, box, eye_cascade)
        if eyes:
            faces.append(Face(*box, eyes))
    return faces


def eye_disparity(disparity: np.ndarray, face: Face) -> float:
    """The disparity at the face's eyes: the median of a small square (``_EYE_WINDOW`` of the face's width) around
    each eye, the nearer of the two (a turned face is focused on its near eye)."""
    h, w = disparity.shape
    r = max(1, round(_EYE_WINDOW * face.w / 2))
    near = -math.inf
    for ex, ey in face.eyes:
        win = disparity[max(0, ey - r) : min(h, ey + r + 1), max(0, ex - r) : min(w, ex + r + 1)]
        near = max(near, float(np.median(win)))
    return near


def eyes_focus(image: np.ndarray, disparity: np.ndarray) -> EyesFocus | None:
    """The eyes of the nearest sizeable face (by the disparity at its eyes), or None when the photo shows none."""
    faces = detect_faces(image)
    if not faces:
        return None
    d, face = max(((eye_disparity(disparity, f), f) for f in faces), key=lambda t: t[0])
    xs, ys = zip(*face.eyes)
    return EyesFocus(d, round(sum(xs) / len(xs)), round(sum(ys) / len(ys)), face, len(faces))
