"""The two synchronisation layers end to end: which one reads what (issue 14).

The connectivity layer survives crops (the surface's frame moves), the geometric layer survives
re-triangulation (the connectivity labels are gone); an untouched file reads with the first.
"""

from __future__ import annotations

import meshoptimizer
import numpy as np
import pytest
from scipy.spatial import ConvexHull

from core import geosync, pipeline, sync
from core.analysis import analyse_geometric, statistic
from core.api import detect_mesh, embed_mesh
from core.coding import encode
from core.embedding import Selection, _Mesh, embed_parts
from core.geosync import rung_size
from core.mesh import adjacency
from core.pipeline import _prepared_placements
from core.sync import vertex_labels
from core.tolerances import TOL
from tests.core.meshes import irregular_sphere, similarity

PAYLOAD = "10110011100011110000101011001010"
KEY = "two layers"


def _drop_unreferenced(v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    used = np.unique(f)
    remap = np.full(len(v), -1, np.int64)
    remap[used] = np.arange(len(used))
    return v[used], remap[f]


def _simplified(v: np.ndarray, f: np.ndarray, fraction: float) -> tuple[np.ndarray, np.ndarray]:
    """meshoptimizer's simplifier (what ``gltf-transform optimize`` runs): ``fraction`` of the faces
    removed by edge collapses onto existing vertices."""
    idx = np.ascontiguousarray(f, np.uint32).ravel()
    out = np.zeros_like(idx)
    target = int(len(idx) * (1.0 - fraction)) // 3 * 3
    n = meshoptimizer.simplify(out, idx, np.ascontiguousarray(v, np.float32), target_index_count=target,
                               target_error=0.05)
    return _drop_unreferenced(v, out[:n].reshape(-1, 3).astype(np.int64))


def _lopsided(n: int = 20000) -> tuple[np.ndarray, np.ndarray]:
    """An irregular closed surface of ``n`` vertices with three distinct principal axes and a
    lopsided bump (third moments far from 0)."""
    v, f = irregular_sphere(n, 7)
    bump = 0.3 * np.exp(-8.0 * ((v - [0.8, 0.3, 0.0]) ** 2).sum(axis=1))[:, None]
    return v * np.array([1.6, 1.0, 0.7]) + bump, f


def _uneven(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A closed lopsided surface of ``n`` vertices, 90 % of them in a cap of a tenth of its area (a
    scan's detailed face and its plain back): where the geometric layer's cells are, the carriers a
    cell size gets hardly depend on it."""
    rng = np.random.default_rng(seed)
    p = rng.normal(size=(n, 3))
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    k = int(0.9 * n)
    z, phi = rng.uniform(0.85, 1.0, k), rng.uniform(0.0, 2.0 * np.pi, k)
    p[:k] = np.stack([np.sqrt(1.0 - z * z) * np.cos(phi), np.sqrt(1.0 - z * z) * np.sin(phi), z], axis=1)
    f = ConvexHull(p).simplices.copy()
    normal = np.cross(p[f[:, 1]] - p[f[:, 0]], p[f[:, 2]] - p[f[:, 0]])
    flip = (normal * p[f].mean(axis=1)).sum(axis=1) < 0
    f[flip] = f[flip][:, ::-1]
    r = 1.0 + 0.05 * np.sin(3 * p[:, 0]) * np.cos(2 * p[:, 1]) + 0.2 * p[:, 0] ** 3 + 0.1 * p[:, 1]
    return p * (r[:, None] * np.array([1.5, 1.0, 0.8])), f


@pytest.fixture(scope="module")
def marked() -> tuple[np.ndarray, np.ndarray, object]:
    """:func:`_lopsided`, marked with planes."""
    v, f = _lopsided()
    new, report = embed_mesh(v, f, KEY, payload=PAYLOAD, method="planes")
    return new, f, report


@pytest.fixture(scope="module")
def cropped(marked) -> tuple[np.ndarray, np.ndarray]:
    """The marked mesh with half its surface cut away (the frame moves, the labels stay)."""
    v, f, _ = marked
    keep = v[f].mean(axis=1)[:, 0] < 0.1
    return _drop_unreferenced(v, f[keep])


def test_both_layers_read_the_untouched_mesh(marked) -> None:
    v, f, report = marked
    assert report.layers == ["connectivity", "geometry"] and report.geometric_carriers > 0
    assert report.rms_displacement <= 2e-4
    res = detect_mesh([(v, f)], KEY)
    assert res.detected and res.payload == PAYLOAD and res.layer == "connectivity"


@pytest.mark.parametrize("fraction", [0.3, 0.5])
def test_a_simplified_mesh_reads_with_the_geometric_layer(marked, fraction: float) -> None:
    """Simplification keeps few connectivity labels (the connectivity view does not read), but the
    vertices nearest the cells' centres are mostly still there; moved, re-ordered and turned, too."""
    v, f, _ = marked
    sv, sf = _simplified(v, f, fraction)
    assert len(sv) < (1.0 - 0.8 * fraction) * len(v)
    res = detect_mesh([(sv, sf)], KEY)
    assert res.detected and res.payload == PAYLOAD and res.layer == "geometry"
    assert res.false_positive_probability < 2e-6
    moved = detect_mesh([similarity(sv, sf, np.random.default_rng(3))], KEY)
    assert moved.detected and moved.payload == PAYLOAD
    assert not detect_mesh([(sv, sf)], "another key").detected


def test_a_file_simplified_below_the_layers_size_still_reads_with_it() -> None:
    """A file just large enough for the geometric layer, simplified by half: fewer vertices than a
    file needs to get the layer, but the detector still looks for it (the rocker arm simplified by
    30 % was read by nothing while it did not)."""
    v, f = _lopsided(8000)
    new, report = embed_mesh(v, f, KEY, payload=PAYLOAD, method="planes")
    assert "geometry" in report.layers and len(v) >= pipeline.GEOMETRIC_MIN_VERTICES
    sv, sf = _simplified(new, f, 0.5)
    assert pipeline.GEOMETRIC_DETECT_FROM <= len(sv) < pipeline.GEOMETRIC_MIN_VERTICES
    res = detect_mesh([(sv, sf)], KEY)
    assert res.detected and res.payload == PAYLOAD and res.layer == "geometry"


def test_the_geometric_layer_reads_every_method_with_planes() -> None:
    """Its carriers are moved and read with one statistic whatever the file's method
    (analysis.GEOMETRIC_METHOD): the ellipsoid marks cost the RMS budget too much there."""
    v, f = _lopsided()
    word = encode(KEY, np.array([int(c) for c in PAYLOAD], np.uint8))
    prepared, placements, _ = _prepared_placements([(v, f)], KEY, len(word), "ellipsoids")
    assert placements[0] is not None
    got = analyse_geometric(v, prepared[0][0], KEY, ["ellipsoids", "planes"], placements[0])
    a = got["ellipsoids"]
    assert a is got["planes"] and a.geometric and len(a.carriers) > 0
    np.testing.assert_allclose(a.z, statistic("planes", v[a.carriers], a.mu, a.axes, a.lam, a.scale))


def test_a_geometric_read_names_the_method_only_when_connectivity_carriers_show_it(marked) -> None:
    """Read through the geometric view alone, every method decodes the same carriers: the method is
    named by the connectivity carriers still at the embedder's margin (planes here), never by the
    decoder that happened to read first, and is None where none show it."""
    v, f, _ = marked
    sv, sf = _simplified(v, f, 0.1)
    res = detect_mesh([(sv, sf)], KEY)
    assert res.detected and res.payload == PAYLOAD and res.layer == "geometry" and res.method == "planes"
    e, _ = embed_mesh(*_lopsided(), KEY, payload=PAYLOAD, method="ellipsoids")
    res = detect_mesh([_simplified(e, f, 0.1)], KEY)
    assert res.detected and res.payload == PAYLOAD and res.method in (None, "ellipsoids")


def test_a_crop_reads_with_the_connectivity_layer(cropped) -> None:
    """Half the surface cut away moves the frame: the geometric carriers are lost, the
    connectivity ones are not."""
    cv, cf = cropped
    res = detect_mesh([(cv, cf)], KEY)
    assert res.detected and res.payload == PAYLOAD and res.layer == "connectivity"


def test_a_piece_whose_labels_stop_a_step_early_reads_one_step_wider(monkeypatch) -> None:
    """A crop breaks symmetries, so its colour refinement can stop a step of ``ROUND_STEPS`` before
    the whole mesh's did (the Beast: 6 rounds, its crops 3) and no label matches; the detector
    also reads the connectivity layer one step wider.  Here the embedder starts at 6 rounds (as
    on a mesh of few distinct 3-ring labels), the detector's piece stops at 3."""
    v, f = irregular_sphere(6000, 11)
    with monkeypatch.context() as m:
        m.setattr(sync, "ROUND_STEPS", sync.ROUND_STEPS[1:])
        assert vertex_labels(v, adjacency(f, len(v))).rounds == sync.ROUND_STEPS[0] == 6
        new, _ = embed_mesh(v, f, KEY, payload=PAYLOAD, method="ellipsoids")
    keep = new[f].mean(axis=1)[:, 0] < 0.2
    cv, cf = _drop_unreferenced(new, f[keep])
    assert vertex_labels(cv, adjacency(cf, len(cv))).rounds == 3
    res = detect_mesh([(cv, cf)], KEY, payload=PAYLOAD)
    assert res.detected and res.payload == PAYLOAD and res.layer == "connectivity"
    with monkeypatch.context() as m:
        m.setattr(pipeline, "has_step", lambda labels, step: False)
        assert not detect_mesh([(cv, cf)], KEY, payload=PAYLOAD).detected


def test_a_piece_whose_labels_go_a_step_further_reads_one_step_narrower(cropped, monkeypatch) -> None:
    """The other way round (an Ogre crop: 12 rounds where the whole stopped at 9, wider rings
    gaining more labels in the piece): here the detector's rounds are pushed to 6 while the
    embedder used 3."""
    cv, cf = cropped
    with monkeypatch.context() as m:
        m.setattr(sync, "ROUND_STEPS", (3, 6))
        m.setattr(sync, "MORE_RINGS_BELOW", 1.01)  # more rings whatever the share and the gain
        m.setattr(sync, "MORE_RINGS_GAIN", 0.0)
        assert vertex_labels(cv, adjacency(cf, len(cv))).rounds == 6
        res = detect_mesh([(cv, cf)], KEY, payload=PAYLOAD)
        assert res.detected and res.payload == PAYLOAD and res.layer == "connectivity"
        m.setattr(pipeline, "has_step", lambda labels, step: False)
        assert not detect_mesh([(cv, cf)], KEY, payload=PAYLOAD).detected


def test_the_wider_and_interior_views_count_in_the_false_positive_figure(cropped, monkeypatch) -> None:
    """Made only when the others do not read, the wider view and the interior one (the piece has a
    boundary) still count in every answer's union bound: one candidate per method for the wider
    view (the embedder's decoding), two for the interior one (also its NEAR variant), 2 + 4 beside
    the 26 of the others with both methods."""
    cv, cf = cropped
    res = detect_mesh([(cv, cf)], KEY, payload=PAYLOAD)
    without = {}
    for name, off in (("wider", ["has_step"]), ("interior", ["_interior_view"]),
                      ("both", ["has_step", "_interior_view"])):
        with monkeypatch.context() as m:
            if "has_step" in off:
                m.setattr(pipeline, "has_step", lambda labels, step: False)
            if "_interior_view" in off:
                m.setattr(pipeline, "_interior_view", lambda layers: [])
            without[name] = detect_mesh([(cv, cf)], KEY, payload=PAYLOAD)
    assert res.detected and all(r.detected for r in without.values())
    fpp = res.false_positive_probability
    assert fpp / without["wider"].false_positive_probability == pytest.approx(32 / 30, rel=1e-6)
    assert fpp / without["interior"].false_positive_probability == pytest.approx(32 / 28, rel=1e-6)
    assert fpp / without["both"].false_positive_probability == pytest.approx(32 / 26, rel=1e-6)


@pytest.mark.parametrize("split", [False, True])
def test_the_selections_made_beside_the_frame_change_nothing(split: bool, monkeypatch) -> None:
    """embed_parts with the connectivity selection that _prepared_placements made (in parallel with
    the geometric layer's frame, and on a large file the geometric carriers read and the tied pairs
    made in the second thread) moves exactly what it moves without it, however often it is reused
    (the budget's retries reuse it: the embedder must not change it in place)."""
    v, f = _lopsided()
    if split:  # the large file's path (a second thread) on this small mesh
        monkeypatch.setattr(pipeline, "SPLIT_FROM", 1000)
    word = encode(KEY, np.array([int(c) for c in PAYLOAD], np.uint8))
    prepared, placements, selections = _prepared_placements([(v, f)], KEY, len(word), "planes")
    assert placements[0] is not None and selections is not None
    assert all((s.geometric is not None and s.tied is not None) == split for s in selections)
    def state(s: Selection) -> list[np.ndarray]:
        geo = [] if s.geometric is None else [s.geometric.result().z, s.geometric.result().mu]
        return [s.prio, s.analysis.z, s.analysis.mu, *geo]

    kept = [[x.copy() for x in state(s)] for s in selections]
    plain = embed_parts([(v, f)], KEY, word, "planes", 0.07, prepared=prepared, placements=placements,
                        rms_budget=1.9e-4)[0][0]
    for _ in range(2):
        got = embed_parts([(v, f)], KEY, word, "planes", 0.07, prepared=prepared, placements=placements,
                          rms_budget=1.9e-4, selections=selections)[0][0]
        assert np.array_equal(got, plain)
    for before, s in zip(kept, selections, strict=True):
        assert all(np.array_equal(x, y) for x, y in zip(before, state(s), strict=True))


def _embedding_lopsided() -> tuple[np.ndarray, np.ndarray, _Mesh]:
    """:func:`_lopsided`'s vertices, the codeword of ``PAYLOAD`` and the embedder's state
    (``planes``, with its placement) before any round."""
    v, f = _lopsided()
    word = encode(KEY, np.array([int(c) for c in PAYLOAD], np.uint8))
    prepared, placements, _ = _prepared_placements([(v, f)], KEY, len(word), "planes")
    (adj, labels), placement = prepared[0], placements[0]
    assert placement is not None
    return v, word, _Mesh(v, f, adj, labels, KEY, "planes", TOL, placement, 1.0, 0.07)


def test_a_cell_that_changes_hands_after_the_follow_keeps_both_vertices() -> None:
    """After the follow, a geometric carrier that loses its cell stays among the carriers the rounds
    move, and a cell going back to it is no change: the ties that flip with every move settle."""
    v, _, st = _embedding_lopsided()
    adj, placement = st.adj, st.placement
    assert placement is not None
    st.followed = True  # the frame as it is: what follows is the rule after the follow
    assert st.geo is not None and not st.reselect()
    first = st.geo.carriers.copy()
    h = rung_size(placement.rung) * placement.frame.rho

    def away(c: int) -> np.ndarray:  # half a cell along an axis: its cell may go to another vertex
        moved = v.copy()
        moved[c] = v[c] + 0.5 * h * placement.axes[0]
        return moved

    def taken(c: int) -> bool:
        got = analyse_geometric(away(c), adj, KEY, ["planes"], placement)["planes"].carriers
        return c not in got and len(np.setdiff1d(got, first)) > 0

    c = next(int(c) for c in first if taken(int(c)))
    st.v[:] = away(c)
    st.dirty = True  # as a round that moves it
    st.reselect()
    assert st.view is not None and c not in st.view.carriers and c in st.geo.carriers
    taker = np.setdiff1d(st.view.carriers, first)
    assert len(taker) >= 1
    st.v[c], st.dirty = v[c], True  # back: the cell is its again, and nothing is new
    assert not st.reselect()
    assert c in st.view.carriers and set(taker) <= set(st.geo.carriers.tolist())
    assert set(first) <= set(st.geo.carriers.tolist())


def test_the_geometric_layer_moves_once_its_frame_has_followed_the_connectivity_moves() -> None:
    """The first round prices the geometric carriers of the original frame but moves only the
    connectivity layer's; the first choice after it makes the frame again, holds the original
    carriers that lost their cell, and the next round moves the geometric layer to the full margin."""
    from core.slots import assign_slots, ranked_by_default

    v, word, st = _embedding_lopsided()
    assert st.geo is not None
    original = st.geo.carriers.copy()
    geometric_only = np.setdiff1d(original, st.local.carriers)
    L = len(word)
    slots = assign_slots([st.local.slot_hash], L, ranked_by_default(len(st.local.carriers), L))[0]
    assert st.round(1, word, slots, 1.9e-4, None)
    moved = np.any(st.v != v, axis=1)
    assert moved[st.local.carriers].any() and not moved[geometric_only].any()
    assert st.reselect() and st.followed and st.fresh
    assert st.view is not None and not np.array_equal(st.view.carriers, original)
    assert set(original.tolist()) <= set(st.geo.carriers.tolist())
    before = st.v.copy()
    assert st.round(2, word, slots, 1.9e-4, None) and not st.fresh
    now_moved = np.any(st.v != before, axis=1)
    assert now_moved[np.setdiff1d(st.geo.carriers, st.local.carriers)].any()


def test_the_interior_view_keeps_the_carriers_whose_labels_the_cut_left_alone() -> None:
    """A cut changes the labels up to the refinement's rounds from it, no further: in a cropped
    piece of a closed mesh, every carrier the interior view keeps voting has the label its vertex
    has in the whole mesh, and the view mutes exactly the carriers that near the boundary.  A closed
    mesh gets no interior view."""
    v, f = _lopsided(8000)
    whole = vertex_labels(v, adjacency(f, len(v)))
    assert pipeline._interior_view(pipeline._layers(pipeline._ArrayDoc([(v, f)]), [0], KEY, ["planes"])) == []
    for axis, cut in ((0, 0.2), (1, -0.3), (2, 0.0)):
        keep = v[f].mean(axis=1)[:, axis] < cut
        used = np.unique(f[keep])
        cv, cf = _drop_unreferenced(v, f[keep])
        layers = pipeline._layers(pipeline._ArrayDoc([(cv, cf)]), [0], KEY, ["planes", "ellipsoids"])
        adj, lab = layers.adjs[0], layers.labels[0]
        assert lab.rounds == whole.rounds and adj.boundary.any()
        (view,) = [made() for layer, made in pipeline._interior_view(layers)]
        near = adj.within(adj.boundary, lab.rounds)
        for m in ("planes", "ellipsoids"):
            (a,), (b,) = layers.local[m], view[m]
            assert np.array_equal(b.muted, near[a.carriers]) and np.array_equal(b.z, a.z)
            kept = a.carriers[~b.muted]
            assert 0 < len(kept) < len(a.carriers)
            assert np.array_equal(lab.labels[kept], whole.labels[used[kept]])
            # the muted ones include carriers whose labels the cut changed
            gone = a.carriers[b.muted]
            assert (lab.labels[gone] != whole.labels[used[gone]]).any()


def test_half_the_vertices_gone_reads_at_a_rung_far_below_the_detectors_own(monkeypatch) -> None:
    """Quadric simplification by half of :func:`_uneven`: the detector's rung, from the vertices
    left, is more than 3 rungs above the embedder's (as quadric 50 % took Beast's and Ogre's 5 above),
    and the geometric layer reads there; the 3 rungs below that the detector tried until stop 35 do
    not reach it."""
    import fast_simplification

    v, f = _uneven(20000, 3)
    new, report = embed_mesh(v, f, KEY, payload=PAYLOAD, method="planes")
    assert "geometry" in report.layers
    sv, sf = fast_simplification.simplify(new, f.astype(np.int32), target_reduction=0.5)
    sf = sf.astype(np.int64)
    res = detect_mesh([(sv, sf)], KEY, payload=PAYLOAD)
    assert res.detected and res.crc_ok and res.payload == PAYLOAD and res.layer == "geometry"
    monkeypatch.setattr(geosync, "RUNGS_BELOW", 3)
    assert not detect_mesh([(sv, sf)], KEY, payload=PAYLOAD).detected


def test_a_geometric_choice_read_from_kept_rows_is_a_fresh_analysis() -> None:
    """The embedder's re-choices (``_Mesh.reselect``) take the rows of the carriers it keeps current
    (analysis.geometric_read): the result is analyse_geometric's, array for array, with the rings a
    neighbour's move flattened dropped and the scale test made over the whole choice."""
    from core.analysis import geometric_read
    from core.embedding import _refresh

    v, f = _lopsided()
    word = encode(KEY, np.array([int(c) for c in PAYLOAD], np.uint8))
    prepared, placements, _ = _prepared_placements([(v, f)], KEY, len(word), "planes")
    adj, placement = prepared[0][0], placements[0]
    assert placement is not None
    rng = np.random.default_rng(5)
    v = v.copy()
    a = analyse_geometric(v, adj, KEY, ["planes"], placement)["planes"]
    others = np.setdiff1d(np.arange(len(v)), a.carriers)
    extra = np.sort(rng.choice(others, len(a.carriers) // 3, replace=False))

    def read(sel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        sel = np.unique(sel)
        return sel, rng.integers(0, 2**63, len(sel)).astype(np.uint64)

    # kept: most of the choice and half the extra carriers, read at these positions
    kept_sel, kept_hash = read(np.concatenate([a.carriers[: 2 * len(a.carriers) // 3], extra[::2]]))
    kept = analyse_geometric(v, adj, KEY, ["planes"], placement, chosen=(kept_sel, kept_hash))["planes"]
    # then the rings of a few kept carriers are laid on a line, and those of a tenth of the extra
    # ones made far coarser (the median of the scale test moves): the moved vertices are no carrier,
    # and the kept rows with a moved neighbour are read again, as the embedder's rounds do
    flat, coarse = kept.carriers[:: 97][:20], extra[1::2][: len(extra) // 10]
    fixed = np.zeros(len(v), bool)
    fixed[np.concatenate([kept_sel, extra])] = True
    moved = np.zeros(len(v), bool)
    for c in flat:
        ring = adj.indices[adj.indptr[c]:adj.indptr[c + 1]]
        line = v[c] + np.linspace(-1e-2, 1e-2, len(ring))[:, None] * np.array([1.0, 0.3, -0.2])
        v[ring[~fixed[ring]]] = line[~fixed[ring]]
        moved[ring[~fixed[ring]]] = True
    ring = adj.indices[adj.ring_entries(coarse)[1]]
    ring = ring[~fixed[ring]]
    v[ring] += 0.05 * rng.normal(size=(len(ring), 3))
    moved[ring] = True
    near = np.zeros(len(v), bool)
    near[adj.indices[adj.ring_entries(np.flatnonzero(moved))[1]]] = True
    _refresh(kept, v, adj, np.flatnonzero(near[kept.carriers]), "planes", TOL)
    sel, hashes = read(np.concatenate([a.carriers[len(a.carriers) // 3:], extra]))
    got = geometric_read([kept], v, adj, (sel, hashes))
    want = analyse_geometric(v, adj, KEY, ["planes"], placement, chosen=(sel, hashes))["planes"]
    dropped = np.setdiff1d(sel, want.carriers)
    assert np.isin(flat, dropped).sum() >= 5 and np.isin(coarse, dropped).any()
    assert got.geometric and got.signed is None
    for name in ("carriers", "slot_hash", "z", "mu", "axes", "lam", "scale"):
        assert np.array_equal(getattr(got, name), getattr(want, name)), name
