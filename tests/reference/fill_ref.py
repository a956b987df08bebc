"""Slow, obvious float64 NumPy references for the hidden-region fill kernels (``bokehray_kernels.fill``).

Written from the kernels' docstrings and docs/renderer.md ("hidden-region fill"), one function
per kernel with the kernel's arguments in NumPy form, plus :func:`layer_fill`, which composes
them in the order the preview launcher uses (layer sources -> pull levels -> push levels ->
distances -> fill sources). Plain loops over pixels; the distance gate also has a brute-force
form (:func:`l1_distance`: the minimum over every pixel of the layer) to check the two-pass
transform against.

Conventions (docs/renderer.md):

- Slice ids grow towards the camera; ``-1`` marks an inactive (copied) pixel. A pixel is *of
  the layer* when its id equals the layer, *visible* ("known": the photo shows this layer or
  something behind it) when ``0 <= id <= layer``, *hidden* when its id is larger (a nearer
  layer covers it).
- Colour is pull-pushed in tone-mapped form ``t = c / (1 + c)``, back with ``c = t / (1 - t)``;
  the 4th channel of the pyramid is the signed CoC.
- A pyramid level holds sums over its footprint: ``total`` (tone-mapped RGB, signed CoC) and
  ``weight`` over the layer's pixels, ``known`` the count of visible pixels. Pushing turns them
  into a mean ``value``, a ``density`` (share of the visible pixels that are the layer's) and
  ``has`` (1 where the density is known), each taken from the next coarser level, sampled
  bilinearly at the pixel's centre, where the level itself has nothing.

Arrays: ``image`` H x W x 3, ``signed_coc`` and ``slice_id`` H x W (the whole frame); the layer
works on a local window of ``h x w`` pixels whose top-left corner is ``(y0, x0)`` in the frame.
"Nothing of the layer in reach" is an infinite distance here (the kernels use about 1e9).
"""

from __future__ import annotations

import math

import numpy as np

SQRT2 = math.sqrt(2.0)
#: A hidden pixel whose extrapolated density is below this share gets no filled source
#: (design.md: "snap tiny slice shares (< ~0.02)"); from fill_sources_kernel, not in its docstring.
MIN_FILL_DENSITY = 0.02
#: The largest tone-mapped value brought back (t = 1 is infinite radiance): c <= 999999.
MAX_TONEMAPPED = 0.999999


def tonemap(c):
    """``c / (1 + c)`` for radiance ``c >= 0``.

    Negative (out-of-gamut) radiance is not covered by the docs; the kernels keep it as it is
    (``c / (1 + max(c, 0))``), which this reference copies so the two can be compared there too.
    """
    t = np.array(c, np.float64)
    pos = t >= 0.0
    t[pos] = t[pos] / (1.0 + t[pos])
    return t


def untonemap(t):
    """Inverse of :func:`tonemap` on ``[0, MAX_TONEMAPPED]``; values outside are first clamped into it."""
    t = np.clip(np.asarray(t, np.float64), 0.0, MAX_TONEMAPPED)
    return t / (1.0 - t)


def bilinear_taps(fy: float, fx: float, h: int, w: int) -> list[tuple[int, int, float]]:
    """The (row, column, weight) taps of bilinear interpolation at texel-centre coordinates (fy, fx).

    The point is first clamped into the rectangle of texel centres ``[0, h-1] x [0, w-1]``
    (clamp to edge); the weights sum to 1.
    """
    fy = min(max(fy, 0.0), h - 1.0)
    fx = min(max(fx, 0.0), w - 1.0)
    ya, xa = int(math.floor(fy)), int(math.floor(fx))
    yb, xb = min(ya + 1, h - 1), min(xa + 1, w - 1)
    ty, tx = fy - ya, fx - xa
    return [(ya, xa, (1 - ty) * (1 - tx)), (ya, xb, (1 - ty) * tx), (yb, xa, ty * (1 - tx)), (yb, xb, ty * tx)]


# --- one function per kernel -----------------------------------------------------------------


def layer_sources(image, signed_coc, slice_id, layer: int, x0: int, y0: int, h: int, w: int, with_fill: bool):
    """``layer_sources_kernel`` on the ``h x w`` window at ``(y0, x0)``.

    Returns ``(src, coc, total, weight, known)``: sources ``(RGB, 1)`` and the signed CoC on the
    layer's pixels, zero elsewhere; with ``with_fill`` also level 0 of the pull-push pyramid
    (tone-mapped RGB and signed CoC with weight 1 on the layer's pixels, ``known = 1`` on the
    visible ones), else ``None`` for those three.
    """
    image = np.asarray(image, np.float64)
    signed_coc = np.asarray(signed_coc, np.float64)
    src = np.zeros((h, w, 4))
    coc = np.zeros((h, w))
    total = np.zeros((h, w, 4))
    weight = np.zeros((h, w))
    known = np.zeros((h, w))
    for y in range(h):
        for x in range(w):
            sid = int(slice_id[y + y0, x + x0])
            if 0 <= sid <= layer:
                known[y, x] = 1.0
            if sid == layer:
                c = image[y + y0, x + x0]
                s = signed_coc[y + y0, x + x0]
                src[y, x] = [c[0], c[1], c[2], 1.0]
                coc[y, x] = s
                total[y, x] = [*tonemap(c), s]
                weight[y, x] = 1.0
    if not with_fill:
        return src, coc, None, None, None
    return src, coc, total, weight, known


def pull(fine_total, fine_weight, fine_known):
    """``pull_kernel``: each coarse pixel sums its (up to) 2 x 2 children; odd sizes round up.

    Returns ``(total, weight, known)`` of shape ``(ceil(h / 2), ceil(w / 2))``.
    """
    fine_total = np.asarray(fine_total, np.float64)
    h, w = fine_weight.shape
    ch, cw = (h + 1) // 2, (w + 1) // 2
    total = np.zeros((ch, cw, 4))
    weight = np.zeros((ch, cw))
    known = np.zeros((ch, cw))
    for y in range(ch):
        for x in range(cw):
            for fy in (2 * y, 2 * y + 1):
                for fx in (2 * x, 2 * x + 1):
                    if fy < h and fx < w:
                        total[y, x] += fine_total[fy, fx]
                        weight[y, x] += fine_weight[fy, fx]
                        known[y, x] += fine_known[fy, fx]
    return total, weight, known


def push(coarse_value, coarse_density, coarse_has, top: bool, total, weight, known):
    """``push_kernel``: one level's sums -> ``(value, density, has)``.

    - ``value``: the mean ``total / weight`` where the level holds some of the layer
      (``weight > 0``); elsewhere the coarser level's values at this pixel's centre, each
      bilinear tap weighted by how much of the layer it holds (``has * density``).
    - ``density``: ``weight / known`` where the level has visible pixels (``known > 0``), with
      ``has = 1``; elsewhere the coarser densities, taps weighted by ``has`` (and ``has = 1`` if
      any tap has a density).
    - Nothing coarser to ask (``top``, or all taps empty): value 0, density 0, has 0.

    The coarser level is already pushed; pixel ``(y, x)`` has its centre at texel-centre
    coordinates ``((y + 0.5) / 2 - 0.5, (x + 0.5) / 2 - 0.5)`` there.
    """
    coarse_value = np.asarray(coarse_value, np.float64)
    coarse_density = np.asarray(coarse_density, np.float64)
    coarse_has = np.asarray(coarse_has, np.float64)
    total = np.asarray(total, np.float64)
    h, w = weight.shape
    ch, cw = coarse_density.shape
    value = np.zeros((h, w, 4))
    density = np.zeros((h, w))
    has = np.zeros((h, w))
    for y in range(h):
        for x in range(w):
            own = weight[y, x] > 0.0
            visible = known[y, x] > 0.0
            if own:
                value[y, x] = total[y, x] / weight[y, x]
            if visible:
                density[y, x] = weight[y, x] / known[y, x]
                has[y, x] = 1.0
            if top:
                continue
            taps = bilinear_taps((y + 0.5) / 2 - 0.5, (x + 0.5) / 2 - 0.5, ch, cw)
            if not visible:
                wsum = sum(b * coarse_has[cy, cx] for cy, cx, b in taps)
                if wsum > 0.0:
                    density[y, x] = sum(b * coarse_has[cy, cx] * coarse_density[cy, cx] for cy, cx, b in taps) / wsum
                    has[y, x] = 1.0
            if not own:
                wsum = sum(b * coarse_has[cy, cx] * coarse_density[cy, cx] for cy, cx, b in taps)
                if wsum > 0.0:
                    value[y, x] = sum(b * coarse_has[cy, cx] * coarse_density[cy, cx] * coarse_value[cy, cx]
                                      for cy, cx, b in taps) / wsum
    return value, density, has


def row_distance(slice_id, layer: int, x0: int, y0: int, width: int, height: int):
    """``row_distance_kernel``: per window row, |x - x'| to the nearest pixel of the layer in that row.

    ``height`` is the launch dimension (rows of the window). Rows without the layer: infinity.
    """
    dist = np.full((height, width), np.inf)
    for y in range(height):
        cols = [xx for xx in range(width) if slice_id[y + y0, xx + x0] == layer]
        for x in range(width):
            for xx in cols:
                dist[y, x] = min(dist[y, x], abs(x - xx))
    return dist


def column_distance(dist, height: int, band: int):
    """``column_distance_kernel``: ``out[y, x] = min over y' < height of dist[y', x] + |y - y'|``.

    With row distances as input this completes the city-block (L1) distance transform. ``band``
    only groups columns per thread and does not change the result. Rows from ``height`` on are
    neither read nor written.
    """
    src = np.asarray(dist, np.float64)
    out = src.copy()
    rows = np.arange(height)
    for y in range(height):
        # every row y' of the column offers its distance plus the |y - y'| rows between them
        out[y] = np.min(src[:height] + np.abs(rows - y)[:, None], axis=0)
    return out


def l1_distance(slice_id, layer: int, x0: int, y0: int, h: int, w: int):
    """Brute force: city-block distance from each window pixel to the nearest pixel of the layer in the window."""
    ys, xs = np.nonzero(np.asarray(slice_id)[y0:y0 + h, x0:x0 + w] == layer)
    dist = np.full((h, w), np.inf)
    for y in range(h):
        for x in range(w):
            if len(ys):
                dist[y, x] = np.min(np.abs(ys - y) + np.abs(xs - x))
    return dist


def fill_sources(slice_id, layer: int, x0: int, y0: int, fill_value, fill_density, dist_l1, signed_coc,
                 s_lo: float, s_hi: float, src, coc, n_filled):
    """``fill_sources_kernel``: returns updated copies of ``(src, coc, n_filled)``.

    A window pixel gets a filled source when a nearer layer hides it (``slice_id > layer``), its
    extrapolated density is at least :data:`MIN_FILL_DENSITY`, and the hiding pixel is blurred
    enough to reveal it: ``dist_l1 <= sqrt(2) * |signed_coc of the hider| + 1``. The source is
    the filled colour brought back from tone-mapped form, premultiplied by the opacity
    ``a = min(density, 1)``, with coverage ``a``; its signed CoC is the filled one clamped to the
    layer's range ``[s_lo, s_hi]``. ``n_filled[layer]`` counts them. Every other pixel is left alone.
    """
    src = np.array(src, np.float64)
    coc = np.array(coc, np.float64)
    n_filled = np.array(n_filled, np.int64)
    fill_value = np.asarray(fill_value, np.float64)
    h, w = coc.shape
    for y in range(h):
        for x in range(w):
            if slice_id[y + y0, x + x0] <= layer or fill_density[y, x] < MIN_FILL_DENSITY:
                continue
            reach = SQRT2 * abs(float(signed_coc[y + y0, x + x0])) + 1.0
            if dist_l1[y, x] <= reach:
                a = min(float(fill_density[y, x]), 1.0)
                c = untonemap(fill_value[y, x, :3])
                src[y, x] = [c[0] * a, c[1] * a, c[2] * a, a]
                coc[y, x] = min(max(fill_value[y, x, 3], s_lo), s_hi)
                n_filled[layer] += 1
    return src, coc, n_filled


# --- the composition ---------------------------------------------------------------------------


def layer_fill(image, signed_coc, slice_id, layer: int, bbox: tuple[int, int, int, int], s_lo: float, s_hi: float,
               pull_levels: int | None, n_layers: int | None = None) -> dict:
    """One layer's sources on its bounding box ``(y0, y1, x0, x1)``, as the preview launcher builds them.

    ``pull_levels``: levels of the pull-push pyramid above level 0, or ``None`` for no fill.
    Returns ``src``, ``coc``, ``n_filled`` (length ``n_layers``, default ``layer + 1``) and, with
    the fill, the pushed level-0 ``value``, ``density``, ``has`` and the ``distance`` (brute force).
    """
    y0, y1, x0, x1 = bbox
    h, w = y1 - y0, x1 - x0
    n_filled = np.zeros(layer + 1 if n_layers is None else n_layers, np.int64)
    fill = pull_levels is not None
    src, coc, total, weight, known = layer_sources(image, signed_coc, slice_id, layer, x0, y0, h, w, fill)
    out = {"src": src, "coc": coc, "n_filled": n_filled}
    if not fill:
        return out
    levels = [(total, weight, known)]
    for _ in range(pull_levels):
        levels.append(pull(*levels[-1]))
    pushed = None
    for lv in range(len(levels) - 1, -1, -1):
        top = lv == len(levels) - 1
        coarse = pushed if not top else (levels[lv][0], levels[lv][1], levels[lv][2])
        pushed = push(*coarse, top, *levels[lv])
    value, density, has = pushed
    dist = l1_distance(slice_id, layer, x0, y0, h, w)
    src, coc, n_filled = fill_sources(slice_id, layer, x0, y0, value, density, dist, signed_coc, s_lo, s_hi,
                                      src, coc, n_filled)
    out.update(src=src, coc=coc, n_filled=n_filled, value=value, density=density, has=has, distance=dist)
    return out
