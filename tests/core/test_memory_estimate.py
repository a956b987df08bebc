"""The preview's memory estimate on frames whose split pixels dominate: a strip's clamped border replicates its split
pixels by the million, and the plan (``scene.split_scene``) holds more a split pixel than the layers do."""

from __future__ import annotations

import numpy as np
import pytest

import bokehray as br
from bokehray import scene as sc
from bokehray.levels import preview as pv


class _Padded(Exception):
    pass


def _strip(w: int = 3000) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(w)
    return rng.random((2, w, 3)).astype(np.float32), (np.indices((2, w)).sum(0) % 2).astype(np.float32)


def test_a_strip_whose_padded_split_cannot_be_planned_drops_its_border(monkeypatch):
    """A budget the old rule let through (the padded frame's arrays and 76 B a split pixel) but that the plan of the
    padded split exceeds (170 B a split pixel): the clamped border is dropped before it is padded."""
    image, d = _strip()
    blur = br.BlurParams(200.0, 0.5)
    seen = {}
    count = sc.soft_replicas

    def counted(soft, shape, pads):
        n = count(soft, shape, pads)
        seen.update(n=len(soft) + n, px=(shape[0] + pads[0] + pads[1]) * (shape[1] + pads[2] + pads[3]))
        return n

    def stop(*_a, **_k):
        raise _Padded

    monkeypatch.setattr(sc, "soft_replicas", counted)
    monkeypatch.setattr(sc, "pad_soft_edges", stop)
    with pytest.raises(_Padded):  # an ample budget pads: the counts of the padded frame
        br.render(image, d, blur, memory=br.MemoryOptions(memory_limit_mb=10_000))
    n, px = seen["n"], seen["px"]
    assert n > px / 4  # the border's rows replicate the strip's split pixels
    old = (pv.WHOLE_IMAGE_B + pv.TILED_B) * px + pv.SOFT_B * n
    new = pv._least_bytes(px, n)
    assert new > 1.2 * old
    out, stats = br.render_with_stats(image, d, blur, memory=br.MemoryOptions(memory_limit_mb=(old + new) / 2 / 2**20))
    assert out.shape == image.shape and np.isfinite(out).all()  # rendered without its border (no pad_soft_edges)
    assert stats.memory_estimate_mb * 2**20 < old


def test_the_estimate_counts_the_plan_where_it_is_the_peak():
    """The reported estimate is the larger of the plan's and the layers' peaks: on a frame that is all split pixels
    the plan's (170 B a split pixel) can be the larger."""
    assert pv._plan_bytes(1000, 1000) == 1000 * (pv.WHOLE_IMAGE_B + pv.SPLIT_PLAN_B)
    assert pv._least_bytes(1000, 0) == 1000 * (pv.WHOLE_IMAGE_B + pv.TILED_B)
    assert pv._least_bytes(1000, 1000) == pv._plan_bytes(1000, 1000)


def test_split_pixels_that_cannot_be_planned_are_refused_before_the_split(monkeypatch):
    """No border (clamp_border=False), a 1-px checkerboard: the matting's check (44 B a band pixel beside the frame)
    lets it through, but planning its split pixels (170 B each) exceeds the budget: one ResourceError naming the
    image, before ``split_scene`` allocates anything."""
    rng = np.random.default_rng(0)
    image = rng.uniform(0, 1, (200, 200, 3)).astype(np.float32)
    d = (np.indices((200, 200)).sum(0) % 2).astype(np.float32)
    blur, options = br.BlurParams(8.0, 0.5), br.PreviewOptions(clamp_border=False)
    seen = {}
    split = sc.split_scene

    def counted(image, s, soft, *a, **k):
        seen["n"] = len(soft)
        return split(image, s, soft, *a, **k)

    monkeypatch.setattr(sc, "split_scene", counted)
    br.render(image, d, blur, options=options)
    need = pv._plan_bytes(200 * 200, seen["n"])
    assert seen["n"] > 5000
    seen.clear()
    with pytest.raises(br.ResourceError, match=r"soft edges of the 200 x 200 px image: its \d+ split pixels need"):
        br.render(image, d, blur, options=options, memory=br.MemoryOptions(memory_limit_mb=0.9 * need / 2**20))
    assert not seen  # refused before the split


def _written_bytes(a) -> int:
    """The 4 KB pages of ``a`` holding anything but zeros: what a lazily zeroed array takes at least."""
    b = a.numpy().view(np.uint8).reshape(-1)
    n = b.size // 4096 * 4096
    return (int(b[:n].reshape(-1, 4096).any(1).sum()) + int(b[n:].any())) * 4096


def test_the_routing_of_a_frame_of_lights_takes_what_the_estimate_counts():
    """Regression: on a 20 000 x 2 noise strip (nearly every pixel a light) a routed layer's routing took 30 B a pixel
    (its clusters' light and shape, a plane a pyramid level), the estimate 0.76 of the growth. The clusters are
    scattered as they are found now: the routing's arrays hold at most ROUTING_B a pixel on a frame where nearly
    every cell has a light or a cluster."""
    import dataclasses

    import warp as wp

    rng = np.random.default_rng(0)
    h, w = 256, 2048
    src = np.ones((h, w, 4), np.float32)
    src[..., :3] = rng.random((h, w, 3)) ** 3 * 20
    coc = (rng.uniform(9.0, 140.0, (h, w)) * rng.choice([-1.0, 1.0], (h, w))).astype(np.float32)  # levels 1-4
    ap = br.Aperture()
    buf0 = wp.zeros((h, w + 2), dtype=wp.vec4, device="cpu")
    routing = pv.route_salient(wp.array(src, dtype=wp.vec4, device="cpu"), wp.array(coc, device="cpu"), 5, 8.0,
                               "cpu", pv.aperture_shape(ap, ap.blade_discs(), "cpu"), buf0)
    exact = routing.exact.numpy()
    assert (exact == 2).sum() > 500 and (exact == 1).sum() > 2000  # clusters and lights everywhere
    held = sum(_written_bytes(getattr(routing, f.name)) for f in dataclasses.fields(routing))
    assert held <= pv.ROUTING_B * h * w
