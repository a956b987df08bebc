"""Float64 NumPy oracle of ``bokehray_kernels.strands`` (``bokehray.strands.bridge_strands``): the same rule, one
pixel pair at a time, written for reading, not speed."""

from __future__ import annotations

import math

import numpy as np


def _inside(s: np.ndarray, y: int, x: int) -> bool:
    return 0 <= y < s.shape[0] and 0 <= x < s.shape[1]


def _farther(s: np.ndarray, y: int, x: int, level: float) -> bool:
    """Outside the frame, or behind ``level``."""
    return not _inside(s, y, x) or s[y, x] < level


def strand_pixels_ref(s: np.ndarray, rule) -> np.ndarray:
    """Pixels nearer (by more than ``jump_px``) than a pixel within ``thin_px`` on both sides along an axis."""
    h, w = s.shape
    out = np.zeros((h, w), bool)
    n = rule.thin_px
    for y in range(h):
        for x in range(w):
            level = s[y, x] - rule.jump_px
            for dy, dx in ((0, 1), (1, 0), (1, 1), (1, -1)):
                fwd = any(_farther(s, y + k * dy, x + k * dx, level) for k in range(1, n + 1))
                bwd = any(_farther(s, y - k * dy, x - k * dx, level) for k in range(1, n + 1))
                if fwd and bwd:
                    out[y, x] = True
    return out


def _round(v: float) -> int:
    return math.floor(v + 0.5)


def _ends_towards(s: np.ndarray, y: int, x: int, oy: int, ox: int, jump: float) -> bool:
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            if dy * oy + dx * ox > 0 and _inside(s, y + dy, x + dx) and abs(s[y + dy, x + dx] - s[y, x]) <= jump:
                return False
    return True


def _segment(y1: int, x1: int, oy: int, ox: int) -> list[tuple[int, int]]:
    steps = max(abs(oy), abs(ox))
    return [(y1 + _round(k / steps * oy), x1 + _round(k / steps * ox)) for k in range(1, steps)]


def _gap_ok(img, s, py, px, ny, nx, level, f, rule) -> bool:
    for m in (1, 2):
        for sg in (1, -1):
            if not _farther(s, py + sg * _round(m * ny), px + sg * _round(m * nx), level):
                return False
    across = [(py + sg * _round(2 * ny), px + sg * _round(2 * nx)) for sg in (1, -1)]
    across = [img[q] for q in across if _inside(s, *q)]
    if not across:
        return False
    b = np.mean(across, 0)
    d = f - b
    den = float(d @ d)
    if den <= rule.min_contrast ** 2 * max(float(f @ f), float(b @ b)) or den <= 1e-20:
        return False
    r = img[py, px] - b
    a = float(r @ d) / den
    off = r - a * d
    return a >= rule.min_share and float(off @ off) <= rule.max_off ** 2 * den


def bridge_strands_ref(image: np.ndarray, s: np.ndarray, rule, offsets: np.ndarray) -> np.ndarray:
    """The bridged map for ``rule`` (a ``bokehray.strands.StrandRule``) and the gap ``offsets`` (the half window,
    ``bokehray.strands.gap_offsets``)."""
    s = s.astype(np.float64)
    img = image.astype(np.float64)
    strand = strand_pixels_ref(s, rule)
    out = s.copy()
    for y1, x1 in zip(*np.nonzero(strand)):
        for oy, ox in offsets:
            y2, x2 = y1 + int(oy), x1 + int(ox)
            if not (_inside(s, y2, x2) and strand[y2, x2] and abs(s[y2, x2] - s[y1, x1]) <= rule.jump_px):
                continue
            if not (_ends_towards(s, y1, x1, oy, ox, rule.jump_px) and _ends_towards(s, y2, x2, -oy, -ox, rule.jump_px)):
                continue
            level = min(s[y1, x1], s[y2, x2]) - rule.jump_px
            steps = max(abs(int(oy)), abs(int(ox)))
            ny, nx = ox / steps, -oy / steps
            f = 0.5 * (img[y1, x1] + img[y2, x2])
            gaps = [p for p in _segment(y1, x1, int(oy), int(ox)) if s[p] < level]
            if gaps and all(_gap_ok(img, s, py, px, ny, nx, level, f, rule) for py, px in gaps):
                for p in gaps:
                    out[p] = max(out[p], 0.5 * (s[y1, x1] + s[y2, x2]))
    return out
