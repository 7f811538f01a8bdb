"""POST /v1/capacity: room for a payload without embedding."""

from __future__ import annotations

import dataclasses

from core.api import CapacityReport
from tests.app.conftest import KEY, assert_problem, embed, shared_mesh


def test_capacity_of_a_real_mesh(client):
    response = client.post("/v1/capacity", files={"mesh": ("spot.obj", shared_mesh("spot.obj"))})
    assert response.status_code == 200, response.text
    report = response.json()
    assert set(report) == {f.name for f in dataclasses.fields(CapacityReport)}
    assert report["method"] == "ellipsoids" and report["carriers"] > 100
    assert 0 < report["max_payload_bits"] <= 256


def test_capacity_grows_with_strength(client, sphere_obj):
    def carriers(strength: str) -> int:
        response = client.post("/v1/capacity", files={"mesh": ("s.obj", sphere_obj)},
                               data={"method": "planes", "strength": strength})
        assert response.status_code == 200, response.text
        assert response.json()["method"] == "planes"
        return int(response.json()["carriers"])

    assert carriers("0.2") >= carriers("0.02")


def test_capacity_needs_no_key_but_a_mesh(client):
    assert_problem(client.post("/v1/capacity", files={"method": (None, "planes")}), 422, "bad-form")
    assert_problem(client.post("/v1/capacity", files={"mesh": ("s.obj", b"v 0 0 0\nf 1 1 9\n")}), 422,
                   "malformed-mesh")
    # a two-corner face is skipped (untidy, not broken): then no triangle is left
    assert_problem(client.post("/v1/capacity", files={"mesh": ("s.obj", b"v 0 0 0\nf 1 1\n")}), 422,
                   "degenerate-mesh")


def test_with_the_key_capacity_counts_the_carriers_embedding_will_have(client):
    """Carriers depend on the key: without one, capacity uses a probe key (an estimate); with the
    caller's key, the count is the one the embedding reports (X-MeshMark-Carriers)."""
    spot = shared_mesh("spot.obj")
    marked = embed(client, "spot.obj", spot)
    exact = client.post("/v1/capacity", files={"mesh": ("spot.obj", spot)}, data={"key": KEY}).json()
    assert exact["carriers"] == int(marked.headers["x-meshmark-carriers"])
    by_header = client.post("/v1/capacity", files={"mesh": ("spot.obj", spot)},
                            headers={"X-Watermark-Key": "another key"}).json()
    assert by_header["carriers"] != exact["carriers"]
