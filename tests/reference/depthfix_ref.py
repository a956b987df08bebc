"""Slow obvious reference of ``bokehray_refiner.depthfix``: pair by pair, pixel by pixel, in float64.

Only the smoothing filters come from SciPy (the disparity's Gaussian and Sobel for the edge normal, the
Gaussian of the normalised convolution along the edge); sampling, colour steps, scores, painting, the
smeared-edge test and the vote are written out as loops.
"""

from __future__ import annotations

import math

import numpy as np
from bokehray_refiner.depthfix import DepthFixOptions
from scipy import ndimage

from .matting_ref import ramp_width_ref

DEFAULT = DepthFixOptions()


def edge_pairs_ref(coc, jump_px):
    h, w = coc.shape
    out = []
    for ax in (0, 1):
        ys, xs = [], []
        for y in range(h - (ax == 0)):
            for x in range(w - (ax == 1)):
                ny, nx = y + (ax == 0), x + (ax == 1)
                if abs(float(coc[y, x]) - float(coc[ny, nx])) > jump_px:
                    ys.append(y)
                    xs.append(x)
        out.append((np.array(ys, np.int64), np.array(xs, np.int64), ax))
    return out


def bilinear(ch, y, x):
    """``scipy.ndimage.map_coordinates(order=1, mode="nearest")`` at one point, by hand."""
    h, w = ch.shape
    y, x = min(max(y, 0.0), h - 1.0), min(max(x, 0.0), w - 1.0)
    y0, x0 = int(math.floor(y)), int(math.floor(x))
    y1, x1 = min(y0 + 1, h - 1), min(x0 + 1, w - 1)
    fy, fx = y - y0, x - x0
    return ((1 - fy) * (1 - fx) * ch[y0, x0] + (1 - fy) * fx * ch[y0, x1] + fy * (1 - fx) * ch[y1, x0]
            + fy * fx * ch[y1, x1])


def colour_edge_offsets_ref(focus, disparity, pairs, radius_px):
    d = ndimage.gaussian_filter(disparity.astype(np.float32), 1.0)
    gy, gx = ndimage.sobel(d, 0), ndimage.sobel(d, 1)
    n_steps = int(round(2 * radius_px / 0.5)) + 1
    steps = [-radius_px + 0.5 * i for i in range(n_steps)]
    offs = [t - 0.5 for t in steps] + [steps[-1] + 0.5]
    chans = [focus[..., c].astype(np.float32).astype(np.float64) for c in range(3)]
    rows = []
    for ys, xs, axis in pairs:
        for y, x in zip(ys, xs):
            y, x = int(y), int(x)
            ny, nx = y + (axis == 0), x + (axis == 1)
            sign = 1.0 if disparity[ny, nx] >= disparity[y, x] else -1.0
            my, mx = y + (0.5 if axis == 0 else 0.0), x + (0.5 if axis == 1 else 0.0)
            gyy, gxx = (float(gy[y, x]) + float(gy[ny, nx])) / 2, (float(gx[y, x]) + float(gx[ny, nx])) / 2
            along = gyy if axis == 0 else gxx
            nn = math.hypot(gyy, gxx)
            if nn <= 1e-12 or along * sign <= 0:
                uy, ux = (sign, 0.0) if axis == 0 else (0.0, sign)
            else:
                uy, ux = gyy / nn, gxx / nn
            cols = [[bilinear(c, my + o * uy, mx + o * ux) for c in chans] for o in offs]
            step = [math.dist(cols[i + 1], cols[i]) for i in range(n_steps)]
            on = max(s for t, s in zip(steps, step) if abs(t) <= 0.5 + 1e-6)
            row = [my, mx, uy, ux]

            def colour(pos, cols=cols):
                j = min(max(int(np.rint((pos - offs[0]) / 0.5)), 0), len(offs) - 1)
                return cols[j]

            for lo, hi, sg in ((-1e9, 0.5 + 1e-6, -1.0), (-0.5 - 1e-6, 1e9, 1.0)):
                side = [(t, s) for t, s in zip(steps, step) if lo <= t <= hi]
                best = max(s for _, s in side)
                t_best = next(t for t, s in side if s == best)
                mid = colour(t_best * 0.5)
                score = math.dist(mid, colour(t_best + sg)) - math.dist(mid, colour(-sg))
                row += [t_best, on / max(best, 1e-12), best, score]
            rows.append(row)
    return np.array(rows, np.float64).reshape(-1, 12)


def untrusted_ref(focus, disparity, k_px, options=DEFAULT):
    h, w = disparity.shape
    masks = (np.zeros((h, w), bool), np.zeros((h, w), bool))
    pairs = edge_pairs_ref(np.float32(k_px) * disparity, options.jump_px)
    rows = colour_edge_offsets_ref(focus, disparity, pairs, options.band_px)
    if rows.shape[0] == 0:
        return masks
    iy = [min(max(int(math.floor(r[0])), 0), h - 1) for r in rows]
    ix = [min(max(int(math.floor(r[1])), 0), w - 1) for r in rows]

    def smooth(v, wt):
        num, den = np.zeros((h, w)), np.zeros((h, w))
        for y, x, a, b in zip(iy, ix, v, wt):
            num[y, x] += a * b
            den[y, x] += b
        num = ndimage.gaussian_filter(num, options.sigma_edge_px)
        den = ndimage.gaussian_filter(den, options.sigma_edge_px)
        return [num[y, x] / max(den[y, x], 1e-12) for y, x in zip(iy, ix)]

    ones = [1.0] * len(rows)
    score = (smooth(rows[:, 7], ones), smooth(rows[:, 11], ones))
    for k in (0, 1):
        t, ratio, strength = rows[:, 4 + 4 * k], rows[:, 5 + 4 * k], rows[:, 6 + 4 * k]
        r_s = smooth([r if s >= options.min_step else 1.0 for r, s in zip(ratio, strength)], ones)
        act = [s >= options.min_step and r < options.max_ratio and score[k][i] > options.min_score
               and score[k][i] > score[1 - k][i] for i, (s, r) in enumerate(zip(strength, r_s))]
        if not any(act):
            continue
        t_s = smooth(t, [float(a) for a in act])
        for i, row in enumerate(rows):
            if not act[i] or abs(t_s[i]) < 0.75:
                continue
            sg = 1.0 if t_s[i] > 0 else -1.0
            s = 0.5
            while s <= options.band_px + 0.5 + 1e-9:
                if s <= abs(t_s[i]) + 0.5:
                    y = min(max(int(np.rint(row[0] + sg * s * row[2])), 0), h - 1)  # nearest pixel centre
                    x = min(max(int(np.rint(row[1] + sg * s * row[3])), 0), w - 1)
                    masks[k][y, x] = True
                s += 0.5
    return masks


def smeared_ref(disparity, k_px, options=DEFAULT):
    h, w = disparity.shape
    r = int(options.ramp_px)
    snap = options.snap_px / float(k_px)
    out = np.zeros((h, w), bool)
    for y in range(h):
        for x in range(w):
            win = disparity[max(y - r, 0):y + r + 1, max(x - r, 0):x + r + 1]
            d = disparity[y, x]
            out[y, x] = (win.max() - d > snap) and (d - win.min() > snap)
    return out


def weighted_median_ref(values, weights):
    pairs = sorted(zip(values, weights), key=lambda p: p[0])
    total = sum(wt for _, wt in pairs)
    if total <= 0:
        return math.nan
    acc = 0.0
    for v, wt in pairs:
        acc += wt
        if acc >= 0.5 * total:
            return v
    return pairs[-1][0]


def _classes_ref(img, cur, sus, keep, y, x, snap, options):
    """The window of pixel ``(y, x)``: per class (far, own, near), the trusted voters' spatial weight, colour weight
    and ``(value, colour weight)`` pairs."""
    h, w = cur.shape
    r = int(math.floor(options.radius_px))
    s = max(1, int(options.step_px))
    seen, simil, vals = [0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [[], [], []]
    for dy in range(-(r // s) * s, r + 1, s):
        for dx in range(-(r // s) * s, r + 1, s):
            qy, qx = y + dy, x + dx
            if dy * dy + dx * dx > options.radius_px ** 2 or not (0 <= qy < h and 0 <= qx < w):
                continue
            if sus[qy, qx] or (keep is not None and keep[qy, qx]):
                continue
            rel = float(cur[qy, qx]) - float(cur[y, x])
            if math.isnan(rel):  # a pixel without a disparity is of no class
                continue
            sp = math.exp(-(dy * dy + dx * dx) / (2 * options.sigma_space_px ** 2))
            dc2 = sum((float(img[qy, qx, c]) - float(img[y, x, c])) ** 2 for c in range(3))
            wt = sp * math.exp(-dc2 / (2 * options.sigma_colour ** 2))
            c = 0 if rel < -snap else (2 if rel > snap else 1)
            seen[c] += sp
            simil[c] += wt
            vals[c].append((float(cur[qy, qx]), wt))
    return seen, simil, vals


def vote_ref(img, cur, sus, snap, options, new, keep=None, one_sided=False):
    h, w = cur.shape
    for y in range(h):
        for x in range(w):
            if not sus[y, x] or (keep is not None and keep[y, x]):
                continue
            seen, simil, vals = _classes_ref(img, cur, sus, keep, y, x, snap, options)
            known = [sv >= options.min_class for sv in seen]
            aff = [simil[c] / max(seen[c], 1e-300) if known[c] else 0.0 for c in range(3)]
            best = 0 if aff[0] >= aff[2] else 2
            rest = max(aff[1], aff[2 - best])
            two_sided = known[1] or (known[0] and known[2]) or one_sided
            if not (two_sided and known[best] and aff[best] >= options.contrast * rest
                    and aff[best] >= options.min_affinity):
                continue
            med = weighted_median_ref([v for v, _ in vals[best]], [wt for _, wt in vals[best]])
            if not math.isnan(med):
                new[y, x] = med


def global_shift_ref(focus, disparity, k_px, options=DEFAULT):  # noqa: C901
    """Pair by pair, shift by shift: the four groups (axis x side of the near pixel), their mean colour step across
    each shifted pair, the geometric mean's best shift and its three checks."""
    m = int(options.max_shift_px)
    h, w = disparity.shape
    if m <= 0 or h <= 2 * m + 1 or w <= 2 * m + 1:
        return 0, 0
    coc = np.float32(k_px) * np.asarray(disparity, np.float32)
    groups = {(ax, side): [] for ax in (0, 1) for side in (True, False)}
    for ax in (0, 1):
        for y in range(m, h - 1 - m):
            for x in range(m, w - 1 - m):
                ny, nx = y + (ax == 0), x + (ax == 1)
                a, b = float(coc[y, x]), float(coc[ny, nx])
                if abs(a - b) > options.jump_px:
                    groups[(ax, b > a)].append((y, x))
    keys = [(0, True), (0, False), (1, True), (1, False)]
    for k in keys:
        if len(groups[k]) > 20000:
            step = -(-len(groups[k]) // 20000)
            groups[k] = groups[k][::step]
    if min(len(groups[k]) for k in keys) < options.min_shift_pairs:
        return 0, 0
    n = 2 * m + 1
    prof = {}
    for k in keys:
        ax = k[0]
        for sy in range(-m, m + 1):
            for sx in range(-m, m + 1):
                tot = 0.0
                for y, x in groups[k]:
                    y0, x0 = y + sy, x + sx
                    y1, x1 = y0 + (ax == 0), x0 + (ax == 1)
                    tot += math.sqrt(sum((float(focus[y1, x1, c]) - float(focus[y0, x0, c])) ** 2 for c in range(3)))
                prof[(k, sy, sx)] = tot / len(groups[k])
    score = {(sy, sx): math.exp(sum(math.log(max(prof[(k, sy, sx)], 1e-12)) for k in keys) / 4)
             for sy in range(-m, m + 1) for sx in range(-m, m + 1)}
    best = max(score, key=lambda s: (score[s], -((s[0] + m) * n + s[1] + m)))  # the first maximum, row-major
    if best == (0, 0):
        return 0, 0
    for k in keys:
        gain = prof[(k, *best)] / max(prof[(k, 0, 0)], 1e-12)
        if gain < 1.0 or (best[k[0]] != 0 and gain < options.shift_gain):
            return 0, 0
        if best[k[0]] != 0:
            own = {s: prof[(k, *s)] for s in score}
            peak = max(own, key=lambda s: (own[s], -((s[0] + m) * n + s[1] + m)))
            if abs(peak[k[0]] - best[k[0]]) > 1:
                return 0, 0
    return best


def correct_disparity_ref(focus, disparity, k_px, options=DEFAULT, active=None, keep=None):
    d = np.asarray(disparity, np.float32)
    out = d.copy()
    if not options.enabled or k_px <= 0:
        return out
    img = np.asarray(focus[..., :3], np.float32)
    snap = options.snap_px / float(k_px)
    sy, sx = global_shift_ref(img, d, k_px, options) if active is None else (0, 0)
    if sy or sx:  # the map moved by (sy, sx), its border continued
        out = np.array([[d[min(max(y - sy, 0), d.shape[0] - 1), min(max(x - sx, 0), d.shape[1] - 1)]
                         for x in range(d.shape[1])] for y in range(d.shape[0])], np.float32)
    # the smeared-edge hypothesis only on a map with ramps (the matting's measure, on the map as given)
    ramps = not options.ramps_only or ramp_width_ref(np.float32(k_px) * out, options.jump_px, options.max_ramp_px) > 0
    for _ in range(max(1, options.iterations)):
        cur = out
        new = cur.copy()
        hyps = list(untrusted_ref(img, cur, k_px, options))
        if options.ramp_px > 0 and ramps:
            hyps.append(smeared_ref(cur, k_px, options))
        for i, sus in enumerate(hyps):
            if active is not None:
                sus = sus & active
            vote_ref(img, cur, sus, snap, options, new, keep, one_sided=options.thin_dilated and i == 1)
        if (new == cur).all():
            break
        out = new
    return out
