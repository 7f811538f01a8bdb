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


# files that carry the key in the places a reader used to quote: PLY element, property and
# keyword names, the OFF keyword, a glTF index, the file name's extension
_KEY_WITH_ESCAPES = "my\\key's \"secret\""
_GLTF = '{"asset":{"version":"2.0"},"meshes":[{"primitives":[{"attributes":{"POSITION":%s}}]}]}'
_QUOTING_FILES = [
    ("a.ply", "ply\nformat ascii 1.0\nelement vertex 3\nproperty float %s\nproperty float %s\nend_header\n"),
    ("a.ply", "ply\nformat ascii 1.0\nelement %s 3\nelement %s 3\nend_header\n"),
    ("a.ply", "ply\nformat ascii 1.0\n%s %s\nend_header\n"),
    ("a.off", "%s %s\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n"),
    ("a.gltf", _GLTF % "\"%s%s\""),
]


@pytest.mark.parametrize(("filename", "template"), _QUOTING_FILES)
@pytest.mark.parametrize("key", [_KEY_WITH_ESCAPES, "HunTer2word"])
def test_problem_details_quote_nothing_of_the_file(client, filename, template, key):
    token = key.replace(" ", "_") if not filename.endswith("gltf") else key.replace('"', "'")
    body = (template % (token, token)).encode()
    response = client.post("/v1/embed", files={"mesh": (filename, body)}, data={"key": key})
    problem = response.json()
    assert 400 <= response.status_code < 500, problem
    text = response.text
    for form in (key, token, repr(token)[1:-1], token.split("'")[0], "[key]", "withheld"):
        assert form not in text, (form, problem)


def test_a_key_that_is_a_common_word_leaves_details_whole(client):
    # cutting the key out of details garbled them when it was a word of one ("56-bit [key]word")
    files = {"mesh": ("a.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1e200 0 0\nf 1 2 3\nf 1 2 4\n")}
    details = {key: client.post("/v1/embed", files=files, data={"key": key}).json()["detail"]
               for key in ("coordinate", "an unrelated key")}
    assert details["coordinate"] == details["an unrelated key"]
    assert "coordinate" in details["coordinate"]
