"""Multipart and HTTP abuse: every malformed, oversized or ambiguous request gets a fast 4xx
(400, 413 or 422) -- a problem document wherever the app sees the request -- never a 500, and
never echoes the key.

In-process cases go through the ASGI app with raw bodies; Content-Length games need a real
server (``meshmark serve``) and raw socket writes, since HTTP clients will not send them.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterator
from typing import Any

import pytest
from fastapi.testclient import TestClient

from tests.app.conftest import assert_problem, make_client
from tests.app.real_server import Server, raw_exchange, serve

CANARY_KEY = "CANARY-KEY-77a1-never-in-a-log"
BOUNDARY = "hardening-boundary-7f3e"
MESH = b"v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\nf 1 3 4\nf 2 3 4\n"
FAST = 1.0


def part(name: str | bytes, value: bytes, filename: str | None = None) -> bytes:
    raw_name = name if isinstance(name, bytes) else name.encode()
    disposition = b'form-data; name="' + raw_name + b'"'
    if filename is not None:
        disposition += f'; filename="{filename}"'.encode()
    head = f"--{BOUNDARY}\r\n".encode() + b"Content-Disposition: " + disposition
    return head + b"\r\n\r\n" + value + b"\r\n"


def multipart(*parts: bytes, preamble: bytes = b"") -> bytes:
    return preamble + b"".join(parts) + f"--{BOUNDARY}--\r\n".encode()


def mesh_part(data: bytes = MESH, name: str = "mesh") -> bytes:
    return part(name, data, filename="m.obj")


def key_part(key: bytes = CANARY_KEY.encode()) -> bytes:
    return part("key", key)


FORM = f"multipart/form-data; boundary={BOUNDARY}"


@pytest.fixture(scope="module")
def client() -> Iterator[TestClient]:
    with make_client(workers=1) as c:
        yield c


@pytest.fixture(autouse=True)
def key_never_logged(caplog) -> Iterator[None]:
    caplog.set_level(logging.DEBUG)
    yield
    for record in caplog.records:
        assert CANARY_KEY not in record.getMessage()


def send(client: TestClient, body: bytes | Any, content_type: str | None = FORM,
         headers: dict[str, str] | None = None) -> Any:
    headers = dict(headers or {})
    if content_type is not None:
        headers["content-type"] = content_type
    start = time.perf_counter()
    response = client.post("/v1/embed", content=body, headers=headers)
    response.elapsed_seconds = time.perf_counter() - start
    assert CANARY_KEY.encode() not in response.content
    return response


def refused(response: Any, status: int, slug: str = "bad-form") -> dict[str, Any]:
    body = assert_problem(response, status, slug)
    assert response.elapsed_seconds < FAST, response.elapsed_seconds
    return body


def test_a_well_formed_raw_body_reaches_the_engine(client):
    """The builders above make forms the app takes (so the refusals below are about the abuse)."""
    response = send(client, multipart(mesh_part(), key_part()))
    assert_problem(response, 422, "too-little-capacity")  # a tetrahedron: parsed and analysed


@pytest.mark.parametrize(("body", "fragment"), [
    (multipart(mesh_part(), mesh_part(b"v 1 1 1\n"), key_part()), "'mesh' is given more than once"),
    (multipart(mesh_part(), mesh_part(name="other"), key_part()), "Too many files"),
    (multipart(mesh_part(), key_part(b"a"), key_part()), "'key' is given more than once"),
    (multipart(mesh_part(), key_part(), part("method", b"planes"), part("method", b"ellipsoids")),
     "'method' is given more than once"),
    (multipart(mesh_part(), key_part(), *[part(f"f{i}", b"x") for i in range(1000)]), "Too many fields"),
    (multipart(mesh_part(), key_part(), part("notes", b"x" * 10_000_000)), "exceeded maximum size"),
    (multipart(mesh_part(), key_part(b"k" * 1_000_000)), "exceeded maximum size"),
    (multipart(mesh_part(), key_part(b"k" * 60_000)), "at most 1024 characters"),
    (multipart(mesh_part(), key_part(b"caf\xe9")), "'key' is not valid UTF-8"),
    (multipart(mesh_part(), key_part(), part(b"\xff\xfe", b"x" * 10)), None),  # unknown, ignored
    (multipart(mesh_part(), key_part(), part("n" * 1_000_000, b"x")), "multipart"),
    (multipart(mesh_part(), key_part(), preamble=b"p" * 10_000_000 + b"\r\n"), "multipart"),
    (multipart(mesh_part()), "key is required"),
    (multipart(key_part()), "mesh"),
    (multipart(mesh_part())[:-30], "ends inside a part"),  # cut short: no closing boundary
    (b"\x00" * 100_000, "multipart"),
    (b"", "key is required"),
], ids=["two-meshes", "two-files", "two-keys", "two-methods", "1000-fields", "10MB-text-field",
        "1MB-key", "60KB-key", "key-not-utf8", "field-name-not-utf8", "1MB-field-name", "10MB-preamble",
        "no-key", "no-mesh", "no-closing-boundary", "binary-junk", "empty"])
def test_multipart_abuse(client, body, fragment):
    response = send(client, body)
    if fragment is None:  # the unknown field is ignored; the tetrahedron goes on to the engine
        assert_problem(response, 422, "too-little-capacity")
        return
    assert fragment in refused(response, 422)["detail"]


def test_fields_a_route_does_not_read_may_repeat(client):
    """``strength`` is not a field of /v1/detect: twice there, it is ignored like any unknown field."""
    body = multipart(mesh_part(), key_part(), part("strength", b"0.1"), part("strength", b"x"))
    response = client.post("/v1/detect", content=body, headers={"content-type": FORM})
    assert response.status_code == 200, response.text  # a tetrahedron: read, no watermark found
    assert response.json()["detected"] is False


@pytest.mark.parametrize(("content_type", "body"), [
    ("multipart/form-data", multipart(mesh_part(), key_part())),  # no boundary
    ("multipart/form-data; boundary=", multipart(mesh_part(), key_part())),
    ("multipart/form-data; boundary=other", multipart(mesh_part(), key_part())),
], ids=["no-boundary", "empty-boundary", "wrong-boundary"])
def test_broken_multipart(client, content_type, body):
    refused(send(client, body, content_type=content_type), 422)


@pytest.mark.parametrize(("content_type", "body"), [
    ("multipart/mixed; boundary=" + BOUNDARY, multipart(mesh_part(), key_part())),
    ("application/x-www-form-urlencoded", b"&".join(b"f%d=x" % i for i in range(2000))),
    ("application/x-www-form-urlencoded", b"key=" + b"k" * 2_000_000),
    ("application/x-www-form-urlencoded", b"key=a&key=b"),
    ("application/json", b'{"key": "' + CANARY_KEY.encode() + b'", "mesh": "v 0 0 0"}'),
    ("text/plain", MESH),
    ("application/octet-stream", MESH),
    (None, MESH),
], ids=["multipart-mixed", "urlencoded-2000-fields", "urlencoded-2MB-field", "urlencoded-two-keys", "json",
        "text", "raw-bytes", "no-content-type"])
def test_a_body_that_is_not_a_form_gets_415_and_what_to_send(client, content_type, body):
    """Not a 'key is required' for a body that is no form at all: 415 and the shape to send."""
    detail = refused(send(client, body, content_type=content_type), 415, "not-multipart")["detail"]
    assert "file part named 'mesh'" in detail and "-F mesh=@" in detail
    assert (content_type or "without Content-Type").split(";")[0] in detail


def test_mesh_sent_as_text_says_to_send_a_file(client):
    """``curl -F mesh=spot.obj`` (no @) sends the path as text: the answer says to add the @."""
    detail = refused(send(client, multipart(part("mesh", b"spot.obj"), key_part())), 422)["detail"]
    assert "'mesh' is text, not a file" in detail and "-F mesh=@" in detail


def test_an_empty_file_is_called_empty(client):
    detail = refused(send(client, multipart(mesh_part(b""), key_part())), 415, "unsupported-format")["detail"]
    assert detail.startswith("the file is empty")


def test_a_part_header_over_4_kib_is_refused(client):
    body = multipart(part("mesh", MESH, filename="m" * 9000 + ".obj"), key_part())
    assert "Maximum header size exceeded" in refused(send(client, body), 422)["detail"]


def test_chunked_upload_beyond_the_limit_in_process():
    with make_client(workers=1, max_upload_bytes=100_000) as small:
        head = f"--{BOUNDARY}\r\nContent-Disposition: form-data; name=\"mesh\"; filename=\"m.obj\"\r\n\r\n"
        chunks = iter([head.encode()] + [b"v 0 0 0\n" * 8192] * 50)  # 3.3 MB, no Content-Length
        body = refused(send(small, chunks), 413, "too-large")
        assert body["max_body_bytes"] == 100_000 + 64 * 1024


# ----------------------------------------------------------------------------- over a real socket

@pytest.fixture(scope="module")
def server(tmp_path_factory) -> Iterator[Server]:
    with serve(tmp_path_factory.mktemp("server") / "server.log", max_upload_bytes="100000") as s:
        yield s
    assert CANARY_KEY not in s.text()


def request(headers: bytes, body: bytes = b"") -> bytes:
    return (b"POST /v1/embed HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: " + FORM.encode() + b"\r\n"
            + headers + b"\r\n" + body)


VALID = multipart(mesh_part(), key_part())


@pytest.mark.parametrize(("headers", "body", "status"), [
    (b"", b"", 422),  # no Content-Length and no body: an empty form
    (b"Content-Length: -5\r\n", VALID, 400),
    (b"Content-Length: abc\r\n", VALID, 400),
    (b"Content-Length: 5\r\nContent-Length: 6\r\n", VALID, 400),
    (b"Content-Length: 1000000000000000\r\n", b"", 413),  # refused before any byte of the body
    (b"Content-Length: 99999999999999999999\r\n", b"", 400),  # past 2**64: not a length at all
    (b"Content-Length: 10\r\nTransfer-Encoding: chunked\r\n", VALID, 400),
    (b"Transfer-Encoding: chunked\r\n", b"zz\r\n" + VALID, 400),
], ids=["none", "negative", "not-a-number", "two-different", "huge", "overflow", "with-chunked",
         "bad-chunk-size"])
def test_content_length_games(server, headers, body, status):
    got, response_headers, content, seconds = raw_exchange(server.port, request(headers, body))
    assert got == status, content[:300]
    assert seconds < FAST
    assert CANARY_KEY.encode() not in content
    if status != 400:  # 400s come from the HTTP parser (httptools), before the app: plain text
        assert response_headers["content-type"] == "application/problem+json"


def test_chunked_body_beyond_the_limit_over_a_socket(server):
    head = (f"--{BOUNDARY}\r\nContent-Disposition: form-data; name=\"mesh\"; filename=\"m.obj\"\r\n\r\n"
            ).encode()
    chunk = b"v 0 0 0\n" * 4096
    chunks = [b"%x\r\n%s\r\n" % (len(head), head)] + [b"%x\r\n%s\r\n" % (len(chunk), chunk)] * 100  # 3.3 MB
    status, headers, content, seconds = raw_exchange(
        server.port, request(b"Transfer-Encoding: chunked\r\n"), body_chunks=chunks)
    assert status == 413 and headers["content-type"] == "application/problem+json", content[:300]
    assert seconds < FAST
    # the server is still fine
    status, _, content, _ = raw_exchange(server.port, b"GET /readyz HTTP/1.1\r\nHost: x\r\n\r\n")
    assert status == 200, content


def test_key_header_abuse_over_a_socket(server):
    """60 KB, Latin-1 and binary header values: refused by the HTTP parser or as a bad form."""
    body = multipart(mesh_part())
    for value in (b"k" * 60_000, b"caf\xe9", b"\xff" * 10, CANARY_KEY.encode() + b"\x7f"):
        headers = b"X-Watermark-Key: " + value + b"\r\nContent-Length: %d\r\n" % len(body)
        status, _, content, seconds = raw_exchange(server.port, request(headers, body))
        assert status in (400, 422, 431), content[:300]
        assert seconds < FAST and CANARY_KEY.encode() not in content
