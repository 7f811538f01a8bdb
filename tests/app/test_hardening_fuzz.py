"""A short fuzz run over the upload path: real meshes, mutated by hypothesis with the operators of
:mod:`tests.mutations`, sent through the HTTP API.  Every answer is a 200 or a documented 4xx
problem: never a 5xx.  ``bench/fuzz_upload.py`` is the long run of the same (results in
``bench/results/hardening.md``)."""

from __future__ import annotations

import logging
from collections.abc import Iterator

import pytest
from fastapi.testclient import TestClient
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.app.conftest import make_client
from tests.app.oracles import ROUTES, check_answer
from tests.conftest import shared_mesh_path
from tests.mutations import OPS, TOKENS, apply_ops

CANARY_KEY = "CANARY-KEY-0e9d-never-in-a-log"
SEEDS = ["teapot.stl", "monkey.glb", "sink.3ds", "spot.obj", "fandisk.off"]


@pytest.fixture(scope="module")
def seeds() -> list[tuple[str, bytes]]:
    return [(name, shared_mesh_path(name).read_bytes()) for name in SEEDS]


@pytest.fixture(scope="module")
def client() -> Iterator[TestClient]:
    # a hang, not a slow machine, must pass the time limit (niced workers: test_hardening_schema.py)
    with make_client(workers=2, job_timeout_seconds=100) as c:
        yield c


operation = st.tuples(
    st.sampled_from(OPS),
    st.one_of(st.floats(0, 1), st.floats(0, 1).map(lambda w: w**6)),  # also near the header
    st.one_of(st.sampled_from(TOKENS), st.binary(min_size=1, max_size=6)),
)


@settings(max_examples=60, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(which=st.integers(0, len(SEEDS) - 1), ops=st.lists(operation, min_size=1, max_size=4),
       route=st.sampled_from(ROUTES))
def test_mutated_real_meshes_never_get_a_5xx(client, seeds, caplog, which, ops, route):
    caplog.set_level(logging.DEBUG)
    name, original = seeds[which]
    data = apply_ops(original, ops)
    form = {} if route == "/v1/capacity" else {"key": CANARY_KEY}
    response = client.post(route, files={"mesh": (name, data)}, data=form)
    assert check_answer(response) is None, (name, route, ops, response.text[:500])
    assert CANARY_KEY.encode() not in response.content
    assert not [r for r in caplog.records if CANARY_KEY in r.getMessage()]
