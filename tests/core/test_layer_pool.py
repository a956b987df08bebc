"""The preview's layer pool: workers take layers in any order, compositing stays back to front."""

import dataclasses
import threading
import time

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from bokehray import Aperture, PreviewOptions
from bokehray.levels import preview as pv


def _scene(size: int = 200) -> tuple[np.ndarray, np.ndarray]:
    """A far plane, a mid plane and near discs of several depths: layers of very different costs."""
    rng = np.random.default_rng(3)
    yy, xx = np.mgrid[:size, :size]
    image = rng.uniform(0.05, 1.0, (size, size, 3)).astype(np.float32)
    image[rng.random((size, size)) < 0.01] *= 40.0
    s = np.full((size, size), -18.0, np.float32)
    s[:, : size // 3] = -9.0
    for k, (cy, cx) in enumerate(((50, 60), (140, 150), (60, 150), (150, 50))):
        s[np.hypot(yy - cy, xx - cx) <= 18 - 2 * k] = 2.0 + 3 * k
    return image, s


def test_renders_are_bit_identical_for_any_number_of_threads():
    image, s = _scene()
    want, stats = pv.render_signed_coc(image, s, Aperture(), options=PreviewOptions(threads=1))
    assert stats.layers >= 5
    for threads in (2, 3, 6):
        got, _ = pv.render_signed_coc(image, s, Aperture(), options=PreviewOptions(threads=threads))
        np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("threads", [1, 2])
def test_a_free_worker_takes_the_next_layer_else_the_costliest(monkeypatch, threads):
    """With the farthest layer held back, the other worker takes the others costliest first, and stops once as many
    results wait as there are workers (each holds its box's result until the layers behind it are composited)."""
    image, s = _scene()
    _, stats = pv.render_signed_coc(image, s, Aperture(), options=PreviewOptions(threads=1))
    started, lock, ahead = [], threading.Lock(), threading.Event()
    render_layer = pv.render_layer
    seen = []

    def record(layer, arrays, scatter, *kept):
        with lock:
            started.append(layer)
            first = len(started) == 1
            if len(started) == 1 + threads:
                ahead.set()
        if threads > 1 and first:
            assert ahead.wait(60)
            time.sleep(0.3)  # a worker let through would start a layer now
            seen.append(len(started))
        return render_layer(layer, arrays, scatter, *kept)

    monkeypatch.setattr(pv, "render_layer", record)
    pv.render_signed_coc(image, s, Aperture(), options=PreviewOptions(threads=threads))
    index = [lyr.index for lyr in started]
    assert sorted(index) == sorted(set(index)) and len(index) == stats.layers  # each layer once
    if threads == 1:
        assert index == sorted(index)  # one worker: back to front
    else:
        assert index[0] == min(index)  # the farthest first: it is composited first
        assert seen == [1 + threads]  # two results waiting behind the held layer: the other worker stopped
        costs = [pv.layer_cost(lyr) for lyr in started[1:1 + threads]]
        assert costs == sorted(costs, reverse=True) and index[1:] != sorted(index[1:])


def test_one_fill_at_a_time(monkeypatch):
    """Two workers never run the pull-push fill (a layer's box-sized working set) at once; the layers' own sources
    are written outside the lock."""
    from bokehray import scene as sc

    image, s = _scene()
    fill, lock, now, most, fills = sc._fill, threading.Lock(), [0], [0], [0]

    def counted(*args):
        with lock:
            now[0] += 1
            fills[0] += 1
            most[0] = max(most[0], now[0])
        time.sleep(0.05)  # a window wide enough for another worker to come in, were it let in
        try:
            return fill(*args)
        finally:
            with lock:
                now[0] -= 1

    monkeypatch.setattr(sc, "_fill", counted)
    want, stats = pv.render_signed_coc(image, s, Aperture(), options=PreviewOptions(threads=1))
    got, _ = pv.render_signed_coc(image, s, Aperture(), options=PreviewOptions(threads=3))
    assert stats.layers >= 5 and fills[0] >= 4 and most[0] == 1
    np.testing.assert_array_equal(got, want)


def test_a_short_budget_takes_fewer_workers_before_tiles():
    """A budget between the one-worker and the two-worker estimates: one worker, untiled, the same render."""
    from bokehray import MemoryOptions, ResourceError

    image, s = _scene(240)
    two = PreviewOptions(threads=2)
    want, st2 = pv.render_signed_coc(image, s, Aperture(), options=two)
    _, st1 = pv.render_signed_coc(image, s, Aperture(), options=PreviewOptions(threads=1))
    assert st2.threads == 2 and st1.memory_estimate_mb < st2.memory_estimate_mb
    limit = 0.5 * (st1.memory_estimate_mb + st2.memory_estimate_mb)
    got, st = pv.render_signed_coc(image, s, Aperture(), options=two, memory=MemoryOptions(memory_limit_mb=limit))
    assert st.threads == 1 and st.image_tiles == 1 and st.memory_estimate_mb == st1.memory_estimate_mb
    np.testing.assert_array_equal(got, want)
    # a budget not even one worker fits untiled: tiles, or (here, a small frame) refused, as before
    with pytest.raises(ResourceError):
        pv.render_signed_coc(image, s, Aperture(), options=two,
                             memory=MemoryOptions(memory_limit_mb=0.9 * st1.memory_estimate_mb))


@given(mask=st.lists(st.lists(st.booleans(), min_size=9, max_size=9), min_size=7, max_size=7),
       box=st.tuples(st.integers(0, 60), st.integers(0, 60), st.integers(0, 80), st.integers(0, 80)),
       origin=st.tuples(st.integers(0, 40), st.integers(0, 60)))
def test_a_layers_lit_area_counts_its_box_pixels_in_support_tiles(mask, box, origin):
    """The memory model's area of a layer: the pixels of its box whose tile (on the scene's grid of 16 px, the box
    at ``origin`` in the scene) is in its support, against the mask blown up to pixels."""
    from bokehray.scene import LayerRecord

    support = np.array(mask, bool)
    y0, y1 = sorted(box[:2])
    x0, x1 = sorted(box[2:])
    layer = LayerRecord(0, -1.0, 1.0, (y0, y1, x0, x1), 1.0, 0.0, support, 16, origin)
    pixels = np.repeat(np.repeat(support, 16, 0), 16, 1)
    oy, ox = origin
    assert pv._lit_area(layer) == int(pixels[oy + y0 : oy + y1, ox + x0 : ox + x1].sum())
    assert pv._lit_area(dataclasses.replace(layer, support=None)) == (y1 - y0) * (x1 - x0)


def test_the_estimate_counts_one_layer_at_its_peak_and_the_other_workers_at_what_they_hold():
    """Two workers, two large (lazily zeroed) layers and a small dense one: the peak layer at its full rate, the
    other worker's at HELD_B (not its own peak: its level 0 and routing take their pages as its light lands), the
    third largest's result waiting. The largest sum is the first layer's peak beside the second's held bytes."""
    layers = [(1000, 46, pv.HELD_B), (900, 30, pv.HELD_B), (100, pv.SMALL_BOX_B, pv.SMALL_BOX_B)]
    want = pv.REGION_B * 2000 + 1000 * 46 + 900 * pv.HELD_B + pv.RESULT_B * 100
    assert pv._region_bytes(2000, layers, 2) == want
    # a dense box is held whole from its start: beside the other layer's peak it counts whole
    dense = [(300, 46, pv.HELD_B), (1000, pv.SMALL_BOX_B, pv.SMALL_BOX_B)]
    assert pv._region_bytes(0, dense, 2) == 1000 * pv.SMALL_BOX_B + 300 * 46
    assert pv._region_bytes(0, dense, 1) == 1000 * pv.SMALL_BOX_B


_footprints = st.lists(st.tuples(st.integers(0, 10**6), st.sampled_from([30, 46, pv.SMALL_BOX_B, pv.DENSE_LAYER_B]))
                       .map(lambda t: (t[0], t[1], pv.HELD_B if t[1] in (30, 46) else t[1])), min_size=1, max_size=12)


def test_a_lazy_accumulator_counts_from_the_back_layer_s_composite_on():
    """A lazily zeroed accumulator takes its pages when the back layer (the first composited) is done: the estimate is
    the larger of the layers before it without the accumulator, the back layer's result composited beside it and
    the other worker's layer, and the layers after it beside it."""
    layers = [(1000, 30, 29), (900, 30, 29), (800, 30, 29), (100, 46, 29)]
    window = 1200
    before = 1000 * 30 + 900 * 29 + pv.RESULT_B * 800
    at_back = pv.RESULT_B * 1000 + 900 * 29 + pv.RESULT_B * 800
    after = 900 * 30 + 800 * 29 + pv.RESULT_B * 100
    flag = (pv.REGION_B - pv.ACC_B) * window
    assert pv._region_bytes(window, layers, 2, lazy_acc=True) == flag + max(before, pv.ACC_B * window + max(at_back, after))
    assert pv._region_bytes(window, layers, 2) == pv.REGION_B * window + before  # dense: there all along


@given(layers=_footprints, threads=st.integers(1, 6), window=st.integers(0, 10**7))
def test_a_lazy_accumulator_never_counts_more_than_a_dense_one(layers, threads, window):
    """Counting the accumulator from the back layer's composite on lowers the estimate at most to the layers' own
    peak (with the opaque map), never below, and never raises it."""
    dense = pv._region_bytes(window, layers, threads)
    lazy = pv._region_bytes(window, layers, threads, lazy_acc=True)
    assert (pv.REGION_B - pv.ACC_B) * window + pv._layers_bytes(layers, threads) <= lazy <= dense


@given(layers=_footprints, threads=st.integers(1, 6), window=st.integers(0, 10**7))
def test_the_estimate_lies_between_one_worker_and_every_worker_at_its_peak(layers, threads, window):
    """More workers never lower it; one worker is its largest layer at its peak; it never exceeds every worker's
    layer counted at its peak (the model it replaced, an upper bound)."""
    one = pv._region_bytes(window, layers, 1)
    assert one == pv.REGION_B * window + max(px * rate for px, rate, _ in layers)
    got = pv._region_bytes(window, layers, threads)
    assert got >= one and got <= pv._region_bytes(window, layers, threads + 1)
    results = sorted((px for px, _, _ in layers), reverse=True)[threads : 2 * threads - 1]
    bound = sum(sorted((px * rate for px, rate, _ in layers), reverse=True)[:threads]) + pv.RESULT_B * sum(results)
    assert got <= pv.REGION_B * window + bound


def test_a_layer_s_footprint_dense_when_small_lazy_when_large():
    """A box below buffers.LAZY_MIN_BYTES of vec4 is zeroed whole as it starts (held whole); a large one counts its
    lit area at its peak rate and HELD_B beside another layer's peak; on a GPU every box is dense."""
    from bokehray.scene import LayerRecord

    small = LayerRecord(0, -1.0, 1.0, (0, 100, 0, 200), 4.0, 0.0)
    assert pv._layer_footprint(small, 8.0, True) == (20000, pv.SMALL_BOX_B, pv.SMALL_BOX_B)
    large = LayerRecord(0, -1.0, 1.0, (0, 2000, 0, 2000), 4.0, 0.0)
    px, rate, held = pv._layer_footprint(large, 8.0, True)
    assert px == 4_000_000 and rate in (pv.LIT_B, pv.LIT_B + pv.LEVEL0_B) and held == pv.HELD_B < rate
    assert pv._layer_footprint(large, 8.0, False) == (4_000_000, pv.DENSE_LAYER_B, pv.DENSE_LAYER_B)


def test_a_routed_layer_holds_its_routing_beside_another_layer_s_peak():
    """A layer with pyramid levels above 0 is routed (exact highlights on): from its routing to the end of its scatter
    it holds the routing's flags and cell sums too, ROUTING_B a lit pixel (a 20 000 x 2 noise strip had two routed
    full-frame layers at their peak at once); with exact highlights off, or no level above 0, it holds HELD_B."""
    from bokehray.scene import LayerRecord

    large = LayerRecord(0, -60.0, -20.0, (0, 2000, 0, 2000), 60.0, 0.0)
    px, rate, held = pv._layer_footprint(large, 8.0, True)
    assert held == pv.HELD_B + pv.ROUTING_B < rate
    assert pv._layer_footprint(large, 8.0, True, routed=False) == (px, rate, pv.HELD_B)
    flat = dataclasses.replace(large, s_lo=-4.0, s_hi=-1.0, max_radius=4.0)  # level 0 only: nothing to route
    assert pv._layer_footprint(flat, 8.0, True)[2] == pv.HELD_B


@given(r0=st.integers(0, 300), n=st.integers(0, 400), threads=st.integers(1, 4))
def test_bands_cover_the_rows_once_each(r0, n, threads):
    """``in_bands`` runs its pass on every row of the range exactly once, in at most ``threads`` bands, none below
    ``BAND_MIN_ROWS`` rows unless the range is."""
    from concurrent.futures import ThreadPoolExecutor

    seen, lock = [], threading.Lock()

    def launch(a, b):
        with lock:
            seen.append((a, b))

    helper = ThreadPoolExecutor(max_workers=threads - 1) if threads > 1 else None
    try:
        pv.in_bands(launch, r0, r0 + n, helper, threads)
    finally:
        if helper is not None:
            helper.shutdown()
    rows = sorted(y for a, b in seen for y in range(a, b))
    assert rows == list(range(r0, r0 + n))
    assert len(seen) <= threads and all(b - a >= min(n, pv.BAND_MIN_ROWS) for a, b in seen)


def test_a_layer_callback_after_the_last_composite_starts_nothing(monkeypatch):
    """A future's waiters are woken before its done callbacks run, so the compositing thread can take the last
    layer's result and move the head past it before that layer's callback (``_Starter.top_up``) runs: it must start
    nothing then (it indexed past the last layer: an IndexError logged from the callback)."""
    from concurrent.futures import ThreadPoolExecutor

    from bokehray.levels.preview import _Starter

    monkeypatch.setattr(pv, "layer_cost", lambda layer: 1.0)
    with ThreadPoolExecutor(max_workers=2) as pool:
        starter = _Starter(lambda layer, kept: layer, ["a", "b"], [None, None], pool, 2)
        starter.head = 2  # both composited
        starter.top_up()
        assert starter.started == {}
        starter.head = 0
        starter.top_up()
        assert sorted(starter.started) == [0, 1]
