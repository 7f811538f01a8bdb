"""Quick slice of the benchmark suite: attack invariants, metric sanity, one end-to-end pass."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest
import trimesh

from bench import attacks as A
from bench.common import bit_error_rate, parse_ply_double, write_obj, write_ply_double
from bench.metrics import Reliability, SurfaceIndex, ber, surface_distance
from tests.conftest import shared_mesh_path

ENGINE = importlib.util.find_spec("core.pipeline") is not None
needs_engine = pytest.mark.skipif(not ENGINE, reason="core/pipeline.py (the engine) has not landed yet")


@pytest.fixture(scope="module")
def sphere():
    m = trimesh.creation.icosphere(subdivisions=3)
    return np.asarray(m.vertices, np.float64), np.asarray(m.faces, np.int64)


@pytest.fixture(scope="module")
def bumpy(sphere):
    v, f = sphere
    rng = np.random.default_rng(1)
    return v * (1 + 0.03 * rng.standard_normal((len(v), 1))), f


def canonical_faces(v, f):
    """Faces as sets of positions, rotated so the smallest index leads (orientation kept)."""
    rows = np.round(v, 9)[f]  # (m, 3, 3)
    keys = [tuple(map(tuple, r)) for r in rows]
    out = set()
    for k in keys:
        i = min(range(3), key=lambda j: k[j])
        out.add(k[i:] + k[:i])
    return out


def edge_lengths(v, f):
    e = A.unique_edges(f)
    return np.linalg.norm(v[e[:, 0]] - v[e[:, 1]], axis=1)


def test_similarity_preserves_edge_ratios(bumpy):
    v, f = bumpy
    v2, f2 = A.similarity(v, f, 1, np.random.default_rng(3))
    assert np.array_equal(f2, f)
    r = edge_lengths(v2, f) / edge_lengths(v, f)
    assert np.allclose(r, r[0], rtol=1e-9)
    assert 0.1 <= r[0] <= 10
    assert not np.allclose(v2, v)


def test_reorder_preserves_face_set(bumpy):
    v, f = bumpy
    v2, f2 = A.reorder(v, f, 1, np.random.default_rng(4))
    assert sorted(map(tuple, v2)) == sorted(map(tuple, v))
    assert not np.array_equal(v2, v)
    assert canonical_faces(v2, f2) == canonical_faces(v, f)


def test_uniform_noise_bounded(bumpy):
    v, f = bumpy
    level = 0.005
    v2, _ = A.uniform_noise(v, f, level, np.random.default_rng(5))
    amp = level * A.mean_centroid_distance(v)
    d = np.abs(v2 - v)
    assert d.max() <= amp + 1e-15 and d.max() > 0.5 * amp


def test_gaussian_noise_matches_eq26(bumpy):
    v, f = bumpy
    e = 0.3
    sigma = A.gaussian_sigma(v, f, e)
    dvi = A.ring_distance(v, f)
    assert np.isclose(np.mean(sigma**2 / dvi), e)
    v2, _ = A.gaussian_noise(v, f, e, np.random.default_rng(6))
    disp2 = np.sum((v2 - v) ** 2, axis=1)
    assert np.mean(disp2 / dvi) == pytest.approx(e, rel=0.15)


def test_ring_distance_one_ring():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 2, 0], [0, 0, 3]], np.float64)
    f = np.array([[0, 1, 2], [0, 2, 3], [0, 3, 1]])
    assert A.ring_distance(v, f)[0] == pytest.approx(1 + 4 + 9)


def test_smoothing_reduces_roughness(bumpy):
    v, f = bumpy

    def roughness(x):
        adj = A.adjacency_matrix(f, len(x))
        deg = np.asarray(adj.sum(axis=1)).ravel()
        return np.linalg.norm(adj @ x / deg[:, None] - x, axis=1).mean()

    v5, _ = A.laplacian_smoothing(v, f, 5, None)
    v30, _ = A.laplacian_smoothing(v, f, 30, None)
    assert roughness(v30) < roughness(v5) < roughness(v)


def test_quantization_error_bounded(bumpy):
    v, f = bumpy
    for bits in (11, 8, 7):
        v2, _ = A.quantize(v, f, bits, None)
        step = A.quantization_step(v, bits)
        assert np.abs(v2 - v).max() <= step / 2 + 1e-12
        assert len(np.unique(v2[:, 0])) <= 2**bits


def test_crop_removes_requested_fraction(bumpy):
    v, f = bumpy
    for level in (0.1, 0.5):
        v2, f2 = A.crop(v, f, level, np.random.default_rng(7))
        assert abs(1 - len(f2) / len(f) - level) < 0.02
        assert f2.max() == len(v2) - 1 and len(np.unique(f2)) == len(v2)  # no unreferenced vertex


def test_simplify_and_subdivide_counts(sphere):
    v, f = sphere
    _v2, f2 = A.simplify(v, f, 0.5, None)
    assert abs(len(f2) / len(f) - 0.5) < 0.1
    _v3, f3 = A.subdivide(v, f, "midpoint", None)
    assert len(f3) == 4 * len(f)
    _v4, f4 = A.subdivide(v, f, "loop", None)
    assert len(f4) == 4 * len(f)


def test_sqrt3_subdivision_closed(sphere):
    v, f = sphere
    v2, f2 = A.subdivide(v, f, "sqrt3", None)
    assert len(v2) == len(v) + len(f) and len(f2) == 3 * len(f)
    m = trimesh.Trimesh(v2, f2, process=False)
    assert m.is_watertight and m.is_winding_consistent and m.volume > 0
    assert np.allclose(v2[len(v) :], v[f].mean(axis=1))  # a new vertex at every centroid
    # Kobbelt's relaxation of an original vertex of valence k
    adj = A.adjacency_matrix(f, len(v))
    i = 0
    ring = adj[i].indices
    k = len(ring)
    alpha = (4 - 2 * np.cos(2 * np.pi / k)) / 9
    assert np.allclose(v2[i], (1 - alpha) * v[i] + alpha * v[ring].mean(axis=0))
    # every new edge joins two centroids or a centroid and an original vertex: no original edge is left
    e = A.unique_edges(f2)
    assert not np.any((e[:, 0] < len(v)) & (e[:, 1] < len(v)))


def test_sqrt3_subdivision_open(sphere):
    v, f = A.crop(*sphere, 0.3, np.random.default_rng(3))
    edges = np.sort(f[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    uniq, inv = np.unique(edges, axis=0, return_inverse=True)
    count = np.bincount(inv.ravel())
    v2, f2 = A.subdivide(v, f, "sqrt3", None)
    # two triangles per interior edge, one per boundary edge
    assert np.sum(count == 1) > 0 and len(f2) == 2 * np.sum(count == 2) + np.sum(count == 1)
    assert trimesh.Trimesh(v2, f2, process=False).is_winding_consistent
    # vertices on the boundary stay where they were, interior ones move
    on_boundary = np.unique(uniq[count == 1])
    assert np.array_equal(v2[on_boundary], v[on_boundary])
    inside = np.setdiff1d(np.arange(len(v)), on_boundary)
    assert np.all(np.linalg.norm(v2[inside] - v[inside], axis=1) > 0)


def test_ply_and_obj_writers_are_exact(bumpy):
    v, f = bumpy
    v2, f2 = parse_ply_double(write_ply_double(v, f))
    assert np.array_equal(v2, v) and np.array_equal(f2, f)
    text = write_obj([(v, f)]).decode()
    vals = np.array([line.split()[1:] for line in text.splitlines() if line.startswith("v ")], float)
    assert np.array_equal(vals, v)


def test_trimesh_roundtrips_keep_shape(sphere):
    v, f = sphere
    for fmt in A.ROUNDTRIP_FORMATS:
        v2, f2 = A.trimesh_roundtrip(v, f, fmt)
        assert len(f2) == len(f), fmt
        assert np.abs(np.sort(v2, axis=0) - np.sort(v, axis=0)).max() < 1e-6, fmt


def test_surface_distance_exact_and_sane(bumpy):
    v, f = bumpy
    same = surface_distance(v, f, v, f, samples=5000, seed=0)
    assert same.mrms < 1e-12 and same.hausdorff < 1e-12
    scaled = surface_distance(v, f, 1.05 * v, f, samples=5000, seed=0)
    assert scaled.mrms > 1e-3 and scaled.hausdorff >= scaled.mrms
    # exact against brute force on a few points
    from trimesh.triangles import closest_point

    rng = np.random.default_rng(2)
    pts = rng.normal(0, 1.2, (40, 3))
    d = SurfaceIndex(v, f).query(pts)[0]
    tri = v[f]
    brute = [
        np.linalg.norm(closest_point(tri, np.repeat(p[None], len(tri), 0)) - p, axis=1).min() for p in pts
    ]
    assert np.allclose(d, brute, atol=1e-12)


def test_detection_metrics():
    assert ber("0101", "0101") == 0 and ber("0111", "0101") == 0.25 and ber(None, "0101") == 0.5
    assert bit_error_rate("1111", "0000") == 1.0
    rel = Reliability()
    rel.add([0.55, 0.97, 1.0, 1.0], "0110", "0111")
    assert rel.count.sum() == 4 and rel.right.sum() == 3


@needs_engine
def test_end_to_end_quick():
    """spot.obj: embed a 64-bit payload with planes (ellipsoids on spot need moves past the
    displacement ceiling), a few mild attacks, blind detection recovers it."""
    from bench.common import load_mesh
    from core.api import detect_file, embed_file

    path = shared_mesh_path("spot.obj")
    data = path.read_bytes()
    payload = "".join(np.random.default_rng(0).choice(["0", "1"], 64))
    emb = embed_file(data, "quick-key", filename=path.name, payload=payload, method="planes")
    marked = load_mesh(emb.data, path.name)
    results = {}
    for name, level in [
        ("none", 0),
        ("similarity", 1),
        ("reorder", 1),
        ("uniform_noise", 0.0005),
        ("crop", 0.1),
    ]:
        v2, f2 = A.ATTACKS[name].function(marked.vertices, marked.faces, level, np.random.default_rng(11))
        r = detect_file(write_ply_double(v2, f2), "quick-key", filename="attacked.ply")
        results[name] = r.detected and r.payload == payload
    # crop 10 % is recorded (in the message) but not required: a plane cut may take too many carriers
    assert results["none"] and results["similarity"] and results["reorder"], results
    assert results["uniform_noise"], results
    wrong = detect_file(emb.data, "another-key", filename=path.name)
    assert not wrong.detected


def test_tracing_quick(tmp_path):
    """`python -m bench tracing` in miniature on rocker-arm: every leak named, no innocent accused,
    the same ranking from SQLite (and PostgreSQL when it answers)."""
    import argparse

    from bench import tracing

    args = argparse.Namespace(meshes=["rocker-arm.obj"], seed=5, recipients=200, copies=4, single_trials=2,
                              collusions=3, innocent_trials=5, registry_copies=500, out=str(tmp_path),
                              registry_only=False)
    shared_mesh_path("rocker-arm.obj")
    doc = tracing.run(args)
    for trials in doc["results"][0]["cases"].values():
        assert all(t["guilty_named"] >= 1 and t["innocent_accused"] == 0 for t in trials)
    innocents = doc["results"][0]["innocents"].values()
    assert all(t["trials_accusing"] == 0 and t["trials"] == 5 for t in innocents)
    assert doc["registry"]["same_answers"]
    assert "Same ranking and scores on every backend: yes" in (tmp_path / "tracing.md").read_text()


def test_attack_ab_runs_one_row_and_compares_two_runs(tmp_path) -> None:
    """bench.attack_ab: one mesh x method row has every attack, and --compare totals two runs."""
    import json

    from bench import attack_ab

    shared_mesh_path("fandisk.off")
    row = attack_ab.run_one("fandisk.off", "planes")
    cols = [k for k, v in row.items() if isinstance(v, dict)]
    assert len(cols) == len(attack_ab.ATTACKS) and row["rms"] <= 2e-4
    assert all(0 <= row[c]["found"] <= row[c]["draws"] for c in cols)
    worse = {**row, **{c: {**row[c], "found": 0, "bit_errors": 32.0} for c in cols}}
    a, b = tmp_path / "a.jsonl", tmp_path / "b.jsonl"
    a.write_text(json.dumps(worse) + "\n")
    b.write_text(json.dumps(row) + "\n")
    text = attack_ab.compare(a, b, verbose=False)
    total = sum(row[c]["found"] for c in cols)
    assert text.splitlines()[-1] == f"total found 0 -> {total} of {sum(row[c]['draws'] for c in cols)}"
