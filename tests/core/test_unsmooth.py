"""Undoing uniform Laplacian smoothing (core.unsmooth) and reading a mark through it."""

from __future__ import annotations

import numpy as np
import pytest

import core.pipeline as pipeline
from core import unsmooth
from core.analysis import Analysis, analyse_methods
from core.api import detect_file, detect_mesh, embed_file, embed_mesh
from core.formats import read_mesh
from core.mesh import adjacency, edge_lengths
from tests.conftest import shared_mesh_path
from tests.core.meshes import irregular_sphere

PAYLOAD = "10110011100011110000101011001010"


def _smooth(v: np.ndarray, f: np.ndarray, n: int, lam: float = 0.1) -> np.ndarray:
    """The attack, written independently of the module: ``V += lam (mean(N(V)) - V)``, n times."""
    m = len(v)
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    e = np.unique(np.sort(e, axis=1), axis=0)
    a, b = np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]]
    deg = np.bincount(a, minlength=m).astype(np.float64)
    out = np.asarray(v, np.float64).copy()
    for _ in range(n):
        mean = np.stack([np.bincount(a, out[b, c], minlength=m) for c in range(3)], axis=1)
        has = deg > 0
        out[has] += lam * (mean[has] / deg[has, None] - out[has])
    return out


def _ply(v: np.ndarray, f: np.ndarray) -> bytes:
    head = ("ply\nformat binary_little_endian 1.0\n"
            f"element vertex {len(v)}\nproperty double x\nproperty double y\nproperty double z\n"
            f"element face {len(f)}\nproperty list uchar int vertex_indices\nend_header\n").encode()
    faces = np.zeros(len(f), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    faces["n"], faces["i"] = 3, f
    return head + np.ascontiguousarray(v, "<f8").tobytes() + faces.tobytes()


def test_coefficients_are_the_inverse_gain() -> None:
    """The Chebyshev series equals (1 - 0.1 k)^-n over the whole spectrum [0, 2], to within the
    truncation's share of the largest gain (and, where the gain is small, the smooth shape's, to
    within a scale error of the order of 1e-6 that the dimensionless statistics do not see)."""
    k = np.linspace(0.0, 2.0, 401)
    for n in (1, 10, 30, 57.5, 95):
        c = unsmooth.coefficients(n)
        got = np.polynomial.chebyshev.chebval(k - 1.0, c)
        want = (1.0 - 0.1 * k) ** -n
        assert np.abs(got - want).max() < 1e-12 * want.max(), n
        assert np.abs(got / want - 1.0).max() < (1e-6 if n <= 60 else 3e-5), n
    assert len(unsmooth.coefficients(30)) < 30  # the series is short: one product per term


@pytest.mark.parametrize("n", [7, 30, 64])
def test_unsmooth_undoes_the_smoothing(n: int) -> None:
    """n iterations smoothed, then undone: the positions come back (stored in double precision)."""
    v, f = irregular_sphere(800, n)
    adj = adjacency(f, len(v))
    back = unsmooth.unsmooth(_smooth(v, f, n), adj, n)
    edge = float(np.median(edge_lengths(v, adj)))
    assert np.abs(back - v).max() < 1e-6 * edge
    # a wrong number of iterations does not: the check above can fail
    assert np.abs(unsmooth.unsmooth(_smooth(v, f, n), adj, n + 3) - v).max() > 1e-3 * edge


def test_rings_only_and_isolated_vertices() -> None:
    """Returning some vertices gives the same values as all of them; a vertex without neighbours
    (which smoothing leaves alone) is returned as it is."""
    v, f = irregular_sphere(300, 2)
    v = np.vstack([v, [[5.0, 5.0, 5.0]]])  # isolated
    adj = adjacency(f, len(v))
    walk = unsmooth.walk_matrix(adj)
    assert np.allclose(np.asarray(walk.sum(axis=1)).ravel()[:-1], 1.0)
    smoothed = _smooth(v, f, 20)
    every = unsmooth.unsmooth_at(smoothed, walk, [12, 20])
    some = np.array([0, 17, len(v) - 1])
    part = unsmooth.unsmooth_at(smoothed, walk, [12, 20], some)
    assert np.array_equal(part, every[:, some])
    assert np.array_equal(every[1, -1], [5.0, 5.0, 5.0])
    assert np.abs(every[1, :-1] - v[:-1]).max() < 1e-9


def _analysis(carriers: np.ndarray, hashes: np.ndarray) -> Analysis:
    k = len(carriers)
    return Analysis(carriers, hashes, np.zeros(k), np.zeros((k, 3)), np.zeros((k, 3, 3)), np.zeros((k, 3)),
                    np.ones(k), False)


def test_score_counts_a_label_once() -> None:
    """Carriers of one label share their slot and read alike; repeating them (as regular regions
    and CAD models do) must not look like agreement: the score has one vote per label."""
    rng = np.random.default_rng(3)
    k = 3000
    hashes = rng.integers(0, 2**63, k, dtype=np.uint64)
    z = rng.normal(size=k)
    lengths = [76, 92, 140]
    alone = unsmooth.Scorer([_analysis(np.arange(k), hashes)], lengths).scores([[z]])[0]
    # every label of the first 1000 carriers repeated 10 times, with its vote
    rep = np.r_[np.arange(k), np.repeat(np.arange(1000), 10)]
    repeated = unsmooth.Scorer([_analysis(np.arange(len(rep)), hashes[rep])], lengths).scores([[z[rep]]])[0]
    assert abs(alone) < 5.0 and abs(repeated) < 5.0
    # counted one by one, the same repeated votes agree by far more (what the score avoids)
    votes = unsmooth._votes(z[rep])
    slots = (hashes[rep] % np.uint64(140)).astype(np.int64)
    sums = np.bincount(slots, votes, minlength=140)
    n = np.bincount(slots, minlength=140).astype(np.float64)
    naive = ((sums**2).sum() - (votes**2).sum()) / ((votes**2).mean() * np.sqrt(2 * (n * (n - 1)).sum()))
    assert naive > 10.0


def test_score_sees_the_codeword() -> None:
    """Votes that follow a slot's bit score far above random ones, at their codeword length."""
    rng = np.random.default_rng(4)
    k = 4000
    hashes = rng.integers(0, 2**63, k, dtype=np.uint64)
    bits = rng.integers(0, 2, 140) * 2.0 - 1.0
    z = 0.3 * bits[(hashes % np.uint64(140)).astype(np.int64)] + rng.normal(size=k)
    scorer = unsmooth.Scorer([_analysis(np.arange(k), hashes)], [76, 140, 300])
    assert scorer.scores([[z]])[0] > 10.0
    assert unsmooth.Scorer([_analysis(np.arange(k), hashes)], [76, 300]).scores([[z]])[0] < 5.0


def test_scores_of_many_positions_are_each_positions_score() -> None:
    """The scorer reads several positions in one pass; each position's figure is the one it reads
    alone, bit for bit (the choice of n compares them)."""
    rng = np.random.default_rng(5)
    k = 2500
    hashes = rng.integers(0, 2**63, k, dtype=np.uint64)[rng.integers(0, 1800, k)]  # labels repeat
    parts = (hashes[:1000], hashes[1000:])
    scorer = unsmooth.Scorer([_analysis(np.arange(len(h)), h) for h in parts], [40, 76, 140, 141, 300])
    bits = rng.integers(0, 2, 300) * 2.0 - 1.0
    zs = [[rng.normal(size=1000), rng.normal(size=1500)] for _ in range(6)]
    zs[2] = [z + 0.4 * bits[(h % np.uint64(140)).astype(np.int64)] for z, h in zip(zs[2], parts, strict=True)]
    zs[4] = [np.full(1000, 0.3), np.full(1500, 0.3)]  # every vote alike: no agreement, no warning
    together = scorer.scores(zs)
    assert together == [scorer.scores([z])[0] for z in zs]
    assert together[2] > 10.0 > max(together[:2] + together[3:])
    assert together[4] == 0.0


def test_ring_mesh_reads_every_part_as_its_own_mesh() -> None:
    """Two meshes' carriers on their rings' mesh: the statistics at any positions are those of
    each whole mesh, bit for bit (the same neighbours in the same order, the same face for the
    orientation), and only the rings' positions count."""
    rng = np.random.default_rng(6)
    meshes = [irregular_sphere(700, 1), irregular_sphere(400, 2)]
    adjs = [adjacency(f, len(v)) for v, f in meshes]
    carriers = [np.sort(rng.choice(len(v), 60, replace=False)) for v, _ in meshes]
    rings, local, sel = unsmooth.ring_mesh(adjs, carriers)
    assert len(rings) < sum(len(v) for v, _ in meshes)
    moved = [v + 0.01 * rng.normal(size=v.shape) for v, _ in meshes]
    methods = ["planes", "ellipsoids"]
    alone = [unsmooth._statistics(v, adj, c, methods, unsmooth.TOL)
             for v, adj, c in zip(moved, adjs, carriers, strict=True)]
    on_rings = unsmooth._statistics(np.concatenate(moved)[rings], local, sel, methods, unsmooth.TOL)
    for m in methods:
        assert np.array_equal(on_rings[m], np.concatenate([a[m] for a in alone]))
        assert np.count_nonzero(on_rings[m]) > 100


@pytest.fixture(scope="module")
def marked_sphere() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    v, f = irregular_sphere(6000, 1)
    marked, _ = embed_mesh(v, f, "k", payload=PAYLOAD, method="planes")
    return v, f, marked


def test_smoothed_mark_reads_after_unsmoothing(marked_sphere, monkeypatch) -> None:
    """Smoothed 0.1 x 30, the mark reads on the unsmoothed mesh (and not without it); the
    false-positive figure counts both files read."""
    _, f, marked = marked_sphere
    untouched = detect_mesh([(marked, f)], "k")
    res = detect_mesh([(_smooth(marked, f, 30), f)], "k")
    assert res.detected and res.payload == PAYLOAD and res.unsmoothed is not None
    assert abs(res.unsmoothed - 30) <= 3
    assert res.false_positive_probability == pytest.approx(2 * untouched.false_positive_probability)
    assert untouched.unsmoothed is None
    monkeypatch.setattr(pipeline, "_unsmoothed", lambda *a, **k: None)
    assert not detect_mesh([(_smooth(marked, f, 30), f)], "k").detected


def test_no_mark_no_unsmoothed_reading(marked_sphere) -> None:
    """An unmarked smoothed mesh and a wrong key: nothing read, and the carriers' votes never agree
    enough for the unsmoothed mesh to be decoded."""
    v, f, marked = marked_sphere
    assert not detect_mesh([(_smooth(v, f, 30), f)], "k").detected
    assert not detect_mesh([(_smooth(marked, f, 30), f)], "other key").detected
    for key in ("k", "k2", "k3"):
        adj = adjacency(f, len(v))
        local = analyse_methods(_smooth(v, f, 30), f, key, ["planes", "ellipsoids"], adj=adj)
        _, score = unsmooth.choose_iterations([(_smooth(v, f, 30), adj)], {m: [a] for m, a in local.items()},
                                              pipeline._codeword_lengths(None))
        assert score < unsmooth.MIN_SCORE


@pytest.mark.parametrize("method", ["planes", "ellipsoids"])
def test_bunny_smoothed_30_times(method: str) -> None:
    """The shared bunny at the default strength and RMS budget: 0.1 x 30 read on the unsmoothed
    file (before: 36-49 % of the carriers on the wrong side, not read)."""
    path = shared_mesh_path("bun_zipper.ply")
    # the benchmark's key (bench/engine_table.py): with it both methods keep the RMS budget
    key = "meshmark-issue14-key"
    out = embed_file(path.read_bytes(), key, filename=path.name, payload=PAYLOAD, method=method)
    assert out.report.rms_displacement <= 2e-4
    part = read_mesh(out.data, path.name).parts[0]
    res = detect_file(_ply(_smooth(part.vertices, part.faces, 30), part.faces), key, filename="s.ply")
    assert res.detected and res.payload == PAYLOAD and res.unsmoothed is not None
    # 1.99e-6 before the interior view (2ccab0d), 2.14e-6 with it: the bunny has holes, so the detector
    # has one more view to try and the union bound counts it (30/28 of the views)
    assert res.false_positive_probability < 3e-6
    if method == "planes":
        assert res.unsmoothed == 30  # the exact inverse: the carriers agree best there
