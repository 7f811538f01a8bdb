"""``POST /v1/embed``: watermark a mesh and send it back in the format it came in."""

from __future__ import annotations

import logging

from fastapi import APIRouter, Request, Response

from app.deps import PoolDep
from app.forms import EmbedForm, PooledFormRoute
from app.logs import log_task
from app.problems import (
    BAD_FORM,
    BUSY,
    DEGENERATE_MESH,
    MALFORMED_MESH,
    TIMED_OUT,
    TOO_LARGE,
    TOO_LITTLE_CAPACITY,
    UNAUTHORIZED,
    UNSUPPORTED_FORMAT,
    WORKER_FAILED,
    problem_responses,
)
from app.results import as_response, embed_openapi_response, embedded_result

log = logging.getLogger("meshmark.app")

router = APIRouter(route_class=PooledFormRoute, tags=["watermark"])

#: problems of every route that runs the engine on an uploaded mesh
MESH_PROBLEMS = (BAD_FORM, UNSUPPORTED_FORMAT, MALFORMED_MESH, DEGENERATE_MESH, TOO_LARGE, BUSY,
                 TIMED_OUT, WORKER_FAILED, UNAUTHORIZED)


@router.post(
    "/v1/embed",
    summary="Watermark a mesh",
    response_class=Response,
    responses={**embed_openapi_response(), **problem_responses(*MESH_PROBLEMS, TOO_LITTLE_CAPACITY)},
)
async def embed(task: EmbedForm, pool: PoolDep, request: Request) -> Response:
    """Hide the key's watermark (or `payload`) in the mesh geometry. Only the coordinates of
    moved vertices change in the returned file; the report is in the `X-MeshMark-*` headers."""
    embedded = await pool.run(task)
    log_task(request, task, carriers=embedded.report.carriers, format=embedded.format)
    return as_response(embedded_result(embedded, task.filename))
