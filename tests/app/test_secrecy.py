"""The watermark key never leaves the request: not in bodies, headers or log records."""

from __future__ import annotations

import logging

import pytest

from tests.app.conftest import wait_job

CANARY = "CANARY-3e1f0c9d-do-not-leak"


@pytest.fixture
def logs(caplog):
    caplog.set_level(logging.DEBUG)  # every logger, every level
    return caplog


def _leaks(response) -> bool:
    headers = "\n".join(f"{k}: {v}" for k, v in response.headers.items())
    return CANARY in headers or CANARY.encode() in response.content


def test_key_is_never_echoed_or_logged(client, logs, sphere_obj):
    files = {"mesh": ("s.obj", sphere_obj)}
    marked = client.post("/v1/embed", files=files, data={"key": CANARY})
    responses = [
        marked,
        client.post("/v1/embed", files=files, headers={"X-Watermark-Key": CANARY}),
        client.post("/v1/embed", files=files, data={"key": CANARY, "payload": CANARY}),
        client.post("/v1/embed", files=files, data={"key": CANARY, "strength": CANARY}),
        client.post("/v1/embed", files=files, data={"key": CANARY * 40}),  # too long
        client.post("/v1/embed", files=files, data={"key": CANARY + "\n"}),  # control character
        client.post("/v1/embed", files=files, data={"key": CANARY}, headers={"X-Watermark-Key": CANARY}),
        client.post("/v1/embed", files={"mesh": ("x.obj", b"\xff\xd8" + bytes(40))}, data={"key": CANARY}),
        client.post("/v1/embed", files={"mesh": ("x.obj", b"v 0 0 0\nf 1 2 3\n")}, data={"key": CANARY}),
        client.post("/v1/detect", files={"mesh": ("s.obj", marked.content)}, data={"key": CANARY}),
        client.post("/v1/detect", files=files, data={"key": CANARY, "method": CANARY}),
        client.post("/v1/embed", data={"key": CANARY}),  # missing mesh: FastAPI's own validation
        client.post("/v1/embed", json={"key": CANARY}),
    ]
    job = client.post("/v1/jobs/embed", files=files, data={"key": CANARY})
    wait_job(client, job.json()["id"])
    responses += [job, client.get(f"/v1/jobs/{job.json()['id']}"),
                  client.get(f"/v1/jobs/{job.json()['id']}/result"), client.get("/metrics")]

    assert responses[0].status_code == 200 and responses[9].json()["detected"] is True
    assert {r.status_code for r in responses[2:9]} >= {415, 422}
    assert not [r.request.url for r in responses if _leaks(r)]
    assert logs.records, "the requests should have been logged"
    for record in logs.records:
        assert CANARY not in record.getMessage(), record.getMessage()
        assert CANARY not in str(record.exc_info or "")
    assert any("key=" in r.getMessage() for r in logs.records)  # the fingerprint stands in for it


def test_fingerprint_is_keyed_and_stable():
    from app.inputs import key_fingerprint

    a = key_fingerprint(CANARY, b"secret-1")
    assert a == key_fingerprint(CANARY, b"secret-1") and len(a) == 8
    assert a != key_fingerprint(CANARY, b"secret-2") and a not in CANARY
