"""bokehray_refiner.edges: the learned edge placement moves only band pixels, only to its candidates, the same on
tiles as on the whole frame, and its weights load only when they fit."""

from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

torch = pytest.importorskip("torch")

from bokehray_refiner.edges import (  # noqa: E402
    EdgeConfig,
    EdgeNet,
    Placement,
    candidates,
    colour_allows,
    edge_features,
    load_edge_net,
    map_sides,
    place_edges,
    save_edge_net,
)

import bokehray as br  # noqa: E402
from bokehray.errors import InputError  # noqa: E402

SMALL = EdgeConfig(width=8, dilations=(2, 4), radius_px=6)


def _scene(h=80, w=120, seed=0):
    rng = np.random.default_rng(seed)
    focus = rng.random((h, w, 3), dtype=np.float32)
    d = np.full((h, w), 0.2, np.float32)
    d[20:60, 30:70] = 0.8
    d[35:45, 90:] = 0.6
    return focus, d, br.BlurParams(12.0, 0.2)


def _red_square():
    """A red square on blue (scene-linear), its exact map and a blur: its depth edges sit on its colour edges."""
    image = np.zeros((64, 64, 3), np.float32)
    image[..., 2] = 0.6
    image[16:48, 16:48] = (0.8, 0.05, 0.05)
    exact = np.full((64, 64), 0.2, np.float32)
    exact[16:48, 16:48] = 0.8
    return image, exact, br.BlurParams(12.0, 0.8)


def _mover(config=SMALL, seed=0) -> EdgeNet:
    """A random network (it does move pixels at a low threshold)."""
    torch.manual_seed(seed)
    return EdgeNet(config).eval()


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**16), threshold=st.floats(0.5, 0.9), passes=st.integers(1, 4), keep_lights=st.booleans())
def test_passes_apply_the_network_again_to_the_map_it_made_until_nothing_moves(seed, threshold, passes, keep_lights):
    from bokehray_refiner.edges import place_edges_once

    focus, d, blur = _scene(48, 64, seed)
    rng = np.random.default_rng(seed)
    band = (rng.random(d.shape) < 0.6).astype(np.float32)
    keep = rng.random(d.shape) < 0.2 if keep_lights else None
    m = _mover(seed=seed % 7)
    out = place_edges(m, focus, d, blur, band, keep, Placement(threshold, tile=16, passes=passes))
    expect = d
    for _ in range(passes):
        expect = place_edges_once(m, focus, expect, blur, band, keep, Placement(threshold, tile=16))
    np.testing.assert_array_equal(out, expect)  # each pass reads the last one's map; a pass that moves nothing ends it
    changed = out != d
    assert not (changed & (band <= 0)).any() and (keep is None or not (changed & keep).any())
    assert set(np.unique(out)) <= set(np.unique(d))  # every value is one the map had: edges move, no new depths
    with pytest.raises(ValueError, match="passes"):
        place_edges(m, focus, d, blur, band, placement=Placement(threshold, passes=0))


def test_the_candidates_are_the_local_extremes_of_the_map_and_the_sides_split_between_them():
    _, d, _blur = _scene()
    near, far = candidates(d, 6)
    assert near[20 - 6, 30 - 6] == 0.8 and near[20 - 7, 30] == 0.2  # within the window of the near square only
    assert far[25, 35] == 0.2 and far[30, 45] == 0.8
    reach, on_near = map_sides(d, near, far)
    assert reach[20 - 6, 30] and not reach[20 - 7, 30] and not reach[40, 50]  # no edge within 6 px: out of reach
    assert on_near[25, 35] and not on_near[15, 35]
    between = np.full_like(d, 0.5)  # halfway: a tie, which counts as far
    assert not map_sides(between, np.full_like(d, 0.8), np.full_like(d, 0.2))[1].any()


def test_on_tiles_the_network_moves_the_map_as_it_would_on_the_whole_frame():
    focus, d, blur = _scene(90, 200)
    band = np.zeros(d.shape, np.float32)
    band[10:70, 20:80] = 1.0
    band[30:50, 150:190] = 0.5  # two boxes of tiles, apart
    m = _mover()
    moved = place_edges(m, focus, d, blur, band, placement=Placement(0.5, tile=16))
    with torch.no_grad():
        p = torch.sigmoid(m(torch.from_numpy(edge_features(focus, d, blur, band, SMALL))[None]))[0, 0].numpy()
    near, far = candidates(d, SMALL.radius_px)
    reach, on_near = map_sides(d, near, far)
    open_ = (band > 0) & reach
    expect = np.where(open_ & ~on_near & (p >= 0.5), near, np.where(open_ & on_near & (p <= 0.5), far, d))
    np.testing.assert_array_equal(moved, expect)
    assert (moved != d).any()


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**16), threshold=st.floats(0.0, 1.0), keep_lights=st.booleans(), attached=st.booleans(),
       margin=st.one_of(st.none(), st.floats(0.0, 0.3)))
def test_moves_only_open_band_pixels_only_to_a_candidate(seed, threshold, keep_lights, attached, margin):
    focus, d, blur = _scene(48, 64, seed)
    rng = np.random.default_rng(seed)
    band = (rng.random(d.shape) < 0.4).astype(np.float32) * rng.random(d.shape, dtype=np.float32)
    keep = rng.random(d.shape) < 0.3 if keep_lights else None
    moved = place_edges(_mover(seed=seed % 7), focus, d, blur, band, keep,
                        Placement(threshold, tile=16, attached=attached, colour_margin=margin))
    near, far = candidates(d, SMALL.radius_px)
    reach, on_near = map_sides(d, near, far)
    changed = moved != d
    if attached:  # every moved region touches the side it joins: no islands, no holes
        from scipy import ndimage

        eight = np.ones((3, 3), bool)
        for joined, side in ((changed & ~on_near, on_near & ~changed), (changed & on_near, reach & ~on_near & ~changed)):
            labels, n = ndimage.label(joined, structure=eight)
            touching = set(np.unique(labels[ndimage.binary_dilation(side, structure=eight) & joined]))
            assert set(range(1, n + 1)) <= touching
    assert not (changed & ((band <= 0) | ~reach)).any()
    if keep is not None:
        assert not (changed & keep).any()
    # a pixel moves only across the edge: from the far side to the near value, or the other way
    assert np.all(~changed | (on_near & (moved == far)) | (~on_near & (moved == near)))
    if margin is not None:  # and only where its colour is nearer the side it joins
        near_ok, far_ok = colour_allows(edge_features(focus, d, blur, band, SMALL), margin)
        assert not (changed & on_near & ~far_ok).any() and not (changed & ~on_near & ~near_ok).any()


def test_the_colour_veto_keeps_a_sharp_subject_whole_and_lets_a_misplaced_strip_go():
    """A network sure that every pixel is far would punch the subject's rim out of an exact map; with the colour veto
    only the strip of background the map wrongly gave the subject moves."""
    h, w = 64, 64
    focus = np.zeros((h, w, 3), np.float32)
    focus[..., 2] = 0.8  # a blue background
    focus[16:48, 16:48] = (0.9, 0.1, 0.1)  # a red subject
    exact = np.full((h, w), 0.2, np.float32)
    exact[16:48, 16:48] = 0.8
    blur = br.BlurParams(12.0, 0.8)
    band = np.ones((h, w), np.float32)
    m = EdgeNet(SMALL).eval()
    with torch.no_grad():
        m.net[-1].weight.zero_()
        m.net[-1].bias.fill_(-10.0)  # sure every pixel is far
    assert (place_edges(m, focus, exact, blur, band, placement=Placement(0.9)) != exact).any()  # holes in the rim
    np.testing.assert_array_equal(place_edges(m, focus, exact, blur, band, placement=Placement(0.9, colour_margin=0.05)), exact)
    grown = np.full((h, w), 0.2, np.float32)
    grown[12:52, 12:52] = 0.8  # the subject grown by 4 px into the background
    moved = place_edges(m, focus, grown, blur, band, placement=Placement(0.9, colour_margin=0.05))
    strip = (grown != exact)
    assert (moved[strip] == 0.2).mean() > 0.9  # the background strip goes back to the background
    np.testing.assert_array_equal(moved[16:48, 16:48], exact[16:48, 16:48])  # and the subject stays whole


def test_an_undecided_network_keeps_the_map():
    focus, d, blur = _scene()
    band = np.ones(d.shape, np.float32)
    m = EdgeNet(SMALL).eval()
    with torch.no_grad():
        m.net[-1].weight.zero_()
        m.net[-1].bias.zero_()  # p = 0.5 everywhere: sure of nothing
    np.testing.assert_array_equal(place_edges(m, focus, d, blur, band, placement=Placement(0.9)), d)
    with torch.no_grad():
        m.net[-1].bias.fill_(10.0)  # sure every pixel is near: the far side next to the edges moves
    moved = place_edges(m, focus, d, blur, band, placement=Placement(0.9))
    near, _ = candidates(d, SMALL.radius_px)
    assert moved[20 - 6, 30] == near[20 - 6, 30] == 0.8 and moved[5, 5] == d[5, 5]


def test_weights_round_trip_and_load_only_when_they_fit(tmp_path):
    m = _mover()
    save_edge_net(m, tmp_path / "e.safetensors")
    back = load_edge_net(tmp_path / "e.safetensors")
    assert back.config == SMALL
    for a, b in zip(m.state_dict().values(), back.state_dict().values()):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    # weights whose tensors do not fit the config they carry
    import json

    from safetensors.torch import save_file

    state = EdgeNet(EdgeConfig(width=4, dilations=(2, 4), radius_px=6)).state_dict()
    save_file(state, str(tmp_path / "bad.safetensors"),
              metadata={"config": json.dumps({"width": 8, "dilations": [2, 4], "radius_px": 6}),
                        "kind": "bokehray-edges"})
    with pytest.raises(InputError, match="bad.safetensors: not edge-network weights"):
        load_edge_net(tmp_path / "bad.safetensors")
    save_file(state, str(tmp_path / "other.safetensors"), metadata={"config": "{}"})  # not ours
    with pytest.raises(InputError, match="other.safetensors"):
        load_edge_net(tmp_path / "other.safetensors")
    with pytest.raises(InputError, match="no edge-network weights"):
        load_edge_net(tmp_path / "missing.safetensors")


def test_refine_renders_once_on_the_map_the_edge_network_moved():
    """With ``RefineOptions(edges=True)`` the edge network runs after the depth fix, and the level renders once, on
    its map; pixels it moved count as corrected."""
    from bokehray_refiner.depthfix import DepthFixOptions
    from bokehray_refiner.refine import RefineOptions, corrected_disparity, refine

    focus, d, blur = _scene()
    image = focus ** 2.2
    m = EdgeNet(SMALL).eval()
    with torch.no_grad():
        m.net[-1].weight.zero_()
        m.net[-1].bias.fill_(10.0)  # sure that every pixel is on the near side
    opts = RefineOptions(edges=True, neural=False, depthfix=DepthFixOptions(enabled=False))
    kept, none = corrected_disparity(image, d, blur, opts, edge_model=m)  # no correction, so nothing found wrong
    assert np.array_equal(kept, d) and not none.any()
    opts = replace(opts, min_fixed_share=0.0)  # the network runs on every map
    moved, changed = corrected_disparity(image, d, blur, opts, edge_model=m)
    assert changed.any() and np.array_equal(changed, moved != d)
    assert np.all(moved[changed] > d[changed])  # only towards the near side
    seen = []
    _out, stats = refine(image, d, blur, None, options=opts, edge_model=m,
                        rerender=lambda dd: seen.append(dd) or np.zeros(image.shape, np.float32))
    assert len(seen) == 1 and np.array_equal(seen[0], moved) and stats.depth_fixed_px == int(changed.sum())
    off, _ = corrected_disparity(image, d, blur, RefineOptions(edges=False, depthfix=opts.depthfix), edge_model=m)
    np.testing.assert_array_equal(off, d)
    vetoed, held = corrected_disparity(image, d, blur, replace(opts, edge_colour_margin=0.1), edge_model=m)
    assert held.any() and held.sum() < changed.sum() and np.array_equal(vetoed[held], moved[held])


def test_a_float64_map_counts_only_the_pixels_the_network_moved():
    from bokehray_refiner.depthfix import DepthFixOptions
    from bokehray_refiner.refine import RefineOptions, corrected_disparity

    focus, d, blur = _scene()
    opts = RefineOptions(edges=True, depthfix=DepthFixOptions(enabled=False), min_fixed_share=0.0)
    _, changed = corrected_disparity(focus ** 2.2, d.astype(np.float64) + 1e-9, blur, opts, edge_model=EdgeNet(SMALL))
    assert not changed.any()  # an undecided network moves nothing; float32 rounding is not a move


def test_the_share_of_the_band_the_depth_fix_moved_counts_band_pixels_only():
    from bokehray_refiner.refine import map_found_wrong

    band = np.zeros((10, 10), np.float32)
    band[:, :5] = 0.5  # 50 band pixels
    fixed = np.zeros((10, 10), bool)
    assert not map_found_wrong(fixed, band, 0.01) and map_found_wrong(fixed, band, 0.0)
    fixed[:, 5:] = True  # 50 moved outside the band: not evidence about the band's edges
    assert not map_found_wrong(fixed, band, 0.01)
    fixed[0, 0] = True  # one of 50 in the band: 2 %
    assert map_found_wrong(fixed, band, 0.02) and not map_found_wrong(fixed, band, 0.021)
    assert not map_found_wrong(fixed, np.zeros_like(band), 0.0)  # no band: nothing to place


def test_a_map_whose_edges_sit_on_the_photos_is_left_to_the_depth_fix():
    """A red square on blue with its exact map: the depth fix moves nothing, so a network sure that every pixel is
    far is not run (it would punch out the square's rim); with the map-level gate at 0 the square's edges still sit
    on its colour edges, so it is not run either; with both gates at 0 it is."""
    from bokehray_refiner.refine import RefineOptions, corrected_disparity

    image, exact, blur = _red_square()
    m = EdgeNet(SMALL).eval()
    with torch.no_grad():
        m.net[-1].weight.zero_()
        m.net[-1].bias.fill_(-10.0)  # sure every pixel is far
    kept, changed = corrected_disparity(image, exact, blur, RefineOptions(edges=True), edge_model=m)
    np.testing.assert_array_equal(kept, exact)
    assert not changed.any()
    # the map-level gate open: the edges still sit on the photo's (no disagreement left), so the network stays off
    kept, changed = corrected_disparity(image, exact, blur, RefineOptions(edges=True, min_fixed_share=0.0),
                                        edge_model=m)
    np.testing.assert_array_equal(kept, exact)
    both_open = RefineOptions(edges=True, min_fixed_share=0.0, edge_min_disagreement=0.0)
    punched, changed = corrected_disparity(image, exact, blur, both_open, edge_model=m)
    assert changed.any() and np.all(punched[changed] < exact[changed])


@pytest.mark.parametrize("field,value", [("edge_threshold", 0.49), ("edge_threshold", 1.01),
                                         ("edge_threshold", float("nan")), ("edge_colour_margin", -0.1),
                                         ("edge_colour_margin", float("nan")), ("edge_colour_margin", 2.0),
                                         ("edge_min_disagreement", -0.01), ("edge_min_disagreement", 1.5),
                                         ("edge_min_disagreement", float("nan")),
                                         ("min_fixed_share", -0.01), ("min_fixed_share", 1.5),
                                         ("min_fixed_share", float("nan")), ("edge_passes", 0), ("edge_passes", 17),
                                         ("edge_passes", 1.5), ("edge_passes", True)])
def test_edge_options_out_of_range_are_refused(field, value):
    from bokehray_refiner.refine import RefineOptions

    with pytest.raises(InputError, match=field):
        RefineOptions(edges=True, **{field: value})


def test_the_shipped_edge_weights_load_and_fit_their_recorded_config():
    import json

    from bokehray_refiner.edges import DEFAULT_EDGE_WEIGHTS

    m = load_edge_net()
    recorded = json.loads((DEFAULT_EDGE_WEIGHTS.parent / "edges.json").read_text())
    assert m.config == EdgeConfig(**recorded["config"])
    assert sum(p.numel() for p in m.parameters()) == recorded["parameters"]


def _eroded_scene_and_refiner():
    """(image, its map eroded by 3 px, blur, the level's rerender, a seeded untrained refiner): a map the correction
    works on, for the tests of what refine reuses."""
    from bokehray_refiner.model import BokehRefiner
    from bokehray_refiner.training.data import corrupt_disparity

    focus, d, blur = _scene(96, 128)
    image = focus ** 2.2
    given = np.clip(corrupt_disparity(d, "erode", 3), 0, 1).astype(np.float32)
    torch.manual_seed(0)
    return image, given, blur, lambda dd: br.render(image, dd, blur), BokehRefiner().eval()


def test_refine_reuses_the_corrections_edge_field_without_changing_a_pixel(monkeypatch):
    """The depth edges the correction found for its band are the gate's too: handed on instead of found again, with
    the same render and stats."""
    import bokehray_refiner.refine as refine_module
    from bokehray_refiner.refine import RefineOptions

    image, given, blur, rer, model = _eroded_scene_and_refiner()
    searches = []
    nearest_edge = refine_module.nearest_edge
    monkeypatch.setattr(refine_module, "nearest_edge", lambda reach: searches.append(1) or nearest_edge(reach))
    # noise: the depth fix finds nothing, so the map-level gate is opened; no edge network (it would move the map)
    opts = RefineOptions(min_fixed_share=0.0, edges=False)
    reused, st1 = refine_module.refine(image, given, blur, None, model=model, rerender=rer, options=opts)
    assert len(searches) == 1 and st1.band_pixels > 0  # one distance transform for the band and the gate
    corrected = refine_module._corrected
    monkeypatch.setattr(refine_module, "_corrected", lambda *a: replace(corrected(*a), edge_field=None))
    fresh, st2 = refine_module.refine(image, given, blur, None, model=model, rerender=rer, options=opts)
    assert len(searches) == 3  # found again
    np.testing.assert_array_equal(reused, fresh)
    assert (st1.band_pixels, st1.gate_open, st1.tiles_refined) == (st2.band_pixels, st2.gate_open, st2.tiles_refined)


def test_the_disagreement_left_is_small_where_depth_edges_sit_on_colour_edges():
    """:func:`disagreement`: the mean confidence gate over the band is near 0 for a square's exact map and large
    where the map's square is shrunk by 5 px (its edges 5 px off the colour edges; the gate opens on the far side of
    an edge only, ``GateOptions.open_dilated``); refine reports it and whether the edge network ran."""
    from bokehray_refiner.refine import RefineOptions, disagreement, edge_band, edge_reach, nearest_edge, refine
    from bokehray_refiner.training.data import corrupt_disparity

    image, exact, blur = _red_square()
    focus = image ** (1 / 2.2)

    def left(d):
        coc = blur.signed_coc(d).astype(np.float32)
        reach = edge_reach(coc, 1.0)
        return disagreement(focus, d, coc, edge_band(reach, 6.0, 4.0), nearest_edge(reach))

    shrunk = np.clip(corrupt_disparity(exact, "erode", 5), 0, 1).astype(np.float32)
    assert left(exact) < 0.02 and left(shrunk) > 0.5
    assert disagreement(focus, exact, blur.signed_coc(exact), np.zeros_like(exact)) == 0.0
    m = EdgeNet(SMALL).eval()
    _, st = refine(image, exact, blur, None, options=RefineOptions(min_fixed_share=0.0, neural=False), edge_model=m,
                   rerender=lambda dd: br.render(image, dd, blur))
    assert st.found_wrong and st.edge_disagreement is not None and st.edge_disagreement < 0.02 and not st.edges_ran
    d = st.as_dict()
    assert d["edges_ran"] is False and d["edge_disagreement"] == st.edge_disagreement


def test_the_gate_reuses_the_agreement_the_disagreement_measured(monkeypatch):
    """Where the edge network is held back by the disagreement rule, the agreement it measured on the map is the
    confidence gate's too: computed once instead of twice, with the same render and stats."""
    import bokehray_refiner.gate as gate_module
    import bokehray_refiner.refine as refine_module
    from bokehray_refiner.refine import RefineOptions

    image, given, blur, rer, model = _eroded_scene_and_refiner()
    opts = RefineOptions(min_fixed_share=0.0, edge_min_disagreement=1.0)  # measured, and never enough
    calls = []
    edge_gate = refine_module.edge_gate
    monkeypatch.setattr(refine_module, "edge_gate", lambda *a: calls.append(1) or edge_gate(*a))
    monkeypatch.setattr(gate_module, "edge_gate", lambda *a: calls.append(1) or edge_gate(*a))
    reused, st1 = refine_module.refine(image, given, blur, None, model=model, rerender=rer, options=opts)
    assert len(calls) == 1 and not st1.edges_ran and st1.edge_disagreement is not None and st1.band_pixels > 0
    corrected = refine_module._corrected
    monkeypatch.setattr(refine_module, "_corrected", lambda *a: replace(
        (c := corrected(*a)), edge_field=replace(c.edge_field, agreement=None)))
    fresh, st2 = refine_module.refine(image, given, blur, None, model=model, rerender=rer, options=opts)
    assert len(calls) == 3  # measured again for the gate
    np.testing.assert_array_equal(reused, fresh)
    assert (st1.band_pixels, st1.gate_open, st1.tiles_refined) == (st2.band_pixels, st2.gate_open, st2.tiles_refined)
