"""The layers' buffer cache (``bokehray.levels.buffers``): blocks reused, the default allocator restored, values
unchanged."""

import numpy as np
import warp as wp

from bokehray.levels import buffers


def test_blocks_reused_and_allocator_restored():
    dev = wp.get_device("cpu")
    before = dev.default_allocator
    with buffers.reuse_buffers("cpu") as cache:
        assert dev.default_allocator is cache
        a = wp.zeros((512, 1024), dtype=wp.vec4, device="cpu")  # 8 MB
        ptr = a.ptr
        a.fill_(wp.vec4(1.0, 2.0, 3.0, 4.0))
        del a
        b = wp.zeros((400, 1024), dtype=wp.vec4, device="cpu")  # fits the freed block: reused, and zeroed
        assert b.ptr == ptr and cache.hits == 1
        assert not b.numpy().any()
        c = wp.zeros((4096, 1024), dtype=wp.vec4, device="cpu")  # no block fits: a new one
        assert cache.misses == 2
        with buffers.reuse_buffers("cpu") as inner:  # nested: the outer cache serves
            assert inner is None and dev.default_allocator is cache
        del b, c
    assert dev.default_allocator is before
    assert not cache.free and not cache.sizes


def test_held_memory_stays_within_the_peak_in_use():
    with buffers.reuse_buffers("cpu") as cache:
        a = [wp.zeros(n << 18, dtype=float, device="cpu") for n in (2, 3, 4)]  # 2, 3, 4 MB
        peak = cache.requested
        del a
        big = wp.zeros(8 << 18, dtype=float, device="cpu")  # 8 MB: no block fits, cached ones make room
        held = cache.in_use + sum(size for size, _ in cache.free)
        assert held <= max(peak, 8 << 20)
        del big


def test_render_unchanged_by_the_cache():
    import bokehray as br
    from bokehray.levels import preview

    rng = np.random.default_rng(3)
    img = rng.random((480, 720, 3), dtype=np.float32)  # layers of 1 MB and more: cached
    s = np.linspace(-12, 9, 480 * 720, dtype=np.float32).reshape(480, 720)
    out1, _ = preview.render_signed_coc(img, s, br.Aperture())
    real = buffers.reuse_buffers
    try:
        from contextlib import nullcontext

        preview.reuse_buffers = lambda device: nullcontext()
        out2, _ = preview.render_signed_coc(img, s, br.Aperture())
    finally:
        preview.reuse_buffers = real
    np.testing.assert_array_equal(out1, out2)


def test_lazy_zeros_are_zeros():
    for shape, dtype in (((3, 300, 400), wp.vec4), ((3, 300, 400), float), ((1200, 1000), wp.uint8), ((4, 5), float)):
        a = buffers.lazy_zeros(shape, dtype, "cpu")
        b = wp.zeros(shape, dtype=dtype, device="cpu")
        assert a.shape == b.shape and a.dtype == b.dtype
        np.testing.assert_array_equal(a.numpy(), b.numpy())
        a.fill_(dtype(1) if dtype is not wp.vec4 else wp.vec4(1.0, 1.0, 1.0, 1.0))  # writable, its own memory
        assert a.numpy().all()


def test_a_slightly_larger_request_reuses_a_freed_block():
    """A freed (h, w) plane serves the (h, w + 2) pyramid buffer asked for next (``SLACK``): no new block."""
    with buffers.reuse_buffers("cpu") as cache:
        a = wp.zeros((600, 1000), dtype=wp.vec4, device="cpu")
        ptr = a.ptr
        del a
        b = wp.zeros((600, 1002), dtype=wp.vec4, device="cpu")
        assert b.ptr == ptr and cache.hits == 1 and cache.misses == 1
        assert not b.numpy().any()
        del b


def test_release_hands_back_the_cached_blocks_and_caching_goes_on():
    with buffers.reuse_buffers("cpu") as cache:
        a = wp.zeros((512, 1024), dtype=wp.vec4, device="cpu")  # 8 MB
        del a
        assert len(cache.free) == 1
        assert buffers.release_cached("cpu") >= 8 << 20 and not cache.free
        b = wp.zeros((512, 1024), dtype=wp.vec4, device="cpu")
        del b
        assert len(cache.free) == 1  # still caching
    assert buffers.release_cached("cpu") == 0  # no cache installed


def _cached_at_scatter(monkeypatch, hand_back: bool) -> tuple[np.ndarray, list[int]]:
    """A render whose every box is lazily zeroed (a large box's), one worker: the bytes the cache keeps as each
    layer starts its scatter (after its fill), and the output."""
    import bokehray as br
    from bokehray.levels import preview

    monkeypatch.setattr(buffers, "LAZY_MIN_BYTES", 1)
    if not hand_back:
        monkeypatch.setattr(preview, "_hand_back", lambda device: None)
    seen = []
    scatter = preview._scatter_sources

    def spy(*a, **k):
        alloc = wp.get_device("cpu").default_allocator
        seen.append(sum(size for size, _ in alloc.free))
        return scatter(*a, **k)

    monkeypatch.setattr(preview, "_scatter_sources", spy)
    rng = np.random.default_rng(5)
    img = rng.random((480, 720, 3), dtype=np.float32)
    s = np.linspace(-14, 10, 480 * 720, dtype=np.float32).reshape(480, 720)
    out, _ = preview.render_signed_coc(img, s, br.Aperture(), options=br.PreviewOptions(threads=1))
    return out, seen


def test_a_large_layer_s_fill_buffers_are_not_kept_beside_its_scatter(monkeypatch):
    """The fill's buffers (reused only by the next layer's fill) are handed back before a large layer scatters, so
    they do not lie beside the layers' peak; the same pixels as when they are kept."""
    kept_out, kept = _cached_at_scatter(monkeypatch, hand_back=False)
    monkeypatch.undo()
    out, cached = _cached_at_scatter(monkeypatch, hand_back=True)
    assert max(kept) > 0  # without the hand-back the fill's blocks wait in the cache
    assert cached and max(cached) == 0
    np.testing.assert_array_equal(out, kept_out)
