"""Slow, obvious float64 references for ``bokehray.matting`` and ``bokehray_kernels.matting``: one pixel at a
time, plain loops."""

import math

import numpy as np


def ramp_width_ref(coc: np.ndarray, jump_px: float, cap: int) -> int:
    """Walk every row and column; every step above ``jump_px`` gets the length of its run of consecutive
    same-sign steps; the 90th percentile minus one, at most ``cap``."""
    lengths = []
    h, w = coc.shape
    lines = [coc[y, :] for y in range(h)] + [coc[:, x] for x in range(w)]
    for line in lines:
        steps = [float(line[i + 1]) - float(line[i]) for i in range(len(line) - 1)]
        sgn = [1 if v > jump_px else (-1 if v < -jump_px else 0) for v in steps]
        i = 0
        while i < len(sgn):
            if sgn[i] == 0:
                i += 1
                continue
            j = i
            while j + 1 < len(sgn) and sgn[j + 1] == sgn[i]:
                j += 1
            lengths += [j - i + 1] * (j - i + 1)
            i = j + 1
    if not lengths:
        return 0
    return int(min(cap, max(0, int(np.percentile(np.array(lengths), 90)) - 1)))


def band_pixel_ref(image, coc, unknown, y, x, offsets, weights, jump_px, unknown_weight, ridge, purity,
                   light_level=1.0, light_ratio=1.2, light_reach=0, light_thin=0.35, light_share=0.25):
    """The matting of one band pixel, as the kernel's docstring states it: returns (alpha, F, B, var F, var B,
    near CoC, far CoC, ok, own_near). ``light_*``: a light behind the near side (``MattingRule``; reach 0: off)."""
    h, w = coc.shape
    win = []
    for (dy, dx), g in zip(offsets, weights):
        yy, xx = y + int(dy), x + int(dx)
        if 0 <= yy < h and 0 <= xx < w:
            win.append((float(g), image[yy, xx].astype(np.float64), float(coc[yy, xx]), bool(unknown[yy, xx])))
    hi = max(v for _, _, v, _ in win)
    lo = min(v for _, _, v, _ in win)
    mid = 0.5 * (hi + lo)
    wts = np.array([g * (unknown_weight if u else 1.0) for g, _, _, u in win])
    cols = np.array([c for _, c, _, _ in win])
    ys = np.array([1.0 if v > mid else 0.0 for _, _, v, _ in win])
    wn = wts / max(wts.sum(), 1e-30)
    mu = (wn[:, None] * cols).sum(0)
    my = (wn * ys).sum()
    cov = sum(wn[k] * np.outer(cols[k] - mu, cols[k] - mu) for k in range(len(win)))
    cy = sum(wn[k] * (ys[k] - my) * (cols[k] - mu) for k in range(len(win)))
    eps = ridge * ridge * (float(mu @ mu) / 3.0 + 1e-8)
    wv = np.linalg.solve(cov + eps * np.eye(3), cy)
    alpha = min(1.0, max(0.0, my + float((image[y, x] - mu) @ wv)))
    sums = {"f": [0.0, np.zeros(3), np.zeros(3)], "b": [0.0, np.zeros(3), np.zeros(3)]}
    best = {"f": 0.0, "b": 0.0}
    for g, c, v, _ in win:
        aq = min(1.0, max(0.0, my + float((c - mu) @ wv)))
        side, wt = ("f", g * aq ** purity) if v > mid else ("b", g * (1.0 - aq) ** purity)
        sums[side][0] += wt
        sums[side][1] = sums[side][1] + wt * c
        sums[side][2] = sums[side][2] + wt * c * c
        best[side] = max(best[side], wt)
    out = []
    for side in ("f", "b"):
        sw = max(sums[side][0], 1e-30)
        mean = sums[side][1] / sw
        out.append((mean, np.maximum(sums[side][2] / sw - mean * mean, 0.0)))
    ok = (hi - lo) > jump_px and best["f"] > 0.0 and best["b"] > 0.0
    own_near = float(coc[y, x]) > mid
    own = image[y, x].astype(np.float64)
    brighter = float(own.sum()) > max(3.0 * light_level, light_ratio * max(float(out[0][0].sum()), float(out[1][0].sum())))
    if light_reach > 0 and best["b"] > 0.0 and own_near and brighter:
        lit = _lit_far_ref(image, coc, y, x, mid, purity)  # near, brighter than both parts: a light behind, B the dark side's
        if lit is not None and float(lit[0].sum()) > float(own.sum()):
            out[1] = lit
            fb = out[0][0] - lit[0]
            alpha = min(1.0, max(0.0, float((own - lit[0]) @ fb) / max(float(fb @ fb), 1e-30)))
    fb_light = _light_behind(image, coc, y, x, offsets, weights, mid, mu, my, wv, purity, out[0][0], out[1][0],
                             light_level, light_ratio, light_reach, light_share) if light_reach > 0 and ok and my < light_thin else None
    if fb_light is not None:
        (mean_f, var_f), alpha = fb_light
        out[0] = (mean_f, var_f)
    return alpha, out[0][0], out[1][0], out[0][1], out[1][1], hi, lo, ok, own_near


def _lit_far_ref(image, coc, y, x, mid, purity, reach=4):
    """The far samples within ``reach`` px of (y, x) (a square), each weighted by its summed RGB over the brightest
    one's, to the power ``purity``: (mean, variance), or None without far samples."""
    h, w = coc.shape
    far = [image[yy, xx].astype(np.float64) for yy in range(max(y - reach, 0), min(y + reach + 1, h))
           for xx in range(max(x - reach, 0), min(x + reach + 1, w)) if float(coc[yy, xx]) <= mid]
    top = max((float(c.sum()) for c in far), default=0.0)
    pairs = [((float(c.sum()) / max(top, 1e-30)) ** purity, c) for c in far]
    sw = sum(wt for wt, _ in pairs)
    if not far or sw <= 0.0:
        return None
    mean = sum((wt * c for wt, c in pairs), np.zeros(3)) / max(sw, 1e-30)
    return mean, np.maximum(sum((wt * c * c for wt, c in pairs), np.zeros(3)) / max(sw, 1e-30) - mean * mean, 0.0)


def _light_behind(image, coc, y, x, offsets, weights, mid, mu, my, wv, purity, mf, mb, light_level, light_ratio,
                  reach, light_share):
    """A far side brighter than ``light_level`` (mean of RGB) and ``light_ratio`` times F (summed RGB) is a light
    behind the near side. Over the window and the full grid out to ``reach`` px beyond it (at the window's smallest
    weight): the unlit background D (far samples weighted by ``(1 - l)^purity``, ``l`` the projection on B); F0, the
    near samples weighted by ``(alpha (1 - l)^2)^purity``; F, the near samples weighted by ``(alpha (1 - l)^2
    t)^purity``, ``t`` the place from D towards F0 clipped to [0, 1.5]; alpha the pixel's place on the line from B to
    F; F is the strand's colour from its cross-sections where they measure it (:func:`_strand_colour_ref`). Returns
    ((F, var F), alpha), alpha with a measured F at most what the strand's width leaves the pixel
    (:func:`_cover_left_ref`) where it exceeds that by over 0.4 (darker than the strand can make it: the light's
    rim); None when no light, or, without a measurement, where the window's F holds at most ``light_share`` more of
    the light's colour than that F."""
    if not (float(mb.sum()) > 3.0 * light_level and float(mb.sum()) > light_ratio * float(mf.sum())):
        return None
    h, w = coc.shape
    bb = max(float(mb @ mb), 1e-30)
    samples = [(float(g), int(dy), int(dx)) for (dy, dx), g in zip(offsets, weights)]
    r_in = float(offsets[-1][0]) ** 2 + float(offsets[-1][1]) ** 2
    samples += [(float(weights[-1]), gy, gx) for gy in range(-reach, reach + 1) for gx in range(-reach, reach + 1)
                if r_in < gy * gy + gx * gx <= reach * reach]
    near, far = [], []
    for g, dy, dx in samples:
        yy, xx = y + dy, x + dx
        if 0 <= yy < h and 0 <= xx < w:
            c = image[yy, xx].astype(np.float64)
            lq = min(1.0, max(0.0, float(c @ mb) / bb))
            if float(coc[yy, xx]) > mid:
                near.append((g, c, lq, min(1.0, max(0.0, my + float((c - mu) @ wv)))))
            else:
                far.append((g, c, lq))

    def mean(pairs):
        sw = sum(wt for wt, _ in pairs)
        return sum((wt * c for wt, c in pairs), np.zeros(3)) / max(sw, 1e-30)

    d = mean([(g * (1 - lq) ** purity, c) for g, c, lq in far])
    fd = mean([(g * (aq * (1 - lq) ** 2) ** purity, c) for g, c, lq, aq in near]) - d
    ff = max(float(fd @ fd), 1e-30)
    pairs = [(g * (aq * (1 - lq) ** 2 * min(1.5, max(0.0, float((c - d) @ fd) / ff))) ** purity, c)
             for g, c, lq, aq in near]
    sw = max(sum(wt for wt, _ in pairs), 1e-30)
    f = sum((wt * c for wt, c in pairs), np.zeros(3)) / sw
    var = np.maximum(sum((wt * c * c for wt, c in pairs), np.zeros(3)) / sw - f * f, 0.0)
    across = _strand_colour_ref(image, coc, y, x, samples, mid, mb)
    if across is not None:
        f, width, (ey, ex) = across
        left = _cover_left_ref(image, coc, y, x, ey, ex, mid, mb, f, width)
        # measured: it is F (the variance stays the unlit samples' spread, now about it)
    elif float((mf - f) @ mb) / bb <= light_share:
        return None  # the window's F holds hardly more of the light than the unlit one: it stays
    fb = f - mb
    alpha = min(1.0, max(0.0, float((image[y, x] - mb) @ fb) / max(float(fb @ fb), 1e-30)))
    if across is not None and alpha > left + 0.4:
        alpha = left  # darker than the strand of that width can make it: the light is dimmer here (its rim)
    return (f, var), alpha


def _strand_colour_ref(image, coc, y, x, samples, mid, mb):
    """The strand's colour from its cross-sections: the near samples' axis of least spread is the one across the
    strand (columns when they spread more along x); along it, through every near sample with both pixels 2 px away
    inside the image and on the far side, the sum over the sample and its two neighbours of the photo less the line
    between those two ends. Both ends' projections on the light ``mb`` at least 0.75: lit (the sum is ``W (F -
    L)``); both below 0.05: unlit (``W (F - D)``). With both kinds, ``W = (mean unlit - mean lit) . (L - D) / |L -
    D|^2`` (L, D: the mean of the ends' means); F = D + mean unlit / W, clipped at 0, for W in (0.05, 2.5] and
    where (y, x)'s strand is one a cross-section holds (:func:`_narrow_here_ref`): (F, W, the axis); else None."""
    h, w = coc.shape
    bb = max(float(mb @ mb), 1e-30)
    near = [(y + dy, x + dx) for _, dy, dx in samples
            if 0 <= y + dy < h and 0 <= x + dx < w and float(coc[y + dy, x + dx]) > mid]
    along_y = sum((q[0] - y) ** 2 for q in near)
    along_x = sum((q[1] - x) ** 2 for q in near)
    ey, ex = (0, 1) if along_y > along_x else (1, 0)
    kinds = {1: [], -1: []}
    for qy, qx in near:
        y1, x1, y2, x2 = qy - 2 * ey, qx - 2 * ex, qy + 2 * ey, qx + 2 * ex
        if not (0 <= y1 and 0 <= x1 and y2 < h and x2 < w):
            continue
        if float(coc[y1, x1]) > mid or float(coc[y2, x2]) > mid:
            continue
        c1, c2 = image[y1, x1].astype(np.float64), image[y2, x2].astype(np.float64)
        total = np.zeros(3)
        for k in (-1, 0, 1):
            total += image[qy + k * ey, qx + k * ex].astype(np.float64) - (c1 + (k + 2) / 4.0 * (c2 - c1))
        l1, l2 = float(c1 @ mb) / bb, float(c2 @ mb) / bb
        if min(l1, l2) >= 0.75:
            kinds[1].append((total, 0.5 * (c1 + c2)))
        elif max(l1, l2) < 0.05:
            kinds[-1].append((total, 0.5 * (c1 + c2)))
    if not kinds[1] or not kinds[-1] or not _narrow_here_ref(coc, y, x, ey, ex, mid):
        return None
    su, d = (np.mean([v[i] for v in kinds[-1]], 0) for i in (0, 1))
    sl, lt = (np.mean([v[i] for v in kinds[1]], 0) for i in (0, 1))
    ld = lt - d
    if float(ld @ ld) <= 1e-30:
        return None
    width = float((su - sl) @ ld) / float(ld @ ld)
    if not 0.05 < width <= 2.5:
        return None
    return np.maximum(d + su / width, 0.0), width, (ey, ex)


def _cover_left_ref(image, coc, y, x, ey, ex, mid, mb, f, width):
    """What a strand ``width`` px across leaves (y, x) of its cover after the near pixels within 2 px of it along
    (ey, ex) take theirs (each its place on the line from the light ``mb`` to the strand's colour ``f``, clipped to
    [0, 1]), counting only pixels holding at least 0.05 of the light (over an unlit background a pixel's place on
    that line is not its cover); at least 0, and 2 (no bound) where (y, x) itself holds less."""
    if float(image[y, x] @ mb) < 0.05 * float(mb @ mb):
        return 2.0
    h, w = coc.shape
    fb = mb - f
    den = max(float(fb @ fb), 1e-30)
    taken = 0.0
    for k in (-2, -1, 1, 2):
        qy, qx = y + k * ey, x + k * ex
        lit = 0 <= qy < h and 0 <= qx < w and float(image[qy, qx] @ mb) >= 0.05 * float(mb @ mb)
        if lit and float(coc[qy, qx]) > mid:
            taken += min(1.0, max(0.0, float((mb - image[qy, qx]) @ fb) / den))
    return max(width - taken, 0.0)


def _narrow_here_ref(coc, y, x, ey, ex, mid):
    """False where a near pixel of (y, x)'s 3 x 3 has a near pixel 2 px either side of it along (ey, ex): the strand
    there is wider than a cross-section (or another near object is beside it), not what the cross-sections
    measured."""
    h, w = coc.shape
    for qy in range(y - 1, y + 2):
        for qx in range(x - 1, x + 2):
            if not (0 <= qy < h and 0 <= qx < w) or float(coc[qy, qx]) <= mid:
                continue
            for s in (-2, 2):
                ye, xe = qy + s * ey, qx + s * ex
                if 0 <= ye < h and 0 <= xe < w and float(coc[ye, xe]) > mid:
                    return False
    return True


def gaussian_weights(dist: np.ndarray, radius: int) -> np.ndarray:
    sigma = 0.5 * radius
    return np.array([math.exp(-(d * d) / (2.0 * sigma * sigma)) for d in dist])


def fuse_alpha_ref(alpha, image, fg, bg, var_f, var_b, model_sd):
    """Pixel by pixel: the model's alpha and the projection of the colour on the F-B line, each weighted by the
    inverse of its variance (the model's ``model_sd^2``; the projection's the spread of F and B carried through
    it), clipped to [0, 1]."""
    out = []
    for a, c, f, b, vf, vb in zip(alpha, image, fg, bg, var_f, var_b):
        a = float(a)
        d = [float(f[k]) - float(b[k]) for k in range(3)]
        den = max(sum(x * x for x in d), 1e-30)
        proj = sum((float(c[k]) - float(b[k])) * d[k] for k in range(3)) / den
        vp = (a * a * sum(float(v) for v in vf) + (1 - a) ** 2 * sum(float(v) for v in vb)) / den
        vm = model_sd * model_sd
        out.append(min(1.0, max(0.0, (a * vp + proj * vm) / (vp + vm))))
    return np.array(out)
