"""Hostile uploads through the HTTP API: each is refused quickly (under 1 s) with the documented
problem type, never a 500; no file outside the request is opened (canary files and a canary TCP
listener stay untouched), no temporary file or descriptor is left behind, and the watermark key
appears in no answer and no log record.

The format readers have their own, finer tests (``tests/core/formats``); these prove the same
files are handled end to end: multipart, admission, worker process, problem mapping.
"""

from __future__ import annotations

import json
import logging
import os
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from app.problems import CORE_ERRORS
from core.coding import codeword_length
from tests.app import hostile as H
from tests.app.conftest import assert_problem, make_client, wait_job
from tests.core.formats import helpers as F
from tests.core.formats.test_text_formats import MALFORMED

CANARY_KEY = "CANARY-KEY-5d2c-never-in-a-log"
ROUTES = ("/v1/embed", "/v1/detect", "/v1/capacity")
FAST = 1.0  # seconds


@pytest.fixture(scope="module")
def private_tmp(tmp_path_factory) -> Iterator[Path]:
    """The system temp dir as the app sees it: a private one, so that other processes on the
    machine cannot make the before/after listings differ."""
    path = tmp_path_factory.mktemp("system-tmp")
    old = tempfile.tempdir
    tempfile.tempdir = str(path)
    try:
        yield path
    finally:
        tempfile.tempdir = old


@pytest.fixture(scope="module")
def client(private_tmp) -> Iterator[TestClient]:
    with make_client(workers=2, job_timeout_seconds=20) as c:
        yield c


@pytest.fixture(autouse=True)
def nothing_left_behind(client, private_tmp, caplog) -> Iterator[None]:
    """Per test: same temp-dir listing, same open descriptors, no key in any log record."""
    caplog.set_level(logging.DEBUG)
    before, fds = sorted(os.listdir(private_tmp)), len(os.listdir("/proc/self/fd"))
    yield
    assert sorted(os.listdir(private_tmp)) == before
    assert len(os.listdir("/proc/self/fd")) <= fds + 2  # (the event loop may open a wake-up pipe)
    for record in caplog.records:
        assert CANARY_KEY not in record.getMessage() and CANARY_KEY not in str(record.exc_info or "")


def post(client: TestClient, name: str, data: bytes, route: str = "/v1/embed", **fields: str) -> Any:
    form = {"key": CANARY_KEY, **fields} if route != "/v1/capacity" else fields
    start = time.perf_counter()
    response = client.post(route, files={"mesh": (name, data)}, data=form)
    response.elapsed_seconds = time.perf_counter() - start
    assert CANARY_KEY.encode() not in response.content
    assert not any(CANARY_KEY in v for v in response.headers.values())
    assert H.CANARY_MARKER not in response.content
    return response


def refused(response: Any, status: int, slug: str, limit: float = FAST) -> dict[str, Any]:
    body = assert_problem(response, status, slug)
    assert response.elapsed_seconds < limit, f"{slug} took {response.elapsed_seconds:.2f} s"
    return body


# ------------------------------------------------------------------------------------- glTF

@pytest.fixture
def canaries(tmp_path, monkeypatch) -> Iterator[dict[str, Any]]:
    """A canary file whose bytes are a *valid* buffer (so resolving it would make a read succeed),
    a FIFO (opening it would block), a TCP listener (fetching would connect).  The cwd is a folder
    below them, so ``../canary.bin`` reaches the file from this process; the worker processes keep
    the cwd of the fork server they come from, so there the absolute and ``file://`` URIs are the
    ones that point at the canaries."""
    v, f = H.icosphere(5)
    meta, blob = F.gltf_document(v, f)
    (tmp_path / "canary.bin").write_bytes(blob + H.CANARY_MARKER)
    (tmp_path / "canary.mtl").write_bytes(b"newmtl red\n# " + H.CANARY_MARKER + b"\n")
    os.mkfifo(tmp_path / "canary.fifo")
    (tmp_path / "sub").mkdir()
    monkeypatch.chdir(tmp_path / "sub")
    with H.listening_canary() as (port, connections):
        yield {"dir": tmp_path, "port": port, "connections": connections, "meta": meta, "blob": blob}
    assert connections == [], "the server made a network connection"


def _external_uris(c: dict[str, Any], name: str) -> list[str]:
    path = c["dir"] / name
    return [str(path), "../" + name, "file:../" + name, f"file://{path}",
            f"http://127.0.0.1:{c['port']}/{name}"]


@pytest.mark.parametrize("container", ["gltf", "glb"])
@pytest.mark.parametrize("which", range(5), ids=["absolute", "dotdot", "file-relative", "file-url", "http"])
def test_gltf_external_buffer_uri_is_refused_unopened(client, canaries, container, which):
    meta = json.loads(json.dumps(canaries["meta"]))
    meta["buffers"][0]["uri"] = _external_uris(canaries, "canary.bin")[which]
    data = F.to_gltf(meta) if container == "gltf" else F.to_glb(meta, None)
    body = refused(post(client, f"m.{container}", data), 422, "malformed-mesh")
    assert "external buffer refused" in body["detail"]


def test_gltf_external_image_uris_are_kept_and_never_opened(client, canaries):
    uris = _external_uris(canaries, "canary.bin") + [str(canaries["dir"] / "canary.fifo"),
                                                     "../canary.fifo"]
    data = F.to_gltf(H.with_images(canaries["meta"], uris), canaries["blob"])
    response = post(client, "m.gltf", data)
    assert response.status_code == 200, response.text[:500]
    assert response.elapsed_seconds < 10  # a FIFO opened for reading would block until the time limit
    assert json.loads(response.content)["images"] == [{"uri": uri} for uri in uris]


def test_gltf_accessor_with_huge_count_and_no_buffer_view(client):
    meta, blob = F.gltf_document(*H.icosphere(1))
    meta["accessors"][0] = {"componentType": 5126, "count": 2**40, "type": "VEC3"}
    for data, name in ((F.to_glb(meta, blob), "m.glb"), (F.to_gltf(meta, blob), "m.gltf")):
        assert "no bufferView" in refused(post(client, name, data), 422, "malformed-mesh")["detail"]


def test_glb_chunk_length_beyond_the_file(client):
    data = bytearray(F.to_glb(*F.gltf_document(*H.icosphere(1))))
    json_length = int.from_bytes(data[12:16], "little")
    data[20 + json_length: 24 + json_length] = (2**31).to_bytes(4, "little")  # BIN chunk length
    assert "past the end" in refused(post(client, "m.glb", bytes(data)), 422, "malformed-mesh")["detail"]
    data[12:16] = (2**32 - 1).to_bytes(4, "little")  # JSON chunk length
    refused(post(client, "m.glb", bytes(data)), 422, "malformed-mesh")


@pytest.mark.parametrize("container", ["gltf", "glb"])
def test_deeply_nested_json(client, container):
    text = H.deep_json(100_000)
    data = text if container == "gltf" else H.glb_json_chunk(text)
    assert "nested deeper" in refused(post(client, f"m.{container}", data), 422, "malformed-mesh")["detail"]


def test_oversized_and_broken_base64(client):
    v, f = H.icosphere(5)
    meta, blob = F.gltf_document(v, f)
    # 3 MB of base64 that breaks at the very end: found without decoding into a mesh
    broken = json.loads(json.dumps(meta))
    broken["buffers"][0]["uri"] = F.data_uri(blob + bytes(2_000_000))[:-8] + "@@@@@@@@"
    refused(post(client, "m.gltf", json.dumps(broken).encode()), 422, "malformed-mesh")
    # a buffer declared far larger than its data
    short = json.loads(json.dumps(meta))
    short["buffers"][0].update(byteLength=2**40, uri=F.data_uri(blob))
    refused(post(client, "m.gltf", json.dumps(short).encode()), 422, "malformed-mesh")
    # base64 beyond the upload limit: 413 from Content-Length, before anything is parsed
    with make_client(workers=1, max_upload_bytes=256 * 1024) as small:
        response = post(small, "m.gltf", F.to_gltf(meta, blob + bytes(1_000_000)))
        assert refused(response, 413, "too-large")["max_body_bytes"] == 256 * 1024 + 64 * 1024


# ------------------------------------------------------------------------------------- PLY

@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian", "binary_big_endian"])
def test_ply_declaring_4e9_vertices(client, fmt):
    data = F.ply_header(fmt, 4_000_000_000, 1) + bytes(64)
    body = refused(post(client, "m.ply", data), 413, "too-large")
    assert (body["what"], body["value"]) == ("vertices", 4_000_000_000)


def _drum(n: int = 255) -> tuple[np.ndarray, list[list[int]]]:
    """A closed prism whose two caps are ``n``-gons (face lists of ``n`` entries)."""
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    ring = np.stack([np.cos(t), np.sin(t), np.zeros(n)], axis=1)
    verts = np.concatenate([ring, ring + [0, 0, 1]]).astype(np.float32)
    faces = [list(range(n))[::-1], list(range(n, 2 * n))]
    faces += [[i, (i + 1) % n, (i + 1) % n + n, i + n] for i in range(n)]
    return verts, faces


def test_ply_face_lists_of_255_entries(client):
    verts, faces = _drum(255)
    for data in (F.ply_binary(verts, faces), F.ply_ascii(verts, faces)):
        # a legal file: fan-triangulated, then too coarse for the key-derived code
        body = refused(post(client, "drum.ply", data), 422, "too-little-capacity")
        assert body["carriers"] < body["needed"]
        report = post(client, "drum.ply", data, route="/v1/capacity")
        assert report.status_code == 200 and report.json()["max_payload_bits"] == 0
    # a 255-entry list that the file ends inside of
    truncated = F.ply_binary(verts[:4], [[0, 1, 2]])[:-13] + bytes([255]) + bytes(12)
    assert "ends inside" in refused(post(client, "t.ply", truncated), 422, "malformed-mesh")["detail"]
    # 255 entries pointing past the vertices
    wild = F.ply_binary(verts[:4], [list(range(255))])
    refused(post(client, "w.ply", wild), 422, "malformed-mesh")


TETRA = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float32)


@pytest.mark.parametrize(("name", "data"), [
    ("ply-ascii-out-of-range", F.ply_ascii(TETRA, [[0, 1, 2], [0, 1, 4]])),
    ("ply-ascii-negative", F.ply_ascii(TETRA, [[0, 1, 2], [0, -1, 3]])),
    ("ply-binary-out-of-range", F.ply_binary(TETRA, [[0, 1, 2], [0, 1, 2**31 - 1]])),
    ("ply-binary-negative", F.ply_binary(TETRA, [[0, 1, 2], [-2**31, 1, 3]])),
    ("ply-binary-uint-max", F.ply_binary(TETRA, [[0, 1, 2], [2**32 - 1, 1, 3]], index="I")),
    ("obj-out-of-range", F.obj_text(TETRA, [[0, 1, 2], [0, 1, 99]])),
    ("obj-negative-too-far", F.obj_text(TETRA, [[0, 1, 2]]) + b"f -1 -2 -9\n"),
    ("off-negative", b"OFF\n4 2 0\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n3 0 1 2\n3 0 -1 3\n"),
], ids=lambda x: x if isinstance(x, str) else "")
def test_out_of_range_and_negative_indices(client, name, data):
    ext = name.split("-")[0]
    assert "index" in refused(post(client, f"m.{ext}", data), 422, "malformed-mesh")["detail"]


def _with(vertex: list[float]) -> np.ndarray:
    v = TETRA.astype(np.float64).copy()
    v[2] = vertex
    return v


@pytest.mark.parametrize(("name", "data"), [
    ("ply-binary-nan", F.ply_binary(_with([0, np.nan, 0]), [[0, 1, 2], [0, 1, 3]])),
    ("ply-binary-inf", F.ply_binary(_with([0, np.inf, 0]), [[0, 1, 2], [0, 1, 3]])),
    ("ply-ascii-nan", F.ply_ascii(_with([0, np.nan, 0]), [[0, 1, 2], [0, 1, 3]])),
    ("obj-inf", F.obj_text(_with([0, -np.inf, 0]), [[0, 1, 2], [0, 1, 3]])),
    ("obj-overflow", F.obj_text(TETRA, [[0, 1, 2]]).replace(b"v 0.0 1.0 0.0", b"v 0.0 1e999 0.0")),
    ("stl-nan", F.binary_stl(_with([0, np.nan, 0])[[0, 1, 2, 0, 1, 3]])),
    ("off-inf", b"OFF\n4 2 0\n0 0 0\n1 0 0\n0 inf 0\n0 0 1\n3 0 1 2\n3 0 1 3\n"),
], ids=lambda x: x if isinstance(x, str) else "")
def test_nan_and_inf_coordinates(client, name, data):
    ext = name.split("-")[0]
    assert "non-finite" in refused(post(client, f"m.{ext}", data), 422, "malformed-mesh")["detail"]


def test_glb_nan_position(client):
    v, f = H.icosphere(1)
    v[3] = np.nan
    refused(post(client, "m.glb", F.to_glb(*F.gltf_document(v, f))), 422, "malformed-mesh")


# ------------------------------------------------------------------------------------- OBJ, STL, others

def test_obj_mtllib_pointing_outside_is_kept_verbatim_and_never_opened(client, canaries):
    mtl = canaries["dir"] / "canary.mtl"
    head = "\n".join([f"mtllib {mtl}", "mtllib ../canary.mtl", "mtllib ../../../../../../etc/passwd",
                      f"mtllib file://{mtl}", f"mtllib http://127.0.0.1:{canaries['port']}/canary.mtl",
                      f"mtllib {canaries['dir'] / 'canary.fifo'}", "usemtl red"])
    data = F.obj_text(*H.icosphere(5), head=head)
    response = post(client, "ball.obj", data)
    assert response.status_code == 200, response.text[:500]
    out_lines = response.content.split(b"\n")
    for line in head.split("\n"):
        assert line.encode() in out_lines
    assert b"root:" not in response.content
    assert response.elapsed_seconds < 10


def test_stl_whose_facet_count_disagrees_with_its_size(client):
    v, f = H.icosphere(2)
    tris = v[f]
    for count in (len(f) + 1, len(f) - 1, 2**32 - 1, 0):
        body = refused(post(client, "m.stl", F.binary_stl(tris, count=count)), 415, "unsupported-format")
        assert "binary STL" in body["detail"] and f"{count:,} facets" in body["detail"]
    tail = F.binary_stl(tris) + b"\0" * 7  # the right count, then junk
    refused(post(client, "m.stl", tail), 415, "unsupported-format")


@pytest.mark.parametrize(("name", "data"), [
    ("empty.obj", b""),
    ("empty.ply", b""),
    ("empty.glb", b""),
    ("photo.obj", H.JPEG),
    ("photo.jpg", H.JPEG),
    ("archive.obj", H.zip_of({"model.obj": b"v 0 0 0\n"})),
    ("archive.zip", H.zip_of({"model.obj": b"v 0 0 0\n"})),
    ("print.3mf", H.three_mf()),
    ("print.stl", H.three_mf()),
    ("scene.dae", H.billion_laughs_dae()),
    ("scene.obj", H.billion_laughs_dae()),
    ("big-junk.obj", H.JPEG * 2000),  # 2 MB: spooled to a temporary file by the multipart parser
], ids=lambda x: x if isinstance(x, str) else "")
def test_not_a_supported_format(client, name, data):
    for route in ROUTES:
        refused(post(client, name, data, route=route), 415, "unsupported-format")


# the core tests' malformed files, end to end (each engine exception maps to one problem type)
@pytest.mark.parametrize("case", sorted(MALFORMED))
def test_core_malformed_files_through_http(client, case):
    name, data, error = MALFORMED[case]
    problem = next(CORE_ERRORS[cls] for cls in error.__mro__ if cls in CORE_ERRORS)
    refused(post(client, name, data), problem.status, problem.slug)


# ------------------------------------------------------------------------------------- no room for a mark

def _soup(subdivisions: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Each triangle its own 3 vertices, nudged apart so that no position is shared."""
    v, f = H.icosphere(subdivisions)
    corners = v[f].reshape(-1, 3).astype(np.float64)
    corners += np.random.default_rng(0).normal(scale=1e-3, size=corners.shape)
    return corners, np.arange(len(corners)).reshape(-1, 3)


CANNOT_CARRY = [
    ("triangle.obj", F.obj_text(TETRA[:3], [[0, 1, 2]]), "degenerate-mesh", "fewer than 4"),
    ("cloud.ply", F.ply_binary(np.random.default_rng(1).random((500, 3)), []), "degenerate-mesh",
     "point cloud"),
    ("collinear.obj", F.obj_text(np.stack([np.arange(50.0), np.zeros(50), np.zeros(50)], axis=1),
                                 [[i, i + 1, i + 2] for i in range(48)]), "degenerate-mesh", "zero area"),
    ("repeated.ply", F.ply_ascii(TETRA, [[0, 0, 1], [2, 3, 3], [1, 1, 1]]), "degenerate-mesh",
     "repeats a vertex"),
    ("soup.obj", F.obj_text(*_soup()), "too-little-capacity", "triangle soup"),
]


@pytest.mark.parametrize(("name", "data", "slug", "reason"), CANNOT_CARRY,
                         ids=[c[0] for c in CANNOT_CARRY])
def test_meshes_that_parse_but_cannot_carry_a_mark(client, name, data, slug, reason):
    body = refused(post(client, name, data), 422, slug)
    assert reason in body["detail"], body["detail"]
    if slug == "too-little-capacity":
        assert body["carriers"] == 0 and body["needed"] == codeword_length(None)


_OVERFLOW_OBJ = b"v 0 0 0\nv 1e200 0 0\nv 0 1e200 0\nv 0 0 1e200\nf 1 2 3\nf 1 2 4\nf 1 3 4\nf 2 3 4\n"


@pytest.mark.parametrize("path", ["/v1/embed", "/v1/detect", "/v1/capacity", "/v1/preview", "/v1/jobs/embed"])
def test_coordinates_that_overflow_are_malformed_not_a_500(client, path):
    # a 76-byte OBJ whose bounding-box diagonal overflows float64 was a 500 on every route
    response = client.post(path, files={"mesh": ("a.obj", _OVERFLOW_OBJ)}, data={"key": "some key"})
    if path.startswith("/v1/jobs"):
        assert response.status_code == 202
        status = wait_job(client, response.json()["id"])
        assert status["state"] == "failed" and status["error"]["status"] == 422, status
        return
    assert_problem(response, 422, "malformed-mesh")
