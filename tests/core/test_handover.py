"""Arrays handed over to the renderer (``bokehray.pipeline.Handover``, the command line's path): the same render, the
arrays freed once the scene is split; the public API never frees nor writes to a caller's arrays."""

import gc
import weakref

import numpy as np
import pytest

import bokehray as br
from bokehray.app.demo import build_demo_scene
from bokehray.errors import InputError
from bokehray.pipeline import Handover, render_handed_over


def _scene():
    s = build_demo_scene(width=192, height=128)
    return np.ascontiguousarray(s.image, np.float32), np.ascontiguousarray(s.disparity, np.float32)


BLUR = br.BlurParams(12.0, 0.2)


def test_handed_over_arrays_are_freed_while_the_layers_render_and_the_render_is_the_same():
    image, d = _scene()
    ref, ref_stats = br.render_with_stats(image.copy(), d.copy(), BLUR)
    alive = []
    refs = weakref.ref(image), weakref.ref(d)

    def progress(done, total):
        if done:  # a layer composited (``(0, 1)``: a check before any layer, in the scene step)
            gc.collect()
            alive.append(tuple(r() is not None for r in refs))

    inputs = Handover(image, d)
    del image, d
    out, stats = render_handed_over(inputs, BLUR, progress=progress)
    assert np.array_equal(out, ref)
    assert stats.layers == ref_stats.layers and stats.max_coc_px == ref_stats.max_coc_px
    assert alive and all(a == (False, False) for a in alive)  # freed before the first layer was composited
    with pytest.raises(InputError, match="already rendered"):
        render_handed_over(inputs, BLUR)


def test_the_public_api_keeps_the_callers_arrays_untouched():
    image, d = _scene()
    before = image.copy(), d.copy()
    alive = []

    def progress(done, total):
        alive.append(image.base is None and image.flags.owndata)

    out = br.render(image, d, BLUR, progress=progress)
    assert np.array_equal(image, before[0]) and np.array_equal(d, before[1])
    assert alive and all(alive)
    assert np.array_equal(out, br.render(before[0], before[1], BLUR))


def test_an_rgba_context_keeps_its_pixels_for_the_alpha():
    """The alpha of an RGBA input renders after the colour, through the same context: it keeps its pixels (and
    the handed-over render equals the API's)."""
    image, d = _scene()
    rgba = np.concatenate([image, np.linspace(0, 1, d.size, dtype=np.float32).reshape(d.shape)[..., None]], axis=2)
    ref = br.render(rgba, d, BLUR)
    out, _ = render_handed_over(Handover(rgba.copy(), d.copy()), BLUR)
    assert np.array_equal(out, ref)


def test_a_handover_must_be_a_handover():
    image, d = _scene()
    with pytest.raises(InputError, match="inputs"):
        render_handed_over((image, d), BLUR)
