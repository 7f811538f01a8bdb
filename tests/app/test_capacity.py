"""POST /v1/capacity: room for a payload without embedding."""

from __future__ import annotations

import dataclasses

from core.api import CapacityReport
from tests.app.conftest import assert_problem, shared_mesh


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
    assert_problem(client.post("/v1/capacity", data={"method": "planes"}), 422, "bad-form")
    assert_problem(client.post("/v1/capacity", files={"mesh": ("s.obj", b"v 0 0 0\nf 1 1\n")}), 422,
                   "malformed-mesh")
