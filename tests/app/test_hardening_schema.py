"""A short schemathesis run against the committed ``openapi/openapi.json``, through the ASGI app
with real workers: no 5xx, and every answer (status, content type, headers, body) as the document
says.  The checks and their two multipart adaptations are in :mod:`tests.app.oracles`;
``bench/schemathesis_run.py`` is the long run (``bench/results/hardening.md``); set
``MESHMARK_SCHEMATHESIS_EXAMPLES`` for a longer run here."""

from __future__ import annotations

import json
import os
from typing import Any

import pytest
from hypothesis import HealthCheck, settings
from schemathesis.python import asgi

from app.config import Settings
from app.main import create_app
from app.openapi import OPENAPI_PATH
from tests.app.conftest import make_client
from tests.app.oracles import call_and_check, load_schema

EXAMPLES = int(os.environ.get("MESHMARK_SCHEMATHESIS_EXAMPLES", "20"))

# the time limit catches a hang, not a slow machine: the workers run niced (app.workers.process.NICENESS),
# so beside the other xdist worker a capacity of the test sphere (3.4-4.9 s alone) passed 30 s in a
# CI run (503 timed-out); it stays under the client's 120 s
app = create_app(Settings(workers=2, job_timeout_seconds=100))
schema = load_schema()


@pytest.fixture(scope="module", autouse=True)
def _stop_the_app():
    yield
    asgi.shutdown_lifespans()  # schemathesis keeps the lifespan (and the worker pool) running


@schema.parametrize()
@settings(max_examples=EXAMPLES, derandomize=True, deadline=None, suppress_health_check=list(HealthCheck))
def test_api_conforms_to_its_document(case: Any) -> None:
    call_and_check(case, app)


def _ball(ext: str) -> bytes:
    import trimesh

    from tests.app.hostile import icosphere
    from tests.core.formats.helpers import gltf_document, to_gltf

    if ext == "gltf":
        return to_gltf(*gltf_document(*icosphere(5)))
    data = trimesh.creation.icosphere(subdivisions=5).export(file_type=ext)
    return data.encode() if isinstance(data, str) else data


@pytest.mark.parametrize("ext", ["obj", "ply", "stl", "off", "glb", "gltf"])
def test_the_answer_of_every_format_is_documented(ext):
    """The 200 of /v1/embed has a documented Content-Type whatever the format (schemathesis only
    sends OBJ)."""
    paths = json.loads(OPENAPI_PATH.read_text())["paths"]
    with make_client(workers=1) as client:
        response = client.post("/v1/embed", files={"mesh": (f"ball.{ext}", _ball(ext))},
                               data={"key": "a key"})
    assert response.status_code == 200, response.text
    for operation in (paths["/v1/embed"]["post"], paths["/v1/jobs/{job_id}/result"]["get"]):
        assert response.headers["content-type"] in operation["responses"]["200"]["content"]
