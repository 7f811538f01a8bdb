"""Undoing one subdivision step (core.resample) and reading a mark through it."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from trimesh import remesh

from core.api import detect_mesh, embed_mesh
from core.resample import undo_subdivision
from tests.conftest import shared_mesh_path
from tests.core.meshes import irregular_sphere, similarity, sqrt3_subdivide


def _subdivide(v: np.ndarray, f: np.ndarray, scheme: str) -> tuple[np.ndarray, np.ndarray]:
    if scheme == "midpoint":
        return remesh.subdivide(v, f)
    if scheme == "sqrt3":
        return sqrt3_subdivide(v, f)
    return remesh.subdivide_loop(v, f, iterations=1)


def _open_patch(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """An irregular sphere with a cap of faces removed: a mesh with a boundary."""
    v, f = irregular_sphere(300, seed)
    keep = v[f].mean(axis=1)[:, 2] < 0.6
    f = f[keep]
    used = np.unique(f)
    remap = np.full(len(v), -1)
    remap[used] = np.arange(len(used))
    return v[used], remap[f]


def _same_mesh(v1: np.ndarray, f1: np.ndarray, v2: np.ndarray, f2: np.ndarray, tol: float) -> bool:
    """Same triangles (as sets of corner positions, orientation included) up to vertex order."""
    def canon(v: np.ndarray, f: np.ndarray) -> np.ndarray:
        corners = v[f]  # (m, 3, 3)
        # rotate each triangle so that its lexicographically smallest corner comes first
        first = np.lexsort(corners.transpose(2, 0, 1)[::-1], axis=1)[:, 0]
        rolled = np.stack([np.roll(c, -k, axis=0) for c, k in zip(corners, first, strict=True)])
        flat = rolled.reshape(len(f), 9)
        return flat[np.lexsort(flat.T[::-1])]

    a, b = canon(v1, f1), canon(v2, f2)
    return a.shape == b.shape and bool(np.abs(a - b).max() <= tol)


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 10_000), scheme=st.sampled_from(["midpoint", "loop", "sqrt3"]),
       open_=st.booleans())
def test_undo_gives_back_the_coarse_mesh(seed: int, scheme: str, open_: bool) -> None:
    """Whatever the vertex and face order of the subdivided mesh, the coarse mesh comes back
    (Loop and sqrt(3): its positions to rounding, from the new vertices alone), boundaries included
    for the 1-to-4 schemes (the sqrt(3) attack's boundary rule is a simplification: closed only)."""
    open_ = open_ and scheme != "sqrt3"
    v, f = _open_patch(seed) if open_ else irregular_sphere(200, seed)
    fine_v, fine_f = _subdivide(v, f, scheme)
    rng = np.random.default_rng(seed)
    perm = rng.permutation(len(fine_v))
    inv = np.argsort(perm)
    fine_v, fine_f = fine_v[perm], inv[fine_f][rng.permutation(len(fine_f))]
    fine_f = np.roll(fine_f, int(rng.integers(0, 3)), axis=1)  # same orientation, other first corner
    undone = undo_subdivision(fine_v, fine_f)
    assert undone is not None
    got_scheme, cv, cf = undone
    assert got_scheme == scheme
    assert _same_mesh(v, f, cv, cf, tol=1e-9)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_midpoint_step_of_a_mesh_with_fins_comes_back_whole(seed: int) -> None:
    """Edges of four faces (CAD sheets meeting along an edge: 242 on the cycloidal gear) carry no
    valence that tells even vertices from odd: the midpoint step is undone whole, every vertex
    and face of the coarse mesh back (the gear lost 1,107 of 21,384 vertices to contradictory
    labels, and its mark with them)."""
    v, f = irregular_sphere(400, seed)
    rng = np.random.default_rng(seed)
    # fins: two triangles on each of some edges, sticking out along the normal
    edges = f[rng.choice(len(f), 12, replace=False)][:, :2]
    extra_v, extra_f = [], []
    for a, b in edges:
        mid = 0.5 * (v[a] + v[b])
        for side in (1.0, -1.0):
            tip = mid * (1.3 + 0.05 * side) + side * 0.02 * (v[b] - v[a])
            extra_v.append(tip)
            k = len(v) + len(extra_v) - 1
            extra_f.append([a, b, k] if side > 0 else [b, a, k])
    v = np.vstack([v, np.array(extra_v)])
    f = np.vstack([f, np.array(extra_f)])
    fine_v, fine_f = remesh.subdivide(v, f)
    undone = undo_subdivision(fine_v, fine_f)
    assert undone is not None
    scheme, cv, cf = undone
    assert scheme == "midpoint"
    assert len(cv) == len(v) and _same_mesh(v, f, cv, cf, tol=1e-12)


def test_split_copies_of_a_solved_vertex_are_one_again() -> None:
    """Coarse vertices solved within MERGE_TOL of each other and not neighbours are one vertex
    the subdivider split (trimesh's Loop, on the gear's four-face edges: 294 of 21,384 twice);
    neighbours that close stay apart."""
    from core.resample import _merged

    v, f = irregular_sphere(300, 4)
    # split vertex 7: the faces on one side of it use a copy 1e-12 away
    copy = len(v)
    ring = np.flatnonzero((f == 7).any(axis=1))
    split = f.copy()
    split[ring[: len(ring) // 2]] = np.where(f[ring[: len(ring) // 2]] == 7, copy, f[ring[: len(ring) // 2]])
    sv = np.vstack([v, v[7] + 1e-12])
    mv, mf = _merged(sv, split)
    assert len(mv) == len(v) and _same_mesh(v, f, mv, mf, tol=0.0)
    # a neighbour moved onto vertex 7 is not merged
    nb = int(f[ring[0]][f[ring[0]] != 7][0])
    close = v.copy()
    close[nb] = v[7] + 1e-12
    cv, cf = _merged(close, f)
    assert len(cv) == len(v) and len(cf) == len(f)


def test_meshes_that_are_not_subdivided_are_left_alone() -> None:
    v, f = irregular_sphere(400, 3)
    assert undo_subdivision(v, f) is None
    # two steps: undoing one gives a mesh that is itself one step of the original
    fine_v, fine_f = _subdivide(*_subdivide(v, f, "midpoint"), "midpoint")
    once = undo_subdivision(fine_v, fine_f)
    assert once is not None and len(once[2]) == 4 * len(f)
    # one edge flipped (a writer's retriangulation of one quad): the rest is still read, with
    # the coarse faces around it (where the labels contradict each other) left out
    fv, ff = _subdivide(v, f, "midpoint")
    mesh = trimesh.Trimesh(fv, ff, process=False)
    a, b = mesh.face_adjacency[0]
    shared = mesh.face_adjacency_edges[0]
    ua, ub = (np.setdiff1d(ff[x], shared)[0] for x in (a, b))
    flipped = ff.copy()
    flipped[a] = [ua, ub, shared[0]]
    flipped[b] = [ub, ua, shared[1]]
    once = undo_subdivision(fv, flipped)
    assert once is not None and 0.95 * len(f) <= len(once[2]) < len(f)
    # simplified after the subdivision: no longer a 1-to-4 step anywhere near enough
    import fast_simplification

    sv, sf = fast_simplification.simplify(fv.astype(np.float64), ff.astype(np.int32), target_reduction=0.1)
    assert undo_subdivision(np.asarray(sv), np.asarray(sf, np.int64)) is None


@pytest.mark.parametrize("scheme", ["midpoint", "loop", "sqrt3"])
@pytest.mark.parametrize("method", ["ellipsoids", "planes"])
def test_mark_is_read_after_subdivision(scheme: str, method: str) -> None:
    """The payload of a marked mesh comes back after a subdivision step, with its vertices and
    faces re-ordered and a similarity applied; the report says which step was undone and counts
    the second view in the false-positive figure."""
    v, f = irregular_sphere(3000, 11)
    payload = "1011001110001111"
    marked, _ = embed_mesh(v, f, "resample-key", payload=payload, method=method)
    fine_v, fine_f = _subdivide(marked, f, scheme)
    direct = detect_mesh([(fine_v, fine_f)], "resample-key", method=method)
    assert direct.detected is False or direct.resampled is not None
    fine_v, fine_f = similarity(fine_v, fine_f, np.random.default_rng(5))
    res = detect_mesh([(fine_v, fine_f)], "resample-key", method=method)
    assert res.detected and res.payload == payload and res.resampled == scheme
    plain = detect_mesh([(marked, f)], "resample-key", method=method)
    assert res.false_positive_probability == pytest.approx(2 * plain.false_positive_probability)
    assert detect_mesh([(fine_v, fine_f)], "another-key", method=method).detected is False


@pytest.mark.parametrize("name", ["bun_zipper.ply", "fandisk.off"])
def test_real_mesh_read_after_loop_subdivision(name: str) -> None:
    mesh = trimesh.load(shared_mesh_path(name), force="mesh")
    v, f = np.asarray(mesh.vertices, float), np.asarray(mesh.faces, np.int64)
    payload = "10110011100011110000101011001010"
    marked, _ = embed_mesh(v, f, "real-resample", payload=payload)
    fine_v, fine_f = _subdivide(marked, f, "loop")
    res = detect_mesh([(fine_v, fine_f)], "real-resample")
    # read by the coarse view, or first by the geometric layer (the bunny has one: Loop's step keeps
    # enough of its carriers nearest their cells' centres)
    assert res.detected and res.payload == payload and (res.resampled == "loop" or res.layer == "geometry")
    undone = undo_subdivision(fine_v, fine_f)
    assert undone is not None and undone[0] == "loop"
    coarse = detect_mesh([(undone[1], undone[2])], "real-resample")
    assert coarse.detected and coarse.payload == payload and coarse.layer == "connectivity"
