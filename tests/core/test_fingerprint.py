"""Fingerprint codewords: scoring, the innocent's null distribution, and a real mesh end to end."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from core.analysis import analyse
from core.errors import CapacityError, PayloadError
from core.fingerprint import (
    MIN_EMBED_SCORE,
    codeword_length,
    codeword_votes,
    correlation_scores,
    embed_codeword,
    false_accusation,
    pack_codeword,
    random_codeword,
    read_votes,
    score_threshold,
    unpack_codeword,
)
from core.formats import read_mesh
from core.options import Options
from tests.conftest import shared_mesh_path


def _packed(codewords: list[np.ndarray]) -> np.ndarray:
    return np.stack([np.frombuffer(pack_codeword(c), np.uint8) for c in codewords])


@settings(max_examples=40, deadline=None)
@given(L=st.integers(1, 300), n=st.integers(1, 40), seed=st.integers(0, 2**32 - 1))
def test_scores_are_the_normalised_correlation(L: int, n: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    votes = rng.normal(size=(2, L))
    cws = [random_codeword(rng, L) for _ in range(n)]
    got = correlation_scores(votes, _packed(cws), L)
    signs = 1.0 - 2.0 * np.stack(cws)
    want = np.max([signs @ y / np.linalg.norm(y) for y in votes], axis=0)
    np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-9)
    assert all(np.array_equal(unpack_codeword(pack_codeword(c), L), c) for c in cws)


def test_the_owner_of_the_votes_scores_sqrt_L_and_zero_votes_score_zero() -> None:
    cw = np.array([0, 1, 1, 0, 1, 0, 0, 0, 1], np.uint8)
    votes = 1.0 - 2.0 * cw  # every bit read as issued, unit weight
    assert correlation_scores(votes, _packed([cw, 1 - cw]), 9) == pytest.approx([3.0, -3.0])
    assert correlation_scores(np.zeros(9), _packed([cw]), 9) == pytest.approx([0.0])


def test_innocent_scores_stay_under_the_hoeffding_bound() -> None:
    """Whatever the votes (here heavy-tailed and uneven), an independent codeword's score exceeds t
    with probability at most exp(-t^2 / 2)."""
    rng = np.random.default_rng(7)
    L = 256
    votes = rng.standard_cauchy(L)
    scores = correlation_scores(votes, _packed([random_codeword(rng, L) for _ in range(20000)]), L)
    for t in (1.0, 2.0, 3.0):
        assert (scores >= t).mean() <= math.exp(-t * t / 2)
    assert abs(scores.mean()) < 0.05 and 0.9 < scores.std() < 1.1


def test_false_accusation_is_the_union_bound_and_the_threshold_its_inverse() -> None:
    assert false_accusation(np.array([-1.0, 0.0]), 10).tolist() == [1.0, 1.0]
    t = score_threshold(1e-9, 2000)
    assert false_accusation(np.array([t]), 2000)[0] == pytest.approx(1e-9)
    assert false_accusation(np.array([t + 1]), 2000)[0] < 1e-9


def test_codeword_length_keeps_four_carriers_per_bit() -> None:
    assert codeword_length(2393) == 598
    assert codeword_length(10**7) == codeword_length(4 * 1024) == 1024  # the cap
    assert codeword_length(4 * 1023 + 3) == 1023
    with pytest.raises(CapacityError):
        codeword_length(255)


def test_real_mesh_copy_is_traced_to_its_recipient_and_an_average_to_both() -> None:
    path = shared_mesh_path("rocker-arm.obj")
    data = path.read_bytes()
    options = Options(key="tracing-test")
    rng = np.random.default_rng(3)
    first = embed_codeword(data, options, rng=rng, filename=path.name)
    L = len(first.codeword)
    assert codeword_length(first.file.report.carriers) == L and first.score >= MIN_EMBED_SCORE
    others = [random_codeword(rng, L) for _ in range(200)]
    second = embed_codeword(data, options, codeword=others[0], filename=path.name)
    again = embed_codeword(data, options, codeword=first.codeword, filename=path.name)
    assert again.file.data == first.file.data  # the same codeword gives the same copy
    packed = _packed([first.codeword, *others])
    threshold = score_threshold(1e-9, 2 * len(packed))

    group = ("ellipsoids", L)
    leaked = read_votes(first.file.data, options, [group], filename=path.name)[group]
    scores = correlation_scores(leaked, packed, L)
    assert scores[0] >= threshold and scores[1:].max() < threshold
    votes = read_votes(data, options, [("planes", L), group], filename=path.name)
    assert set(votes) == {("planes", L), group}
    unmarked = correlation_scores(votes[group], packed, L)
    assert unmarked.max() < threshold
    wrong_key = read_votes(first.file.data, Options(key="another"), [group], filename=path.name)[group]
    assert correlation_scores(wrong_key, packed, L).max() < threshold

    a, b = (read_mesh(f.file.data, path.name).parts[0] for f in (first, second))
    avg = analyse(0.5 * (a.vertices + b.vertices), a.faces, "tracing-test", "ellipsoids")
    scores = correlation_scores(codeword_votes([avg], "tracing-test", L), packed, L)
    assert min(scores[0], scores[1]) >= threshold and scores[2:].max() < threshold


def test_a_payload_is_refused() -> None:
    with pytest.raises(PayloadError):
        embed_codeword(b"", Options(key="k", payload="01"))


def test_a_copy_reports_what_the_file_skipped_like_an_embedding() -> None:
    """Copies are written by the same step as embeddings: two-corner faces and line elements are
    carried through and counted in the copy's report too."""
    path = shared_mesh_path("rocker-arm.obj")
    data = path.read_bytes() + b"l 1 2\nf 1 2\n"
    copy = embed_codeword(data, Options(key="tracing-test"), rng=np.random.default_rng(5), filename=path.name)
    assert copy.file.report.skipped_elements == 2
    assert copy.file.data.endswith(b"l 1 2\nf 1 2\n") and copy.file.report.reencoded == []
