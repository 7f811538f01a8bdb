"""POST /v1/capacity: room for a payload without embedding."""

from __future__ import annotations

import dataclasses

from core.api import CapacityReport
from tests.app.conftest import KEY, assert_problem, embed, shared_mesh


def test_capacity_of_a_real_mesh(client):
    """Without a method, the report of the method that carries the longer payload (ellipsoids on a tie),
    as an embedding without one chooses."""
    def asked(**method: str) -> dict[str, object]:
        response = client.post("/v1/capacity", files={"mesh": ("spot.obj", shared_mesh("spot.obj"))},
                               data=method)
        assert response.status_code == 200, response.text
        return dict(response.json())

    report = asked()
    assert set(report) == {f.name for f in dataclasses.fields(CapacityReport)}
    assert report["carriers"] > 100 and 0 < report["max_payload_bits"] <= 256
    each = {m: asked(method=m) for m in ("ellipsoids", "planes")}
    best = max(each.values(), key=lambda r: (r["max_payload_bits"], r["method"] == "ellipsoids"))
    assert report == best, (report, each)


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
