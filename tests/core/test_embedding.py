"""core.embedding: the closest point on an ellipsoid, the target of a move, and the embedding of
a codeword as the detector then reads it."""

from __future__ import annotations

import numpy as np
import pytest

from core.analysis import analyse, keyed_sides, signed_statistic, statistic
from core.coding import encode
from core.embedding import closest_on_ellipsoid, embed_parts, target_positions
from core.slots import assign_slots
from tests.core.meshes import irregular_sphere


def test_closest_point_on_a_sphere_is_radial() -> None:
    got = closest_on_ellipsoid(np.array([[3.0, 4.0, 0.0]]), np.array([[2.0, 2.0, 2.0]]))
    assert got == pytest.approx(np.array([[1.2, 1.6, 0.0]]))


def test_closest_point_on_an_ellipsoid() -> None:
    axes = np.array([[2.0, 1.0, 1.0]] * 3)
    points = np.array([[5.0, 0.0, 0.0], [0.0, 0.0, 3.0], [2.0, 2.0, 0.0]])
    got = closest_on_ellipsoid(points, axes)
    assert got[:2] == pytest.approx(np.array([[2.0, 0.0, 0.0], [0.0, 0.0, 1.0]]))
    x, y, _ = got[2]
    assert x**2 / 4 + y**2 == pytest.approx(1.0)  # on the ellipsoid
    normal = np.array([x / 4, y, 0.0])  # gradient there, parallel to (point - x) at the closest point
    assert np.cross(normal, points[2] - got[2]) == pytest.approx(np.zeros(3), abs=1e-9)
    collapsed = closest_on_ellipsoid(np.array([[1.0, 1.0, 1.0]]), np.zeros((1, 3)))
    assert collapsed == pytest.approx(np.zeros((1, 3)))


@pytest.mark.parametrize("method", ["planes", "ellipsoids"])
def test_targets_land_at_the_margin_on_the_wanted_side(method: str) -> None:
    v, f = irregular_sphere(1500, 7)
    a = analyse(v, f, "key", method)
    margin = 0.07
    bits = np.where(a.z > 0, 0, 1).astype(np.uint8)  # what each carrier reads now...
    bits[::2] ^= 1  # ...and the opposite for every other one
    new = target_positions(method, a, v[a.carriers], bits, margin)
    z = statistic(method, new, a.mu, a.axes, a.lam, a.scale)
    want = np.where(bits == 0, 1.0, -1.0)
    moved = np.any(new != v[a.carriers], axis=1)
    assert np.array_equal(moved, want * a.z < margin) and moved[::2].all()
    assert want[moved] * z[moved] == pytest.approx(np.full(moved.sum(), margin), abs=1e-6)
    # on the right side with the margin asked for: left alone
    assert np.array_equal(target_positions(method, a, new, bits, 0.5 * margin), new)


@pytest.mark.parametrize("method", ["planes", "ellipsoids"])
def test_carriers_moved_outside_go_to_their_keyed_side(method: str) -> None:
    """A carrier moved outside its boundary goes to its keyed side of its oriented ring (there its
    signed statistic equals the unsigned one), unless it sat more than half its target offset on
    the other side; moved inside, it stays on its side.  The keyed sides are half out, half in."""
    v, f = irregular_sphere(1500, 7)
    a = analyse(v, f, "key", method)
    sides = keyed_sides(a.slot_hash)
    assert 0.4 < (sides > 0).mean() < 0.6
    y0 = np.einsum("ki,ki->k", a.axes[:, :, 0], v[a.carriers] - a.mu)
    for bit in (0, 1):
        bits = np.full(len(a.carriers), bit, np.uint8)
        new = target_positions(method, a, v[a.carriers], bits, 0.07)
        moved = np.any(new != v[a.carriers], axis=1)
        assert moved.sum() > 50
        y1 = np.einsum("ki,ki->k", a.axes[:, :, 0], new - a.mu)
        args = (method, new, a.mu, a.axes, a.lam, a.scale)
        if bit == 0:
            keyed = moved & (sides * y0 >= -0.5 * np.abs(y1))
            assert keyed.sum() > 0.9 * moved.sum() and (sides * y1 > 0)[keyed].all()
            assert (sides * y0 < 0)[keyed].any()  # some crossed to their keyed side
            assert signed_statistic(*args, sides)[keyed] == pytest.approx(statistic(*args)[keyed])
            assert (np.sign(y1[moved & ~keyed]) == np.sign(y0[moved & ~keyed])).all()
        else:
            off = moved & (np.abs(y1) > 1e-9 * a.scale)  # planes put a flat ring's carrier on it
            assert (np.sign(y1[off]) == np.sign(y0[off])).all()
            assert off.sum() > 20 or method == "planes"


def test_embedded_carriers_read_the_codeword() -> None:
    v, f = irregular_sphere(2000, 8)
    original = v.copy()
    word = encode("key", np.array([1, 0, 1, 1, 0, 1], np.uint8))
    (new,), (stats,), (view,) = embed_parts([(v, f)], "key", word, "planes", 0.07)
    assert np.array_equal(v, original)  # the input is not modified
    slots = assign_slots([view.slot_hash], len(word))[0]
    reads = (view.z < 0).astype(np.uint8)
    assert np.array_equal(reads, word[slots])
    fresh = analyse(new, f, "key", "planes")  # the detector's own view agrees with the embedder's
    assert np.array_equal(fresh.carriers, view.carriers) and np.allclose(fresh.z, view.z)
    assert stats.carriers == len(view.carriers) and stats.moved == int(np.any(new != v, axis=1).sum())


def _rms(new: np.ndarray, old: np.ndarray) -> float:
    diag = float(np.linalg.norm(old.max(axis=0) - old.min(axis=0)))
    return float(np.sqrt(((new - old) ** 2).sum(axis=1).mean())) / diag


def test_the_rms_budget_spends_itself_on_the_margin() -> None:
    """Under an RMS budget the first round's margin is the largest that fits (between 0.4 and 2 x
    the strength): a budget the marks would exceed lowers every carrier's margin before any carrier
    is left out (which then read wrong), one they would not reach raises it."""
    v, f = irregular_sphere(3000, 9)
    word = encode("key", np.array([1, 0, 1, 1, 0, 1, 1, 1], np.uint8))
    (free,), _, _ = embed_parts([(v, f)], "key", word, "planes", 0.07)
    natural = _rms(free, v)
    for share in (0.8, 1.5):
        (new,), (stats,), (view,) = embed_parts([(v, f)], "key", word, "planes", 0.07,
                                                rms_budget=share * natural)
        got = _rms(new, v)
        assert got <= share * natural * 1.1  # the rounds after the first add a little
        if share < 1:
            assert stats.skipped <= 0.02 * stats.carriers  # a smaller margin, not carriers left out
        else:
            assert got > 1.2 * natural  # the room was used: stronger marks
        slots = assign_slots([view.slot_hash], len(word))[0]
        assert ((view.z < 0).astype(np.uint8) == word[slots]).mean() > 0.97


@pytest.mark.parametrize(("n", "crossing"), [(2000, False), (6000, True)])
def test_keyed_sides_from_1024_connectivity_carriers(n: int, crossing: bool) -> None:
    """Below SIGNED_FROM connectivity carriers (where the detector never reads the signed statistic)
    every moved carrier stays on its side of its ring's plane; from there some cross to their keyed
    side."""
    from core.analysis import SIGNED_FROM

    v, f = irregular_sphere(n, 11)
    word = encode("key", np.array([1, 0, 1, 1, 0, 1], np.uint8))
    (new,), _, (view,) = embed_parts([(v, f)], "key", word, "planes", 0.07)
    assert (len(view.carriers) >= SIGNED_FROM) == crossing
    a = analyse(v, f, "key", "planes")
    keep = np.isin(a.carriers, view.carriers)
    c, mu, e1 = a.carriers[keep], a.mu[keep], a.axes[keep][:, :, 0]
    y0 = np.einsum("ki,ki->k", e1, v[c] - mu)
    y1 = np.einsum("ki,ki->k", e1, new[c] - mu)
    off = np.abs(y1) > 1e-9 * a.scale[keep]
    crossed = off & (np.sign(y1) != np.sign(y0)) & (y0 != 0)
    assert crossed.any() == crossing


def test_a_bit_1_out_of_reach_is_not_moved_round_after_round() -> None:
    # planes at margin 0.2: a bit 1 on a ring flatter than the margin reads at most plane_floor
    # (0.07) below its boundary, under the later rounds' half margin (0.1); once there it has
    # nowhere to go, and the embedding settles instead of "moving" it by rounding every round
    from core.embedding import deepest
    from core.tolerances import TOL

    v, f = irregular_sphere(4000, 3)
    cw = encode("k", None)
    _, stats, final = embed_parts([(v, f)], "k", cw, "planes", 0.2)
    a = final[0]
    bits = cw[assign_slots([a.slot_hash], len(cw))[0]]
    at_best = (bits == 1) & (-a.z >= 0.99 * deepest("planes", a)) & (-a.z < 0.1)
    assert at_best.sum() > 50  # the case is there
    assert stats[0].rounds < TOL.verify_rounds


def test_the_connectivity_check_beside_the_geometric_choice_changes_nothing(monkeypatch) -> None:
    # a large file checks its connectivity selection in a thread beside the geometric choice and
    # uses the answer when the positions did not change since: the same file, bit for bit, as the
    # check made after it in this thread
    import core.embedding as emb
    from core.pipeline import embed_mesh

    v, f = irregular_sphere(30000, 2)
    v = v * np.array([1.0, 0.7, 0.5])  # a frame of three distinct axes: a geometric layer
    v[:, 0] += 0.2 * v[:, 1] ** 2  # (and a second choice after the follow, on this one)
    used = []
    beside = emb.beside
    monkeypatch.setattr(emb, "beside", lambda fn: used.append(1) or beside(fn))
    monkeypatch.setattr(emb, "SPLIT_FROM", 0)
    with_check, rep = embed_mesh(v, f, "k", method="ellipsoids")
    assert used and rep.geometric_carriers > 0
    monkeypatch.setattr(emb, "SPLIT_FROM", 10**12)
    without, _ = embed_mesh(v, f, "k", method="ellipsoids")
    assert np.array_equal(with_check, without)
