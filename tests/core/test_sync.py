"""core.sync: connectivity labels and the keyed maximal independent set of carriers."""

from __future__ import annotations

import threading
from dataclasses import replace

import numpy as np
import trimesh

from core.analysis import analyse
from core.formats import read_mesh
from core.mesh import adjacency
from core.sync import (
    MAX_DEGREE,
    ROUND_STEPS,
    is_regular,
    select_carriers,
    stepped_labels,
    tie_broken,
    vertex_labels,
    wl_colours,
)
from tests.conftest import shared_mesh_path
from tests.core.formats.helpers import OCTAHEDRON, TETRAHEDRON
from tests.core.meshes import irregular_sphere, similarity


def test_highest_priority_wins_then_the_next_independent_one() -> None:
    """Octahedron: vertex 5 has the highest priority; the only vertex not next to it is its
    opposite, 4, which joins in the next round although its priority is low."""
    adj = adjacency(OCTAHEDRON.faces, 6)
    chosen = select_carriers(adj, np.array([5, 1, 2, 3, 4, 6], np.uint64), np.ones(6, bool))
    assert chosen.tolist() == [4, 5]


def test_equal_priorities_never_win_against_each_other() -> None:
    adj = adjacency(TETRAHEDRON.faces, 4)
    assert select_carriers(adj, np.full(4, 9, np.uint64), np.ones(4, bool)).size == 0
    # an unusable vertex neither carries nor blocks its neighbours
    usable = np.array([True, True, True, False])
    assert select_carriers(adj, np.array([1, 2, 3, 99], np.uint64), usable).tolist() == [2]


def test_carriers_form_a_maximal_independent_set() -> None:
    v, f = irregular_sphere(800, 3)
    adj = adjacency(f, len(v))
    priority = np.random.default_rng(0).permutation(len(v)).astype(np.uint64) + np.uint64(1)  # distinct
    chosen = select_carriers(adj, priority, np.ones(len(v), bool))
    taken = np.zeros(len(v), bool)
    taken[chosen] = True
    neighbours_taken = np.bincount(adj.rows, taken[adj.indices], minlength=len(v))
    assert not (taken & (neighbours_taken > 0)).any()  # independent
    assert (taken | (neighbours_taken > 0)).all()  # maximal: every other vertex touches a carrier


def test_labels_ignore_numbering_and_geometry() -> None:
    v, f = irregular_sphere(500, 1)
    adj = adjacency(f, len(v))
    colours = wl_colours(adj, 3)
    perm = np.random.default_rng(1).permutation(len(v))
    inverse = np.argsort(perm)
    moved = adjacency(inverse[f], len(v))  # vertex i is now vertex inverse[i]
    assert np.array_equal(wl_colours(moved, 3)[inverse], colours)
    labels = vertex_labels(v, adj)
    assert not labels.regular and np.array_equal(labels.labels, colours)
    assert np.array_equal(vertex_labels(v * 3 + 1, adj).labels, labels.labels)


def test_usable_vertices_by_valence() -> None:
    adj = adjacency(TETRAHEDRON.faces, 4)  # valence 3, closed: below the minimum of 4
    assert not vertex_labels(TETRAHEDRON.vertices, adj).usable.any()
    adj = adjacency(OCTAHEDRON.faces, 6)
    assert vertex_labels(OCTAHEDRON.vertices, adj).usable.all()
    assert MAX_DEGREE == 12


def test_stepped_labels_are_the_neighbouring_refinement_steps() -> None:
    """What the detector reads when a crop's refinement stopped a step before or after the
    whole's: the colours of the next or previous step of ROUND_STEPS (none past either end), the
    fallback decided anew."""
    v, f = irregular_sphere(3000, 4)
    adj = adjacency(f, len(v))
    labels = vertex_labels(v, adj)
    assert labels.rounds == ROUND_STEPS[0] and not labels.regular
    wider = stepped_labels(v, adj, labels, 1)
    assert wider is not None and wider.rounds == ROUND_STEPS[1] and not wider.regular
    assert np.array_equal(wider.connectivity, wl_colours(adj, ROUND_STEPS[1]))
    assert np.array_equal(wider.labels, wider.connectivity) and np.array_equal(wider.usable, labels.usable)
    assert not np.array_equal(wider.labels, labels.labels)
    assert stepped_labels(v, adj, labels, -1) is None
    back = stepped_labels(v, adj, wider, -1)
    assert back is not None and back.rounds == labels.rounds and np.array_equal(back.labels, labels.labels)
    assert stepped_labels(v, adj, replace(labels, rounds=ROUND_STEPS[-1]), 1) is None
    m = trimesh.creation.icosphere(subdivisions=3)  # regular: the geometric fallback at every step
    iv = np.asarray(m.vertices)
    iadj = adjacency(m.faces, len(iv))
    ico = vertex_labels(iv, iadj)
    assert ico.regular and ico.rounds == ROUND_STEPS[-1] and stepped_labels(iv, iadj, ico, 1) is None
    below = stepped_labels(iv, iadj, ico, -1)
    assert below is not None and below.regular and below.rounds == ROUND_STEPS[-2]
    assert np.array_equal(below.connectivity, wl_colours(iadj, ROUND_STEPS[-2]))
    assert np.unique(below.labels).size > 0.5 * len(iv)


def test_subdivided_meshes_are_regular_and_use_the_geometric_fallback() -> None:
    """An icosphere has 2 connectivity classes (valence 5 and 6) however many rings are used; its
    labels then depend on position, and are kept for vertices whose neighbours did not move."""
    m = trimesh.creation.icosphere(subdivisions=3)
    v = np.asarray(m.vertices)
    adj = adjacency(m.faces, len(v))
    labels = vertex_labels(v, adj)
    assert labels.regular and np.unique(labels.connectivity).size < 0.1 * len(v)
    assert np.unique(labels.labels).size > 0.5 * len(v)
    assert is_regular(labels.connectivity, labels.usable)
    again = vertex_labels(v, adj, labels)  # same geometry: the same labels
    assert np.array_equal(again.labels, labels.labels)


def test_ties_are_broken_by_pose_invariant_geometry() -> None:
    """Equal priorities on neighbours: the tie-break (distance of the neighbour mean to the
    centroid) picks one of them, and the same one after a similarity transform with re-ordering."""
    v, f = irregular_sphere(3000, 11)
    adj = adjacency(f, len(v))
    tied = np.full(len(v), np.uint64(1) << np.uint64(40))  # every vertex tied with every neighbour
    assert select_carriers(adj, tied, np.ones(len(v), bool)).size == 0
    chosen = select_carriers(adj, tie_broken(tied, v, adj), np.ones(len(v), bool))
    assert chosen.size > 0.1 * len(v)
    rng = np.random.default_rng(5)
    v2, f2 = similarity(v, f, rng)
    adj2 = adjacency(f2, len(v2))
    chosen2 = select_carriers(adj2, tie_broken(tied, v2, adj2), np.ones(len(v2), bool))
    # similarity() permutes vertices: compare the chosen positions, normalised back
    key = np.round(np.sort(np.linalg.norm(v[chosen] - v.mean(axis=0), axis=1)), 9)
    radius = np.linalg.norm(v - v.mean(axis=0), axis=1).max()
    scale = np.linalg.norm(v2 - v2.mean(axis=0), axis=1).max() / radius
    key2 = np.round(np.sort(np.linalg.norm(v2[chosen2] - v2.mean(axis=0), axis=1)) / scale, 9)
    assert np.array_equal(key, key2)


def test_cad_meshes_keep_their_connectivity_labels_and_surfaces_of_revolution_do_not() -> None:
    """The CAD STL soup (26 % distinct labels, but 11k of them) and the gear keep connectivity
    labels (found after a rotation); the capsule's rings tie every neighbour: geometric fallback."""
    for name, regular in (("counter.unitsmm.STL", False), ("cycloidal.ply", False), ("capsule.obj", True)):
        doc = read_mesh(shared_mesh_path(name).read_bytes(), name)
        part = doc.parts[0]
        adj = adjacency(part.faces, len(part.vertices))
        assert vertex_labels(part.vertices, adj).regular is regular, name
        if not regular:
            a = analyse(part.vertices, part.faces, "k", "planes")
            assert len(a.carriers) >= 0.1 * len(part.vertices), name


def test_colour_refinement_in_two_row_halves_is_the_one_thread_refinement(monkeypatch) -> None:
    # a large mesh refines its colours in two row halves, the second in the rows' worker: the same
    # colours bit for bit, also when resumed from fewer rounds; and a block of the ring matrix gives
    # its rows of the whole product
    import core.parallel as parallel
    import core.sync as sync

    v, f = irregular_sphere(6000, 4)
    adj = adjacency(f, len(v))
    monkeypatch.setattr(sync, "SPLIT_FROM", 10**9)
    one, three = wl_colours(adj, 9), wl_colours(adj, 3)
    monkeypatch.setattr(sync, "SPLIT_FROM", 1000)
    monkeypatch.setattr(parallel, "SPLIT_FROM", 1000)
    seen: set[str] = set()
    real = parallel.by_chunks

    def spy(fn, total, size, split_from=None):
        def where(lo, hi):
            seen.add(threading.current_thread().name[:13])
            return fn(lo, hi)
        return real(where, total, size, split_from)

    monkeypatch.setattr(sync, "by_chunks", spy)
    assert np.array_equal(wl_colours(adj, 9), one)
    assert np.array_equal(wl_colours(adj, 9, three, 3), one)
    assert seen == {"MainThread", "meshmark-rows"}
    x = np.random.default_rng(2).integers(0, 2**63, len(v), dtype=np.uint64)
    whole = adj.ring_sum_u64(x)
    for lo, hi in ((0, 2500), (2500, len(v)), (100, 101)):
        assert np.array_equal(adj.ring_block(lo, hi) @ x, whole[lo:hi])
