"""``POST /v1/preview``: geometry read by the engine's readers, in the documented binary layout."""

from __future__ import annotations

import numpy as np
import pytest

from app.preview import PREVIEW_MEDIA_TYPE, unpack
from core.formats import read_mesh
from core.preview import merged_parts
from tests.app.conftest import KEY, assert_problem, embed, make_client, shared_mesh


def preview(client, name, data, original=None, original_name=None, **headers):
    files = [("mesh", (name, data))]
    if original is not None:
        files.append(("original", (original_name or name, original)))
    return client.post("/v1/preview", files=files, headers=headers)


def test_preview_sends_what_the_engine_reads(client):
    data = shared_mesh("CesiumMilkTruck.glb")  # several parts
    response = preview(client, "truck.glb", data)
    assert response.status_code == 200, response.text
    assert response.headers["content-type"] == PREVIEW_MEDIA_TYPE
    assert response.headers["cache-control"] == "no-store"
    head, positions, triangles, displacement = unpack(response.content)
    V, F = merged_parts(read_mesh(data, "truck.glb"))
    assert head["parts"] > 1 and head["format"] == "glb" and displacement is None
    assert (head["vertices"], head["triangles"]) == (len(V), len(F))
    np.testing.assert_array_equal(triangles, F)
    np.testing.assert_allclose(positions + np.array(head["center"]), V, atol=1e-5 * head["diagonal"])
    assert head["diagonal"] == pytest.approx(np.linalg.norm(V.max(axis=0) - V.min(axis=0)))


def test_heat_map_of_a_marked_file_agrees_with_the_embedding(client, sphere_obj):
    marked = embed(client, "sphere.obj", sphere_obj)
    assert marked.status_code == 200
    answer = preview(client, "sphere.marked.obj", marked.content, sphere_obj)
    head, _, _, displacement = unpack(answer.content)
    assert head["displacement"] and head["comparison"] is None and displacement is not None
    assert head["vertices_moved"] == int(marked.headers["X-MeshMark-Vertices-Moved"])
    assert np.count_nonzero(displacement) == head["vertices_moved"]
    # the header rounds to 6 significant digits; displacement is float32
    assert float(displacement.max()) == pytest.approx(float(marked.headers["X-MeshMark-Max-Displacement"]),
                                                      rel=1e-5)


def test_unrelated_original_gives_geometry_and_the_reason(client, sphere_obj):
    other = shared_mesh("teapot.stl")
    response = preview(client, "sphere.obj", sphere_obj, other, "teapot.stl")
    head, _, _, displacement = unpack(response.content)
    assert displacement is None and not head["displacement"]
    assert "original has" in head["comparison"]


@pytest.mark.parametrize(("name", "data", "status", "slug"), [
    ("broken.ply", b"ply\nformat ascii 1.0\nelement vertex 3\nend_header\n1 2\n", 422, "malformed-mesh"),
    ("notes.txt", b"hello, not a mesh", 415, "unsupported-format"),
    ("points.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\n", 422, "degenerate-mesh"),
])
def test_bad_files_are_problems(client, name, data, status, slug):
    assert_problem(preview(client, name, data), status, slug)


def test_a_bad_original_is_named(client, sphere_obj):
    answer = preview(client, "s.obj", sphere_obj, b"solid x\nfacet normal 0 0 1\n", "o.stl")
    body = assert_problem(answer, 422, "malformed-mesh")
    assert body["detail"].startswith("original: ")


def test_form_takes_two_files_and_no_more(client, sphere_obj):
    files = [("mesh", ("a.obj", sphere_obj)), ("original", ("b.obj", sphere_obj)), ("extra", ("c.obj", b"x"))]
    body = assert_problem(client.post("/v1/preview", files=files), 422, "bad-form")
    assert "files" in body["detail"].lower()
    assert_problem(client.post("/v1/preview", files=[("original", ("b.obj", sphere_obj))]), 422, "bad-form")
    twice = [("mesh", ("a.obj", sphere_obj)), ("mesh", ("b.obj", sphere_obj))]
    assert_problem(client.post("/v1/preview", files=twice), 422, "bad-form")


def test_limits_and_api_keys_apply(sphere_obj):
    with make_client(max_vertices=100, api_keys="k1-0123456789abcdef") as client:
        assert_problem(preview(client, "s.obj", sphere_obj), 401, "unauthorized")
        answer = preview(client, "s.obj", sphere_obj, Authorization="Bearer k1-0123456789abcdef")
        body = assert_problem(answer, 413, "too-large")
        assert body["what"] == "vertices"


def test_busy_pool_refuses_a_preview(big_ply, sphere_obj):
    with make_client(workers=1, queue_size=1) as client:
        client.post("/v1/jobs/embed", files={"mesh": ("big.ply", big_ply)}, data={"key": KEY})
        response = preview(client, "s.obj", sphere_obj)
        assert_problem(response, 429, "busy")
        assert int(response.headers["retry-after"]) >= 1
