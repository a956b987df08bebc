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


def _gap_ok(img, s, py, px, ny, nx, level, f, rule, flat=None) -> bool:
    """``flat``: the background 2 px across must lie within this of the pixel's CoC (None: no such test)."""
    for m in (1, 2):
        for sg in (1, -1):
            if not _farther(s, py + sg * _round(m * ny), px + sg * _round(m * nx), level):
                return False
    across = [q for q in ((py + sg * _round(2 * ny), px + sg * _round(2 * nx)) for sg in (1, -1)) if _inside(s, *q)]
    if flat is not None and any(abs(s[q] - s[py, px]) > flat for q in across):
        return False
    across = [img[q] for q in across]
    if not across:
        return False
    b = np.mean(across, 0)
    if max(f.mean(), b.mean()) > rule.light_level:
        return False  # a light's colour: the test cannot read the strand's share
    d = f - b
    den = float(d @ d)
    if den <= rule.min_contrast ** 2 * max(float(f @ f), float(b @ b)) or den <= 1e-20:
        return False
    r = img[py, px] - b
    a = float(r @ d) / den
    off = r - a * d
    return a >= rule.min_share and float(off @ off) <= rule.max_off ** 2 * den


def _extend_end_ref(img, s, y1, x1, rule, out) -> None:
    """Walk from a dash end away from its own-depth 8-neighbours (their mean offset) over the pixels behind it whose
    colour shows the strand (``_gap_ok`` with F the end's colour and one surface across), giving each the end's
    value."""
    v = s[y1, x1]

    def own(dy, dx):
        return (dy, dx) != (0, 0) and _inside(s, y1 + dy, x1 + dx) and abs(s[y1 + dy, x1 + dx] - v) <= rule.jump_px

    near = [(dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1) if own(dy, dx)]
    # within 2 px, of its depth and joined to it (an 8-neighbour, or next to one): its own dash, not the next one
    joined = [(dy, dx) for dy in range(-2, 3) for dx in range(-2, 3) if own(dy, dx)
              and (max(abs(dy), abs(dx)) == 1 or any(max(abs(dy - my), abs(dx - mx)) <= 1 for my, mx in near))]
    sy, sx = sum(o[0] for o in joined), sum(o[1] for o in joined)
    if not joined or len(joined) > 8 or (sy, sx) == (0, 0) or not _ends_towards(s, y1, x1, -sy, -sx, rule.jump_px):
        return
    steps = max(abs(sy), abs(sx))
    uy, ux = -sy / steps, -sx / steps
    level = v - rule.jump_px
    by, bx = y1 - _round(uy), x1 - _round(ux)  # the pixel before the end: of its depth
    if not _inside(s, by, bx) or abs(s[by, bx] - v) > rule.jump_px:
        return
    ny, nx = _round(ux), -_round(uy)  # across the way out: the end and the pixel before it thin there (a tip)
    n = rule.thin_px
    for cy, cx in ((y1, x1), (by, bx)):
        if not (any(_farther(s, cy + k * ny, cx + k * nx, level) for k in range(1, n + 1))
                and any(_farther(s, cy - k * ny, cx - k * nx, level) for k in range(1, n + 1))):
            return
    for k in range(1, rule.end_px + 1):
        py, px = y1 + _round(k * uy), x1 + _round(k * ux)
        if not _inside(s, py, px) or s[py, px] >= level:
            return
        if not _gap_ok(img, s, py, px, ux, -uy, level, img[y1, x1], rule, flat=rule.jump_px):
            return
        out[py, px] = max(out[py, px], v)


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
        if rule.end_px > 0:
            _extend_end_ref(img, s, y1, x1, rule, out)
    return out


def hidden_lights_ref(image: np.ndarray, s: np.ndarray, soft, rule) -> dict[int, tuple[np.ndarray, float]]:
    """The pixels ``bokehray.strands.hidden_lights`` adds, one at a time: flat index -> (the light's colour behind
    it, its CoC). A pixel qualifies when it is not split, not lit itself and lies within ``reach`` along one of the
    four axes of a split pixel with a lit far part, nearer than that far part by more than ``jump_px``; along each axis and side the first light within ``reach`` (a split pixel's
    lit B or a whole lit pixel, farther by more than ``jump_px``) counts when only unsplit, unlit pixels of the
    strand's depth lie before it; the axis with lights on both sides (within ``jump_px`` of each other's CoC)
    nearest in all wins, the light interpolated linearly in the distances."""
    h, w = s.shape
    img = image.astype(np.float64)
    where = {int(i): k for k, i in enumerate(soft.index)}
    seeds = [int(i) for k, i in enumerate(soft.index) if soft.background[k].mean() > rule.light_level]
    out = {}
    for c in range(h * w):
        cy, cx = divmod(c, w)
        if c in where or img[cy, cx].mean() > rule.light_level:
            continue
        if not any(_on_an_axis(cy - sy, cx - sx, rule.reach) and s[cy, cx] > soft.far_coc[where[q]] + rule.jump_px
                   for q, (sy, sx) in ((q, divmod(q, w)) for q in seeds)):
            continue
        best = None
        for dy, dx in ((0, 1), (1, 0), (1, 1), (1, -1)):
            found = [_first_light(img, s, soft, where, rule, cy, cx, sg * dy, sg * dx) for sg in (1, -1)]
            if None in found or abs(found[0][2] - found[1][2]) > rule.jump_px:
                continue  # a light on both sides, at one depth
            if best is None or found[0][0] + found[1][0] < best[0]:
                (k1, b1, f1), (k2, b2, f2) = found
                best = (k1 + k2, (k2 * b1 + k1 * b2) / (k1 + k2), (k2 * f1 + k1 * f2) / (k1 + k2))
        if best is not None:
            out[c] = (best[1], best[2])
    return out


def _first_light(img, s, soft, where, rule, cy, cx, dy, dx):
    """(steps, colour, CoC) of the first light from (cy, cx) along (dy, dx) within ``reach`` with only the strand's
    unsplit pixels before it; None if there is none."""
    w = s.shape[1]
    for k in range(1, rule.reach + 1):
        y, x = cy + k * dy, cx + k * dx
        if not _inside(s, y, x):
            return None
        q = y * w + x
        colour = soft.background[where[q]].astype(np.float64) if q in where else img[y, x]
        coc = float(soft.far_coc[where[q]]) if q in where else float(s[y, x])
        if colour.mean() > rule.light_level and coc < s[cy, cx] - rule.jump_px:
            return k, colour, coc
        if q in where or s[y, x] < s[cy, cx] - rule.jump_px:
            return None  # not the strand going on
    return None


def _on_an_axis(dy: int, dx: int, reach: int) -> bool:
    """(dy, dx) is 1 to ``reach`` steps along a row, a column or a diagonal."""
    return (dy, dx) != (0, 0) and max(abs(dy), abs(dx)) <= reach and (dy == 0 or dx == 0 or abs(dy) == abs(dx))
