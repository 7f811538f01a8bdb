"""core.mesh on tiny meshes with known answers: adjacency, boundary and non-manifold flags,
neighbour-only moments, bounding box."""

from __future__ import annotations

import numpy as np

from core.mesh import adjacency, bbox_diagonal, edge_lengths, neighbour_moments
from tests.core.formats.helpers import SQUARE, TETRAHEDRON


def test_tetrahedron_every_vertex_sees_the_three_others() -> None:
    adj = adjacency(TETRAHEDRON.faces, 4)
    assert adj.degree.tolist() == [3, 3, 3, 3]
    assert [sorted(adj.indices[adj.indptr[i]:adj.indptr[i + 1]].tolist()) for i in range(4)] == [
        [1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]]
    assert not adj.boundary.any() and not adj.nonmanifold.any()


def test_square_is_all_boundary_with_one_interior_edge() -> None:
    adj = adjacency(SQUARE.faces, 4)  # triangles (0 1 2), (0 2 3): the diagonal 0-2 is shared
    assert adj.degree.tolist() == [3, 2, 3, 2]
    assert adj.boundary.all() and not adj.nonmanifold.any()
    assert adj.rows.tolist() == [0, 0, 0, 1, 1, 2, 2, 2, 3, 3]


def test_an_edge_of_three_faces_is_non_manifold() -> None:
    faces = np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4]])
    adj = adjacency(faces, 6)  # vertex 5 is isolated
    assert adj.nonmanifold.tolist() == [True, True, False, False, False, False]
    assert adj.degree[5] == 0


def test_ring_entries_and_sums() -> None:
    adj = adjacency(SQUARE.faces, 4)
    first, pos = adj.ring_entries(np.array([1, 3]))
    assert first.tolist() == [0, 2] and adj.indices[pos].tolist() == [0, 2, 0, 2]
    assert adj.ring_sum_u64(np.array([1, 10, 100, 1000], np.uint64)).tolist() == [1110, 101, 1011, 101]


def test_moments_of_a_regular_hexagon_ring() -> None:
    """Centre vertex 0 lifted off the plane of a hexagon of radius 2: the moments ignore it, the
    mean is the hexagon's centre and the covariance diag(r^2/2, r^2/2, 0)."""
    angles = np.arange(6) * np.pi / 3
    ring = np.stack([2 * np.cos(angles), 2 * np.sin(angles), np.zeros(6)], axis=1) + [5.0, -1.0, 3.0]
    vertices = np.vstack([[5.0, -1.0, 7.0], ring])
    faces = np.array([[0, 1 + k, 1 + (k + 1) % 6] for k in range(6)])
    mu, sigma = neighbour_moments(vertices, adjacency(faces, 7), np.array([0]))
    assert np.allclose(mu, [[5.0, -1.0, 3.0]])
    assert np.allclose(sigma[0], np.diag([2.0, 2.0, 0.0]))


def test_lengths_and_diagonal() -> None:
    adj = adjacency(SQUARE.faces, 4)
    assert sorted(np.round(edge_lengths(SQUARE.vertices, adj), 6).tolist()) == [1, 1, 1, 1, round(2**0.5, 6)]
    assert bbox_diagonal(TETRAHEDRON.vertices) == 3**0.5 and bbox_diagonal(np.zeros((0, 3))) == 0.0


def test_the_least_variance_axis_is_turned_to_the_side_the_faces_call_outside() -> None:
    """``oriented``: on an outward-wound closed surface every ring's e1 points away from the centre,
    on the same surface wound the other way towards it, and the vertex's own position never enters."""
    from core.analysis import analyse
    from core.eig3 import eigh3
    from core.mesh import oriented
    from tests.core.meshes import irregular_sphere

    v, f = irregular_sphere(800, 3)
    sel = analyse(v, f, "key", "planes").carriers  # an independent set: no ring holds another
    assert len(sel) > 100
    for faces, side in ((f, 1.0), (f[:, ::-1], -1.0)):
        adj = adjacency(faces, len(v))
        mu, sigma = neighbour_moments(v, adj, sel)
        axes = oriented(v, adj, sel, mu, eigh3(sigma)[1])
        outward = np.einsum("ki,ki->k", axes[:, :, 0], mu) * side
        assert (outward > 0).all()
        # the vertices themselves moved far along their axes, to either side: the same orientation
        moved = v.copy()
        moved[sel] += 0.3 * np.where(np.arange(len(sel)) % 2 == 0, 1.0, -1.0)[:, None] * axes[:, :, 0]
        assert np.array_equal(oriented(moved, adj, sel, mu, axes.copy()), axes)
        flipped = axes.copy()
        flipped[:, :, 0] *= -1  # whatever sign the eigen-solver gave
        assert np.array_equal(oriented(v, adj, sel, mu, flipped), axes)


def test_rows_split_over_two_threads_give_the_same_arrays(monkeypatch) -> None:
    # ring boundaries of many vertices in chunks, every other one in the worker thread: bit for bit
    # what one call in this thread gives, in the order of the rows
    import core.parallel as parallel
    from core.analysis import ring_boundaries
    from tests.core.meshes import irregular_sphere

    v, f = irregular_sphere(20000, 7)
    adj = adjacency(f, len(v))
    sel = np.random.default_rng(1).permutation(len(v))[:15000]
    monkeypatch.setattr(parallel, "SPLIT_FROM", 10**9)
    one = ring_boundaries(v, adj, sel)
    monkeypatch.setattr(parallel, "SPLIT_FROM", 1000)
    monkeypatch.setattr(parallel, "CHUNK_ROWS", 1024)
    two = ring_boundaries(v, adj, sel)
    for a, b in zip(one, two, strict=True):
        assert np.array_equal(a, b)


def test_ring_sum_adds_the_neighbours_in_the_order_bincount_does() -> None:
    from tests.core.meshes import irregular_sphere

    v, f = irregular_sphere(3000, 2)
    adj = adjacency(f, len(v))
    rng = np.random.default_rng(0)
    x = rng.normal(size=len(v)) * 10.0 ** rng.integers(-8, 8, len(v))
    want = np.bincount(adj.rows, x[adj.indices], minlength=len(v))
    assert np.array_equal(adj.ring_sum(x), want)
    # columns at once: each as it is alone
    cols = np.stack([x, -3.0 * x[::-1], np.sqrt(np.abs(x))], axis=1)
    assert np.array_equal(adj.ring_sum(cols), np.stack([adj.ring_sum(c) for c in cols.T], axis=1))
    # a vertex of no face sums to 0
    assert adjacency(f, len(v) + 1).ring_sum(np.append(x, 1.0))[-1] == 0.0


def test_within_is_the_ring_distance_from_the_seeds() -> None:
    """``Adjacency.within(seeds, k)`` is every vertex at most ``k`` edges from a seed (graph
    distance by scipy's breadth-first search), for k = 0..5 and seeds anywhere or nowhere."""
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import shortest_path

    from tests.core.meshes import irregular_sphere

    v, f = irregular_sphere(800, 3)
    adj = adjacency(f, len(v))
    graph = csr_matrix((np.ones(len(adj.indices)), adj.indices, adj.indptr), shape=(len(v), len(v)))
    rng = np.random.default_rng(1)
    for n_seeds in (0, 1, 5):
        seeds = np.zeros(len(v), bool)
        seeds[rng.choice(len(v), n_seeds, replace=False)] = True
        dist = shortest_path(graph, unweighted=True, indices=np.flatnonzero(seeds)).min(axis=0) \
            if n_seeds else np.full(len(v), np.inf)
        for k in range(6):
            assert np.array_equal(adj.within(seeds, k), dist <= k)
