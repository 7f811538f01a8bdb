"""POST /v1/copies and /v1/trace: copies recorded in a real registry (SQLite, then PostgreSQL),
leaks traced back to their recipients, collusions, innocents and refusals."""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import trimesh
from fastapi.testclient import TestClient

from app.registry import Registry, sqlite_url
from core.formats import read_mesh
from tests.app.conftest import KEY, assert_problem, make_client, shared_mesh
from tests.app.registries import postgres_database

NAME = "rocker-arm.obj"


@pytest.fixture(scope="module")
def registry_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("registry") / "copies.sqlite3"


@pytest.fixture(scope="module")
def tracing_client(registry_file: Path) -> Iterator[TestClient]:
    with make_client(registry_path=registry_file) as c:
        yield c


def copy(client: TestClient, recipient: str, data: bytes | None = None, key: str = KEY,
         **fields: str) -> Any:
    return client.post("/v1/copies", files={"mesh": (NAME, data or shared_mesh(NAME))},
                       data={"key": key, "recipient": recipient, **fields})


def trace(client: TestClient, data: bytes, name: str = NAME, key: str = KEY, **fields: str) -> Any:
    response = client.post("/v1/trace", files={"mesh": (name, data)}, data={"key": key, **fields})
    assert response.status_code == 200, response.text
    return response.json()


def average(name: str, *copies: bytes) -> bytes:
    """The copies averaged vertex by vertex (what colluders with the same cover can do), as PLY."""
    parts = [read_mesh(c, name).parts[0] for c in copies]
    v = sum(p.vertices for p in parts) / len(parts)
    return trimesh.Trimesh(v, parts[0].faces, process=False).export(file_type="ply")


def test_copies_are_traced_to_their_recipients(tracing_client: TestClient, registry_file: Path) -> None:
    c = tracing_client
    copies = {}
    for who in ("alice", "bob", "carol", "dave ünïcode"):
        response = copy(c, who, asset_id="rocker")
        assert response.status_code == 200, response.text
        assert response.headers["x-meshmark-asset-id"] == "rocker"
        assert int(response.headers["x-meshmark-codeword-bits"]) >= 64
        assert float(response.headers["x-meshmark-fingerprint-score"]) > 8
        copies[who] = response.content
    assert len(set(copies.values())) == 4
    again = copy(c, "alice", asset_id="rocker")
    assert again.content == copies["alice"]  # idempotent per recipient

    leaked = trace(c, copies["bob"], asset_id="rocker")
    assert leaked["verdict"] == "accused" and leaked["accused"] == ["bob"]
    assert leaked["copies_scored"] == 4 and leaked["ranked"][0]["recipient"] == "bob"
    assert leaked["ranked"][0]["false_accusation_probability"] <= 1e-9 < leaked["ranked"][1][
        "false_accusation_probability"]
    assert trace(c, copies["dave ünïcode"])["accused"] == ["dave ünïcode"]  # every asset

    both = trace(c, average(NAME, copies["alice"], copies["carol"]), "avg.ply", asset_id="rocker")
    assert sorted(both["accused"]) == ["alice", "carol"]

    for suspect, key in ((shared_mesh(NAME), KEY), (copies["bob"], "another key")):
        nobody = trace(c, suspect, key=key, asset_id="rocker")
        assert nobody["verdict"] == "no-one" and nobody["accused"] == []
        assert all(r["false_accusation_probability"] > 1e-9 for r in nobody["ranked"])

    # the registry holds the copies, never the key
    stored = Registry(sqlite_url(registry_file))
    assert stored.count() == 4
    stored.close()
    assert KEY.encode() not in registry_file.read_bytes()


def test_the_default_asset_id_is_the_cover_hash(tracing_client: TestClient) -> None:
    response = copy(tracing_client, "erin")
    assert response.status_code == 200, response.text
    asset = response.headers["x-meshmark-asset-id"]
    assert asset.startswith("sha256:") and len(asset) == 7 + 64
    assert trace(tracing_client, response.content, asset_id=asset)["accused"] == ["erin"]


def test_refusals_are_problems(tracing_client: TestClient) -> None:
    c = tracing_client
    assert copy(c, "frank", asset_id="refusals").status_code == 200
    body = assert_problem(copy(c, "frank", asset_id="refusals", method="planes"), 409, "copy-conflict")
    assert body["method"] == "ellipsoids"
    assert_problem(copy(c, "bad\nname", asset_id="refusals"), 422, "bad-form")
    assert_problem(copy(c, "frank", asset_id="no spaces"), 422, "bad-form")
    assert_problem(c.post("/v1/trace", files={"mesh": (NAME, shared_mesh(NAME))},
                          data={"key": KEY, "asset_id": "nothing-issued"}), 404, "no-copies")
    assert_problem(c.post("/v1/trace", files={"mesh": (NAME, shared_mesh(NAME))},
                          data={"key": KEY, "threshold": "2"}), 422, "bad-form")
    tiny = trimesh.creation.icosphere(subdivisions=1).export(file_type="obj").encode()
    refused = c.post("/v1/copies", files={"mesh": ("tiny.obj", tiny)},
                     data={"key": KEY, "recipient": "x", "asset_id": "tiny"})
    assert_problem(refused, 422, "too-little-capacity")


def copy_job(client: TestClient, recipient: str, asset_id: str) -> Any:
    """The result of a copy job, once it has finished."""
    job = client.post("/v1/jobs/copies", files={"mesh": (NAME, shared_mesh(NAME))},
                      data={"key": KEY, "recipient": recipient, "asset_id": asset_id})
    assert job.status_code == 202, job.text
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        status = client.get(f"/v1/jobs/{job.json()['id']}").json()
        if status["state"] not in ("queued", "running"):
            break
        time.sleep(0.05)
    assert status["state"] == "succeeded", status
    return client.get(f"/v1/jobs/{job.json()['id']}/result")


def test_copy_job_gives_the_same_copy(tracing_client: TestClient) -> None:
    c = tracing_client
    sync = copy(c, "grace", asset_id="jobs")
    result = copy_job(c, "grace", "jobs")
    assert result.content == sync.content and result.headers["x-meshmark-asset-id"] == "jobs"
    leaked = copy_job(c, "heidi", "jobs").content
    assert trace(c, leaked, asset_id="jobs")["accused"] == ["heidi"]


def test_postgresql_registry_gives_the_same_answers() -> None:
    with postgres_database() as url, make_client(registry_url=url) as c:
        first = copy(c, "ivan", asset_id="pg")
        assert first.status_code == 200, first.text
        assert copy(c, "ivan", asset_id="pg").content == first.content
        copy(c, "judy", asset_id="pg")
        assert trace(c, first.content, asset_id="pg")["accused"] == ["ivan"]
        reg = Registry(url)
        assert reg.count() == 2
        reg.close()
