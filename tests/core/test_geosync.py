"""core.geosync: the surface's pose-invariant frame, the angle of a degenerate pair, geometric carriers."""

from __future__ import annotations

import numpy as np
import pytest

from core import geosync as G
from core.mesh import adjacency
from tests.conftest import shared_mesh_path
from tests.core.meshes import irregular_sphere, similarity

KEY = "geosync-test-key"


def lobed_plate(lobes: int, boundary: int, rings: int, bump: float = 0.06,
                amplitude: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """A flat star-shaped plate ``r(theta) = 1 + amplitude cos(lobes theta)`` with a bump on the lobe
    at ``2 pi / lobes`` (one lobe differs: a gear with a mark), its outline sampled at ``boundary``
    angles.  ``rings = 0``: a fan from the centre (CAD's triangulation: every face spans
    ``2 pi / boundary``, the area sits far from the vertices); else ``rings`` concentric rings of
    vertices (fine).  Both are exactly the same surface."""
    theta = 2.0 * np.pi * np.arange(boundary) / boundary
    d = (theta - 2.0 * np.pi / lobes + np.pi) % (2.0 * np.pi) - np.pi
    r = 1.0 + amplitude * np.cos(lobes * theta) + bump * np.exp(-d * d / 0.02)
    outline = np.stack([r * np.cos(theta), r * np.sin(theta), np.zeros(boundary)], axis=1)
    levels = [1.0] if rings == 0 else list(np.arange(1, rings + 1) / rings)
    v = np.concatenate([np.zeros((1, 3))] + [s * outline for s in levels])
    j = np.arange(boundary)
    k = (j + 1) % boundary
    faces = [np.stack([np.zeros(boundary, np.int64), 1 + j, 1 + k], axis=1)]
    for ring in range(len(levels) - 1):
        a, b = 1 + ring * boundary, 1 + (ring + 1) * boundary
        faces.append(np.stack([a + j, b + j, b + k], axis=1))
        faces.append(np.stack([a + j, b + k, a + k], axis=1))
    return v, np.concatenate(faces)


def skewed_blob(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """An irregular closed surface with three distinct second moments and clear third moments."""
    v, f = irregular_sphere(n, seed)
    v = v * np.array([2.0, 1.4, 1.0])
    return v + 0.3 * v**2 * np.array([0.5, 0.7, 1.0]), f  # sqrt ratios 1.37, 1.29; skews 0.14-0.17


def rotation_angle(a: np.ndarray, b: np.ndarray) -> float:
    """Angle (degrees) of the rotation taking the rows of ``b`` to those of ``a``."""
    return float(np.degrees(np.arccos(np.clip((np.trace(a @ b.T) - 1.0) / 2.0, -1.0, 1.0))))


def transform(v: np.ndarray, f: np.ndarray, seed: int
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, np.ndarray]:
    """:func:`similarity` with its rotation, scale and vertex permutation recovered (the same draws):
    new vertex ``j`` is old vertex ``perm[j]``."""
    v2, f2 = similarity(v, f, np.random.default_rng(seed))
    rng = np.random.default_rng(seed)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    s = float(np.exp(rng.uniform(np.log(0.05), np.log(20))))
    rng.normal(size=3)
    perm = rng.permutation(len(v))
    assert np.allclose(v2, (s * v @ q.T)[perm] + (v2 - (s * v @ q.T)[perm])[0])
    return v2, f2, q, s, perm


def test_frame_moves_with_similarity_transforms_and_ignores_order() -> None:
    v, f = skewed_blob(3000, 1)
    fr = G.surface_frame(v, f)
    assert fr is not None and fr.degenerate == -1 and np.all(np.abs(fr.skew) > G.SKEW_SURE)
    for seed in range(3):
        v2, f2, q, s, _ = transform(v, f, seed)
        fr2 = G.surface_frame(v2, f2)
        assert fr2 is not None
        assert fr2.rho == pytest.approx(s * fr.rho, rel=1e-9)
        assert fr2.area == pytest.approx(s * s * fr.area, rel=1e-9)
        assert np.allclose(fr2.axes, fr.axes @ q.T, atol=1e-7)
        assert len(G.frame_candidates(fr2)) == 1


def test_geometric_carriers_are_the_same_vertices_after_a_similarity_and_reordering() -> None:
    v, f = skewed_blob(6000, 2)
    adj = adjacency(f, len(v))
    p = G.embed_placement(v, f, adj, KEY)
    assert p is not None
    c, h = G.geometric_carriers(v, adj, p.frame, p.axes, p.rung, KEY)
    assert len(c) > 200
    # cells are keyed: another key puts them elsewhere
    other = G.geometric_carriers(v, adj, p.frame, p.axes, p.rung, "another key")[0]
    assert len(np.intersect1d(c, other)) < 0.5 * len(c)
    for seed in range(3):
        v2, f2, _, _, perm = transform(v, f, seed)
        adj2 = adjacency(f2, len(v2))
        p2 = G.embed_placement(v2, f2, adj2, KEY)
        assert p2 is not None and p2.rung == p.rung
        c2, h2 = G.geometric_carriers(v2, adj2, p2.frame, p2.axes, p2.rung, KEY)
        back = {int(perm[j]): int(hh) for j, hh in zip(c2, h2, strict=True)}
        same = sum(1 for i, hh in zip(c, h, strict=True) if back.get(int(i)) == int(hh))
        assert same >= 0.99 * len(c) and len(c2) <= 1.01 * len(c)


def test_sliver_triangulation_has_the_surfaces_spectrum_not_its_vertices() -> None:
    """The fan's 63 outline vertices carry all its vertex weight: weighted by vertices its strongest
    line is m = 63 (|F| near 1, the sampling), as the counter plate's were; integrated over the
    faces it has the fine mesh's spectrum and its strongest harmonic is the 7 lobes."""
    fine = lobed_plate(7, 63, 12)
    fan = lobed_plate(7, 63, 0)
    frames = [G.surface_frame(*m) for m in (fine, fan)]
    assert all(fr is not None for fr in frames)
    ex, ey = np.eye(3)[0], np.eye(3)[1]
    spectra = []
    for v, f in (fine, fan):
        areas = G._face_integrals(v, f)[3]
        spectra.append(G.angular_spectrum(v, f, areas, np.zeros(3), ex, ey))
    assert np.abs(spectra[0] - spectra[1]).max() < 0.01
    assert int(np.argmax(np.abs(spectra[1]))) + 1 == 7 and abs(spectra[1][6]) > 0.1
    v, f = fan
    areas = G._face_integrals(v, f)[3]
    weight = np.bincount(f.ravel(), np.repeat(areas / 3.0, 3), minlength=len(v))
    r = np.hypot(v[:, 0], v[:, 1])
    by_vertex = (weight * r) @ np.exp(1j * 63 * np.arctan2(v[:, 1], v[:, 0])) / (weight * r).sum()
    assert abs(by_vertex) > 0.9  # what the vertex quadrature saw
    for fr in frames:
        assert fr is not None and fr.degenerate == 0 and fr.harmonic == 7


def test_degenerate_pair_takes_the_marked_lobe_under_retriangulation_and_similarity() -> None:
    fine = lobed_plate(7, 63 * 4, 16)
    fr = G.surface_frame(*fine)
    assert fr is not None and fr.sqrt_ratios[0] < G.DEGENERATE and fr.harmonic == 7
    # one turn of seven: the marked lobe's density leads (both signs of the plate's normal are tried)
    assert len(fr.turns) == 1 and len(G.frame_candidates(fr)) == 2
    # the first axis points at the marked lobe
    assert abs(np.degrees(np.arctan2(fr.axes[0, 1], fr.axes[0, 0])) - 360.0 / 7) < 0.05
    for mesh, seed in ((lobed_plate(7, 63, 0), 0), (lobed_plate(7, 63 * 2, 5), 1), (fine, 2)):
        v2, f2, q, _, _ = transform(*mesh, seed)
        fr2 = G.surface_frame(v2, f2)
        assert fr2 is not None and fr2.harmonic == 7
        assert min(rotation_angle(c, fr.axes @ q.T) for c in G.frame_candidates(fr2)) < 0.05


def test_symmetric_part_offers_every_tied_turn() -> None:
    """Without the mark the seven lobes tie: the detector tries all seven turns (both signs)."""
    fr = G.surface_frame(*lobed_plate(7, 63 * 4, 16, bump=0.0))
    assert fr is not None and fr.harmonic == 7
    assert len(fr.turns) == 7 and len(G.frame_candidates(fr)) == 14
    turns = np.sort(np.round(np.degrees(fr.turns) % 360.0, 6))
    assert np.allclose(turns, 360.0 / 7 * np.arange(7), atol=1e-6)


def test_surface_of_revolution_has_no_frame() -> None:
    """A disc: no angular harmonic, no frame (no geometric carriers)."""
    assert G.surface_frame(*lobed_plate(7, 120, 8, bump=0.0, amplitude=0.0)) is None


def test_follow_keeps_the_turn_and_rung_in_the_moved_frame() -> None:
    v, f = lobed_plate(7, 63 * 4, 16)
    adj = adjacency(f, len(v))
    p = G.embed_placement(v, f, adj, KEY)
    assert p is not None
    moved = v + np.random.default_rng(0).normal(scale=1e-4, size=v.shape) * np.array([1.0, 1.0, 0.0])
    q = G.follow(p, moved, f)
    assert q.rung == p.rung and rotation_angle(q.axes, p.axes) < 0.05
    assert np.array_equal(q.frame.centroid, G.surface_frame(moved, f).centroid)


def test_counter_plate_frame_survives_simplification() -> None:
    """The CAD plate whose strongest vertex-weighted line jumped (55 -> 15, 2, 20) under quadric
    simplification: integrated, m = 20 holds and a detector candidate is within 0.05 degrees."""
    import fast_simplification
    import meshoptimizer

    from core.formats import read_mesh

    name = "counter.unitsmm.STL"
    part = read_mesh(shared_mesh_path(name).read_bytes(), name).parts[0]
    v, f = part.vertices.astype(np.float64), part.faces.astype(np.int64)
    fr = G.surface_frame(v, f)
    assert fr is not None and fr.harmonic == 20
    # quadric simplification of half the faces (its vertices move), meshoptimizer's of 10 % (kept)
    vq, fq = fast_simplification.simplify(v, f.astype(np.int32), target_reduction=0.5)
    idx = np.ascontiguousarray(f, np.uint32).ravel()
    out = np.zeros_like(idx)
    n = meshoptimizer.simplify(out, idx, np.ascontiguousarray(v, np.float32),
                               target_index_count=int(len(idx) * 0.9) // 3 * 3, target_error=0.05)
    quadric = (np.asarray(vq, np.float64), np.asarray(fq, np.int64))
    for v2, f2 in (quadric, (v, out[:n].reshape(-1, 3).astype(np.int64))):
        fr2 = G.surface_frame(v2, f2)
        assert fr2 is not None and fr2.harmonic == 20
        assert min(rotation_angle(c, fr.axes) for c in G.frame_candidates(fr2)) < 0.05


def test_kept_rings_are_the_rings_of_any_set_of_vertices() -> None:
    """Rings.least gives every vertex the axis a direct call on any set containing it gives
    (repeats, any order, asked before or after), so a detection that keeps them reads as one that
    does not; in_frame is the matrix product it replaces."""
    from core.eig3 import eigh3
    from core.mesh import neighbour_moments

    v, f = irregular_sphere(3000, 5)
    adj = adjacency(f, len(v))
    rings = G.Rings(v, adj)
    rng = np.random.default_rng(1)
    for _ in range(4):
        which = rng.integers(0, len(v), 700)  # repeats and overlaps with the earlier asks
        direct = eigh3(neighbour_moments(v, adj, which)[1])[1][:, :, 0]
        assert np.array_equal(rings.least(which), direct)
    rot = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    origin = rng.normal(size=3)
    assert G.in_frame(v, origin, rot) == pytest.approx((v - origin) @ rot.T, abs=1e-12)


def test_kept_rings_follow_positions_changed_in_place_once_forgotten() -> None:
    """The embedder keeps its Rings across rounds and forgets the rings of its moved vertices'
    neighbours (``Rings.forget``): what it then reads are the rings at the new positions."""
    v, f = irregular_sphere(3000, 5)
    adj = adjacency(f, len(v))
    rings = G.Rings(v, adj)
    everything = np.arange(len(v))
    before = rings.least(everything).copy()
    rng = np.random.default_rng(2)
    moved = rng.choice(len(v), 50, replace=False)
    v[moved] += rng.normal(0.0, 0.02, (50, 3))  # in place: the array the kept rings read
    near = np.zeros(len(v), bool)
    near[adj.indices[adj.ring_entries(moved)[1]]] = True
    fresh = G.Rings(v, adj).least(everything)
    stale = rings.least(everything)
    assert not np.array_equal(stale, fresh)  # unforgotten, they are the old rings
    rings.forget(near)
    assert np.array_equal(rings.least(everything), fresh)
    assert np.array_equal(fresh[~near], before[~near])  # the others did not change
