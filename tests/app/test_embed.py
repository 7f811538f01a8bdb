"""POST /v1/embed: round trips on real meshes, response headers, and every input problem."""

from __future__ import annotations

import json

import pytest
import trimesh

from tests.app.conftest import KEY, assert_problem, detect, embed, make_client, shared_mesh


@pytest.mark.parametrize(("name", "payload"), [("rocker-arm.obj", "1011001110001111"), ("fandisk.off", None),
                                               ("bun_zipper.ply", "10" * 40)])
def test_embed_then_detect_round_trip(client, name, payload):
    data = shared_mesh(name)
    response = embed(client, name, data, **({"payload": payload} if payload else {}))
    assert response.status_code == 200, response.text
    stem, ext = name.rsplit(".", 1)
    assert response.headers["content-disposition"] == f'attachment; filename="{stem}.marked.{ext}"'
    assert response.headers["content-type"] == {"obj": "model/obj", "off": "application/off",
                                                "ply": "application/x-ply"}[ext]
    assert response.content != data

    found = detect(client, name, response.content).json()
    assert found["detected"] is True
    if payload:
        assert found["payload"] == payload and found["crc_ok"] is True
    else:
        assert found["key_derived"] is True and len(found["payload"]) == 32
    assert not detect(client, name, response.content, key="some other key").json()["detected"]


def test_a_mesh_too_coarse_for_the_method_is_refused_with_what_fits(client):
    """Spot (2,930 vertices) with ellipsoids needs moves past the displacement ceiling for a 192-bit
    payload under this key (128 bits fit since the convolutional code, 48 with Hamming(7,4) before):
    422, and the detail names the method that fits, which then embeds.  Without a method the service
    takes that one itself: the file reads back and its report and header say planes."""
    data = shared_mesh("spot.obj")
    payload = "1011001110001111" * 12
    body = assert_problem(embed(client, "spot.obj", data, payload=payload, method="ellipsoids"), 422,
                          "too-little-capacity")
    assert "ceiling" in body["detail"] and "method=planes" in body["detail"], body
    assert embed(client, "spot.obj", data, payload=payload, method="planes").status_code == 200
    chosen = embed(client, "spot.obj", data, payload=payload)
    assert chosen.status_code == 200, chosen.text
    assert chosen.headers["x-meshmark-method"] == "planes"
    assert json.loads(chosen.headers["x-meshmark-report"])["method"] == "planes"
    found = detect(client, "spot.obj", chosen.content, payload=payload).json()
    assert found["payload"] == payload and found["method"] == "planes", found


def test_binary_stl_keeps_its_size(client):
    data = trimesh.creation.icosphere(subdivisions=5).export(file_type="stl")
    response = embed(client, "ball.stl", data)
    assert response.status_code == 200, response.text
    assert response.headers["content-type"] == "model/stl"
    assert len(response.content) == len(data) and response.content != data
    assert detect(client, "ball.stl", response.content).json()["detected"]


def test_report_headers_match_the_report(client, sphere_obj):
    response = embed(client, "sphere.obj", sphere_obj)
    assert response.status_code == 200, response.text
    h = response.headers
    report = json.loads(h["x-meshmark-report"])
    assert report["key_derived"] is True and report["payload_bits"] == 32
    assert h["x-meshmark-method"] == report["method"] == "ellipsoids"
    assert int(h["x-meshmark-carriers"]) == report["carriers"] > 0
    assert int(h["x-meshmark-payload-bits"]) == 32
    assert int(h["x-meshmark-vertices-moved"]) == report["vertices_moved"] > 0
    assert float(h["x-meshmark-copies"]) == pytest.approx(report["copies"], rel=1e-6)
    for name, field in [("rms-displacement", "rms_displacement"), ("max-displacement", "max_displacement"),
                        ("hausdorff", "hausdorff")]:
        assert float(h[f"x-meshmark-{name}"]) == pytest.approx(report[field], rel=1e-5)
    assert 0 < report["rms_displacement"] <= report["max_displacement"] < 0.05
    assert int(h["x-meshmark-skipped-elements"]) == report["skipped_elements"] == 0
    assert h["x-meshmark-reencoded"] == "none" and report["reencoded"] == []


def test_skipped_elements_header(client, sphere_obj):
    untidy = sphere_obj + b"f 1 2\nl 1 2 3\np 4\n"
    response = embed(client, "sphere.obj", untidy)
    assert response.status_code == 200, response.text
    assert response.headers["x-meshmark-skipped-elements"] == "3"
    assert response.content.endswith(b"f 1 2\nl 1 2 3\np 4\n")


def test_key_in_header_and_planes_method(client, sphere_ply):
    key = "clé secrète ✓"
    response = client.post("/v1/embed", files={"mesh": ("s.ply", sphere_ply)},
                           data={"method": "planes", "strength": "0.1"},
                           headers={"X-Watermark-Key": key.encode()})
    assert response.status_code == 200, response.text
    assert response.headers["x-meshmark-method"] == "planes"
    assert json.loads(response.headers["x-meshmark-report"])["strength"] == 0.1
    # the same UTF-8 key as a form field finds it
    found = detect(client, "s.ply", response.content, key=key, method="planes").json()
    assert found["detected"] and found["method"] == "planes"


def test_download_name_is_sanitised(client, sphere_obj):
    response = embed(client, "..\\..\\my mesh;v2 é.obj", sphere_obj)
    assert response.headers["content-disposition"] == 'attachment; filename="my_mesh_v2.marked.obj"'


@pytest.mark.parametrize(("fields", "fragment"), [
    ({}, "key is required"),
    ({"key": ""}, "key is required"),
    ({"key": "x" * 1025}, "at most 1024"),
    ({"key": "line\n"}, "control, format or separator"),
    ({"key": "right-to-left \u202e mark"}, "control, format or separator"),
    ({"key": "next line \x85"}, "control, format or separator"),
    ({"key": KEY, "payload": "10102"}, "payload"),
    ({"key": KEY, "payload": "1" * 257}, "payload"),
    ({"key": KEY, "method": "spheres"}, "method"),
    ({"key": KEY, "strength": "-1"}, "strength"),
    ({"key": KEY, "strength": "nan"}, "strength"),
    ({"key": KEY, "strength": "strong"}, "strength"),
])
def test_bad_form_fields(client, sphere_obj, fields, fragment):
    response = client.post("/v1/embed", files={"mesh": ("s.obj", sphere_obj)}, data=fields)
    body = assert_problem(response, 422, "bad-form")
    assert fragment in body["detail"]


def test_missing_mesh_and_both_key_sources(client, sphere_obj):
    body = assert_problem(client.post("/v1/embed", files={"key": (None, KEY)}), 422, "bad-form")
    assert body["errors"] == [{"loc": ["body", "mesh"], "msg": "Field required", "type": "missing"}]
    response = client.post("/v1/embed", files={"mesh": ("s.obj", sphere_obj)}, data={"key": KEY},
                           headers={"X-Watermark-Key": KEY})
    assert "once" in assert_problem(response, 422, "bad-form")["detail"]


def test_key_that_is_not_utf8(client, sphere_obj):
    response = client.post("/v1/embed", files={"mesh": ("s.obj", sphere_obj), "key": (None, b"caf\xe9")})
    assert "not valid UTF-8" in assert_problem(response, 422, "bad-form")["detail"]
    # (TestClient re-encodes header bytes; the X-Watermark-Key case is in test_server.py)


def test_unsupported_format(client):
    jpeg = b"\xff\xd8\xff\xe0\x00\x10JFIF\x00\x01\x01\x00\x00\x01\x00\x01\x00\x00" + bytes(200)
    assert_problem(embed(client, "photo.obj", jpeg), 415, "unsupported-format")


def test_malformed_degenerate_and_too_small_meshes(client):
    bad = b"v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 9\n"
    assert "line 5" in assert_problem(embed(client, "bad.obj", bad), 422, "malformed-mesh")["detail"]
    truncated = trimesh.creation.icosphere(subdivisions=5).export(file_type="ply")[:5000]
    assert "ends early" in assert_problem(embed(client, "s.ply", truncated), 422, "malformed-mesh")["detail"]
    triangle = b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n"
    assert_problem(embed(client, "tri.obj", triangle), 422, "degenerate-mesh")
    tetrahedron = b"v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\nf 1 3 4\nf 2 3 4\n"
    body = assert_problem(embed(client, "tet.obj", tetrahedron), 422, "too-little-capacity")
    assert body["needed"] > body["carriers"]


def test_too_large():
    # a 2,562-vertex icosphere: 174 kB as OBJ, 97 kB as binary PLY
    sphere_obj = trimesh.creation.icosphere(subdivisions=4).export(file_type="obj").encode()
    sphere_ply = trimesh.creation.icosphere(subdivisions=4).export(file_type="ply")
    with make_client(workers=1, max_upload_bytes=120_000, max_vertices=1000) as small:
        # 174 kB: within the body cap (file cap + 64 KiB), over the file cap: the engine refuses it
        body = assert_problem(embed(small, "sphere.obj", sphere_obj), 413, "too-large")
        assert (body["what"], body["limit"]) == ("bytes", 120_000)
        # 330 kB: refused from Content-Length, before any parsing
        body = assert_problem(embed(small, "spot.obj", shared_mesh("spot.obj")), 413, "too-large")
        assert body["max_body_bytes"] == 120_000 + 64 * 1024
        # no Content-Length (chunked): cut off while streaming
        chunks = (b"x" * 8192 for _ in range(30))
        response = small.post("/v1/embed", content=chunks,
                              headers={"content-type": "multipart/form-data; boundary=b"})
        assert "max_body_bytes" in assert_problem(response, 413, "too-large")
        # 97 kB but 2562 vertices
        body = assert_problem(embed(small, "sphere.ply", sphere_ply), 413, "too-large")
        assert (body["what"], body["value"], body["limit"]) == ("vertices", 2562, 1000)


def test_reencoded_header_for_a_draco_glb(client):
    """A Draco-compressed GLB comes back Draco-compressed, and the answer says it was re-encoded."""
    import DracoPy
    import numpy as np

    from core.formats import read_mesh
    from tests.core.formats.test_gltf_encodings import draco_glb

    part = read_mesh(shared_mesh("Duck.glb"), "Duck.glb").parts[0]
    stream = DracoPy.encode(part.vertices.astype(np.float32), part.faces, quantization_bits=14)
    data = draco_glb(part.vertices, part.faces, stream)
    response = embed(client, "duck.glb", data)
    assert response.status_code == 200, response.text
    assert response.headers["x-meshmark-reencoded"] == "draco"
    assert b"KHR_draco_mesh_compression" in response.content[:4096]
    assert detect(client, "duck.glb", response.content).json()["detected"]
