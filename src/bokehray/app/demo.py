"""Built-in demo scene (no downloads) and a contact-sheet helper.

The scene is a layered composition painted back to front with straight-alpha
"over" compositing and antialiased (distance-based) edges. The disparity of a
pixel is that of the front-most layer whose alpha at the pixel is >= 0.5.
Layers (disparity 1 = nearest, 0 = farthest):

* far background: ``skimage.data.rocket`` (a launch pad at dusk) on a tilted
  plane, disparity 0.0 (top left) to 0.2 (bottom right), its clipped lamps
  lifted to a linear radiance of about 4;
* fairy lights: a garland of small discs (radius 1.5-3 px, linear radiance
  5-20, warm and cool) in the sky, plus a few distant lamps near the horizon,
  all on the background plane;
* mid-ground: a rotated brick panel with rounded corners and a printed notice
  (``brick`` and ``page``), disparity 0.45 -> 0.55 across its width;
* thin structures: wires and grass-like blades 0.4-3 px wide at 0.70-0.84
  (behind the subject) and 0.95-1.0 (in front of it);
* near subject: ``chelsea`` (the cat) in an elliptical cut-out, a dome of
  disparity 0.92 at the centre falling to 0.86 at the rim.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from skimage import data as skdata
from skimage.transform import resize

from ..errors import InputError
from ..validate import fits_in_memory

__all__ = ["SHEET_GAP", "SHEET_LABEL_H", "DemoScene", "build_demo_scene", "contact_sheet", "stroke"]

_REF_WIDTH = 768
_MAX_COC_PX = 24.0
_BG_D = (0.16, 0.04)  # background disparity slope along y and x (0 at top left)
_PANEL_D = (0.45, 0.55)
_SUBJECT_D = (0.92, 0.86)  # centre, rim
_FOCUS_FAR = 0.1
_BUILD_BYTES_PER_PX = 64  # peak of build_demo_scene: 55 B/px measured at 4 MP (coordinate grids, layers, texture)
SHEET_GAP = 8  # contact sheet: gap between tiles (px)
SHEET_LABEL_H = 26  # contact sheet: label strip height under each tile (px)


@dataclass(frozen=True)
class DemoScene:
    """A synthetic all-in-focus photo with its disparity map.

    Attributes:
        image: float32 H x W x 3, scene-linear, all-in-focus.
        disparity: float32 H x W in [0, 1] (1 = nearest).
        focus_near: focus disparity ``d_f`` that puts the near subject in focus.
        focus_far: focus disparity that puts the far background in focus.
        k_px: suggested blur strength K (max CoC radius ~24 px at 768 px width).
        description: human-readable layer layout.
    """

    image: np.ndarray
    disparity: np.ndarray
    focus_near: float
    focus_far: float
    k_px: float
    description: str


def _linear(img: np.ndarray) -> np.ndarray:
    x = img.astype(np.float32) / 255.0
    from ..colour import srgb_to_linear  # the same numbers as colour-science's sRGB decoding, without its import

    return srgb_to_linear(x)


def _cover(tex: np.ndarray, h: int, w: int, centre: tuple[float, float] = (0.5, 0.5)) -> np.ndarray:
    """Resize ``tex`` keeping its aspect so that it covers h x w, then crop around ``centre``."""
    th, tw = tex.shape[:2]
    s = max(h / th, w / tw)
    nh, nw = max(h, round(th * s)), max(w, round(tw * s))
    r = resize(tex, (nh, nw) + tex.shape[2:], order=1, anti_aliasing=True, preserve_range=True)
    y0 = int(np.clip(round(centre[0] * nh - h / 2), 0, nh - h))
    x0 = int(np.clip(round(centre[1] * nw - w / 2), 0, nw - w))
    return r[y0:y0 + h, x0:x0 + w].astype(np.float32)


def _over(img: np.ndarray, disp: np.ndarray, sl: tuple[slice, slice], alpha: np.ndarray, rgb, d) -> None:
    """Composite a layer over ``img[sl]`` and take its disparity where alpha >= 0.5."""
    a = alpha[..., None]
    img[sl] = img[sl] * (1.0 - a) + a * rgb
    disp[sl] = np.where(alpha >= 0.5, d, disp[sl])


def _bbox(x0: float, y0: float, x1: float, y1: float, w: int, h: int):
    xa, ya = max(int(math.floor(x0)), 0), max(int(math.floor(y0)), 0)
    xb, yb = min(int(math.ceil(x1)) + 1, w), min(int(math.ceil(y1)) + 1, h)
    if xa >= xb or ya >= yb:
        return None
    gy, gx = np.mgrid[ya:yb, xa:xb].astype(np.float32)
    return (slice(ya, yb), slice(xa, xb)), gx, gy


def stroke(pts: np.ndarray, widths: np.ndarray, w: int, h: int):
    """Coverage of a polyline of varying width (area-preserving, sub-pixel widths allowed)."""
    pad = float(widths.max()) + 2.0
    box = _bbox(pts[:, 0].min() - pad, pts[:, 1].min() - pad, pts[:, 0].max() + pad, pts[:, 1].max() + pad, w, h)
    if box is None:
        return None
    sl, gx, gy = box
    alpha = np.zeros_like(gx)
    for (ax, ay), (bx, by), wa, wb in zip(pts[:-1], pts[1:], widths[:-1], widths[1:]):
        vx, vy = bx - ax, by - ay
        t = np.clip(((gx - ax) * vx + (gy - ay) * vy) / max(vx * vx + vy * vy, 1e-12), 0.0, 1.0)
        dist = np.hypot(gx - ax - t * vx, gy - ay - t * vy)
        wid = wa + t * (wb - wa)
        np.maximum(alpha, np.clip(wid / 2 + 0.5 - dist, 0.0, np.minimum(wid, 1.0)), out=alpha)
    return sl, alpha


def build_demo_scene(width: int = 768, height: int = 512, seed: int = 0) -> DemoScene:  # noqa: C901
    """Build the deterministic layered demo scene.

    Args:
        width: image width in pixels (>= 64).
        height: image height in pixels (>= 64).
        seed: seed of the random placement of lights and strands.

    Returns:
        The :class:`DemoScene`.

    Raises:
        InputError: if the size is smaller than 64 x 64.
        ResourceError: if the scene would not fit in the memory available.
    """
    W, H = int(width), int(height)
    if W < 64 or H < 64:
        raise InputError(f"demo size: expected width and height >= 64, got {width} x {height}")
    fits_in_memory((H, W), _BUILD_BYTES_PER_PX, "demo size")  # before the coordinate grids are allocated
    rng = np.random.default_rng(seed)
    s = W / _REF_WIDTH  # pixel-size scale
    gy, gx = np.mgrid[0:H, 0:W].astype(np.float32)


    # Far background: dusk launch pad on a tilted plane; clipped lamps lifted to HDR.
    rocket = skdata.rocket()
    lamp = np.clip((rocket.max(axis=2).astype(np.float32) / 255.0 - 0.92) / 0.08, 0.0, 1.0)
    bg = _linear(rocket) * (1.0 + 3.0 * lamp * lamp * (3.0 - 2.0 * lamp))[..., None]
    img = _cover(bg, H, W, centre=(0.45, 0.5))
    disp = (_BG_D[0] * gy / (H - 1) + _BG_D[1] * gx / (W - 1)).astype(np.float32)

    # Fairy lights: a garland sagging across the sky, plus distant lamps near the horizon.
    n = 24
    u = (np.arange(n) + rng.uniform(-0.3, 0.3, n)) / (n - 1)
    lx = W * (0.03 + 0.94 * u)
    ly = H * (0.08 + 0.07 * u + 0.16 * (1.0 - (2.0 * u - 1.0) ** 2))
    cord = stroke(np.stack([lx, ly + 1.5 * s], 1), np.full(n, 0.6 * s), W, H)
    if cord is not None:
        _over(img, disp, cord[0], 0.8 * cord[1], np.float32(0.01), disp[cord[0]])
    lx = np.concatenate([lx, W * rng.uniform(0.05, 0.95, 8)])
    ly = np.concatenate([ly, H * rng.uniform(0.62, 0.74, 8)])
    palette = np.array([[1.0, 0.55, 0.22], [1.0, 0.78, 0.45], [0.35, 0.6, 1.0], [0.55, 1.0, 0.7], [1.0, 0.4, 0.6]])
    for x, y in zip(lx, ly):
        r = max(rng.uniform(1.5, 3.0) * s, 1.0)
        rgb = palette[rng.integers(len(palette))] * rng.uniform(5.0, 20.0)
        box = _bbox(x - r - 1, y - r - 1, x + r + 1, y + r + 1, W, H)
        if box is not None:
            sl, bx, by = box
            a = np.clip(r + 0.5 - np.hypot(bx - x, by - y), 0.0, 1.0)
            _over(img, disp, sl, a, rgb.astype(np.float32), disp[sl])

    # Mid-ground: rotated brick panel with rounded corners and a printed notice; tilted left -> right.
    pw, ph, theta = max(round(0.34 * W), 8), max(round(0.50 * H), 8), math.radians(-5.0)
    cx, cy = 0.30 * W, 0.50 * H
    v = _cover(_linear(skdata.brick()), ph, pw)
    v = np.clip(v / max(float(v.max()), 1e-6), 0.0, 1.0)[..., None] ** 1.5
    tex = np.array([0.26, 0.065, 0.03], np.float32) * (1 - v) + np.array([0.58, 0.55, 0.48], np.float32) * v
    nh, nw = max(round(0.30 * ph), 2), max(round(0.66 * pw), 2)
    ny, nx = round(0.14 * ph), (pw - nw) // 2
    paper = _cover(_linear(skdata.page()), nh, nw)[..., None] * np.array([0.95, 0.92, 0.82], np.float32)
    tex[ny:ny + nh, nx:nx + nw] = paper
    frame = max(round(2 * s), 1)
    tex[ny - frame:ny, nx - frame:nx + nw + frame] = tex[ny + nh:ny + nh + frame, nx - frame:nx + nw + frame] = 0.03
    tex[ny:ny + nh, nx - frame:nx] = tex[ny:ny + nh, nx + nw:nx + nw + frame] = 0.03
    half = math.hypot(pw, ph) / 2 + 2
    box = _bbox(cx - half, cy - half, cx + half, cy + half, W, H)
    if box is not None:
        sl, bx, by = box
        ux = math.cos(theta) * (bx - cx) + math.sin(theta) * (by - cy)
        uy = -math.sin(theta) * (bx - cx) + math.cos(theta) * (by - cy)
        rad = 0.07 * min(pw, ph)
        qx, qy = np.abs(ux) - (pw / 2 - rad), np.abs(uy) - (ph / 2 - rad)
        sd = np.hypot(np.maximum(qx, 0), np.maximum(qy, 0)) + np.minimum(np.maximum(qx, qy), 0) - rad
        a = np.clip(0.5 - sd, 0.0, 1.0)
        coords = [uy + ph / 2 - 0.5, ux + pw / 2 - 0.5]
        rgb = np.stack([ndimage.map_coordinates(tex[..., c], coords, order=1, mode="nearest") for c in range(3)], -1)
        d = _PANEL_D[0] + (_PANEL_D[1] - _PANEL_D[0]) * np.clip(ux / pw + 0.5, 0.0, 1.0)
        _over(img, disp, sl, a, rgb, d)

    # Thin structures: wires and grass blades / stems (painted by disparity around the subject).
    strands = []  # (disparity, points, widths, rgb)
    xs = np.linspace(-0.02 * W, 1.02 * W, 33)
    for y0, y1, sag, wid, d, rgb in ((0.30, 0.22, 0.07, 1.3, 0.78, (0.55, 0.55, 0.58)),
                                     (0.40, 0.47, 0.05, 0.7, 0.74, (0.02, 0.02, 0.02))):
        t = xs / W
        ys = H * (y0 + (y1 - y0) * t + sag * (1.0 - (2.0 * t - 1.0) ** 2))
        strands.append((d, np.stack([xs, ys], 1), np.full(xs.size, wid * s), rgb))
    tt = np.linspace(0.0, 1.0, 12)[:, None]
    for i in range(34):
        front = i % 3 == 0
        d = rng.uniform(0.95, 1.0) if front else rng.uniform(0.70, 0.84)
        stem = i % 5 == 4  # tall sub-pixel stems
        hgt = H * (rng.uniform(0.40, 0.62) if stem else rng.uniform(0.12, 0.42))
        xb, lean = W * rng.uniform(0.0, 1.0), W * rng.uniform(-0.10, 0.10)
        p0, p1, p2 = np.array([xb, H + 2.0]), np.array([xb + 0.2 * lean, H - 0.6 * hgt]), np.array([xb + lean, H - hgt])
        pts = (1 - tt) ** 2 * p0 + 2 * (1 - tt) * tt * p1 + tt**2 * p2
        w0, w1 = (rng.uniform(0.4, 0.8), 0.35) if stem else (rng.uniform(1.5, 3.0), rng.uniform(0.3, 0.8))
        widths = np.maximum(np.linspace(w0, w1, tt.size) * s, 0.3 if stem else 0.5)
        rgb = np.array([0.42, 0.38, 0.16]) * rng.uniform(0.6, 1.3) + np.array([-0.1, 0.02, -0.05]) * rng.uniform(0, 1)
        strands.append((d, pts, widths, tuple(rgb)))
    strands.sort(key=lambda st: st[0])

    def paint(strand_list) -> None:
        for d, pts, widths, rgb in strand_list:
            res = stroke(pts, widths, W, H)
            if res is not None:
                _over(img, disp, res[0], res[1], np.asarray(rgb, np.float32), np.float32(d))

    paint([st for st in strands if st[0] < _SUBJECT_D[1]])

    # Near subject: the cat in an elliptical cut-out, a gentle dome of disparity.
    ea = min(0.17 * W, 0.255 * H)
    ex, ey, eb = 0.70 * W, 0.58 * H, 1.18 * ea
    box = _bbox(ex - ea - 1, ey - eb - 1, ex + ea + 1, ey + eb + 1, W, H)
    if box is not None:
        sl, bx, by = box
        tx0, ty0 = int(math.floor(ex - ea - 1)), int(math.floor(ey - eb - 1))
        th, tw = int(math.ceil(ey + eb + 1)) + 1 - ty0, int(math.ceil(ex + ea + 1)) + 1 - tx0
        cat = _cover(_linear(skdata.chelsea()[:, 60:420]), th, tw)
        rgb = cat[sl[0].start - ty0:sl[0].stop - ty0, sl[1].start - tx0:sl[1].stop - tx0]
        nx_, ny_ = (bx - ex) / ea, (by - ey) / eb
        q = np.hypot(nx_, ny_)
        grad = np.hypot(nx_ / ea, ny_ / eb) / np.maximum(q, 1e-6)
        a = np.clip(0.5 - (q - 1.0) / np.maximum(grad, 1e-6), 0.0, 1.0)
        d = _SUBJECT_D[0] + (_SUBJECT_D[1] - _SUBJECT_D[0]) * np.minimum(q, 1.0) ** 2
        _over(img, disp, sl, a, rgb, d)

    paint([st for st in strands if st[0] >= _SUBJECT_D[1]])

    img = np.ascontiguousarray(np.maximum(img, 0.0), dtype=np.float32)
    disp = np.ascontiguousarray(np.clip(disp, 0.0, 1.0), dtype=np.float32)
    focus_near = _SUBJECT_D[0]
    max_dev = max(float(np.abs(disp - f).max()) for f in (focus_near, _FOCUS_FAR))
    k_px = _MAX_COC_PX * s / max(max_dev, 1e-6)
    desc = (
        "bokehray demo: dusk launch pad on a tilted plane (d 0.00-0.20) with fairy lights "
        "(radiance 5-20); brick panel with a printed notice (d 0.45-0.55); wires and grass "
        "blades 0.4-3 px wide (d 0.70-0.84 and 0.95-1.00); cat in an elliptical cut-out "
        f"(d 0.92 centre, 0.86 rim). focus_near={focus_near:.2f}, focus_far={_FOCUS_FAR:.2f}, K={k_px:.2f} px."
    )
    return DemoScene(img, disp, focus_near, _FOCUS_FAR, float(k_px), desc)


def _label(text: str, width: int, height: int, fg: str, bg: str) -> np.ndarray:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width / 100, height / 100), dpi=100, facecolor=bg)
    canvas = FigureCanvasAgg(fig)
    fig.text(0.5, 0.5, text, ha="center", va="center", color=fg, fontsize=max(6.0, min(11.0, width / 30)))
    canvas.draw()
    return np.asarray(canvas.buffer_rgba())[:height, :width, :3].copy()


def contact_sheet(
    images: list[np.ndarray], labels: list[str], *, columns: int = 4, tile_width: int = 384
) -> np.ndarray:
    """Lay out linear images as a labelled grid for viewing.

    Each image is clipped to [0, 1], resized to ``tile_width`` keeping its aspect
    (in linear light), sRGB-encoded, and placed in a grid cell with its label
    underneath. Cells are as tall as the tallest tile.

    Args:
        images: scene-linear H x W x 3 images.
        labels: one label per image.
        columns: maximum number of tiles per row.
        tile_width: width of every tile in pixels.

    Returns:
        uint8 sRGB array of shape (rows * (tile_h + 26) + (rows + 1) * 8,
        cols * tile_width + (cols + 1) * 8, 3).

    Raises:
        InputError: on an empty list, mismatched labels or a non-RGB image.
    """
    if len(images) == 0 or len(images) != len(labels):
        raise InputError(
            f"contact sheet: expected as many labels as images (>= 1), got {len(images)} and {len(labels)}"
        )
    if columns < 1 or tile_width < 8:
        raise InputError(f"contact sheet: expected columns >= 1 and tile_width >= 8, got {columns} and {tile_width}")
    tiles = []
    for i, im in enumerate(images):
        im = np.asarray(im, dtype=np.float32)
        if im.ndim != 3 or im.shape[2] != 3:
            raise InputError(f"contact sheet image {i}: expected H x W x 3, got shape {im.shape}")
        im = np.clip(np.nan_to_num(im, nan=0.0, posinf=1.0, neginf=0.0), 0.0, 1.0)
        th = max(round(tile_width * im.shape[0] / im.shape[1]), 1)
        im = np.clip(resize(im, (th, tile_width, 3), order=1, anti_aliasing=True), 0.0, 1.0)
        from ..colour import linear_to_srgb

        tiles.append(np.round(linear_to_srgb(im).astype(np.float64) * 255.0).astype(np.uint8))
    cols = min(columns, len(tiles))
    rows = math.ceil(len(tiles) / cols)
    cell_h = max(t.shape[0] for t in tiles) + SHEET_LABEL_H
    sheet = np.full((rows * cell_h + (rows + 1) * SHEET_GAP, cols * tile_width + (cols + 1) * SHEET_GAP, 3), 24, np.uint8)
    for i, (tile, text) in enumerate(zip(tiles, labels)):
        r, c = divmod(i, cols)
        y, x = SHEET_GAP + r * (cell_h + SHEET_GAP), SHEET_GAP + c * (tile_width + SHEET_GAP)
        sheet[y:y + tile.shape[0], x:x + tile_width] = tile
        ly = y + cell_h - SHEET_LABEL_H
        sheet[ly:ly + SHEET_LABEL_H, x:x + tile_width] = _label(str(text), tile_width, SHEET_LABEL_H, "#e6e6e6", "#181818")
    return sheet
