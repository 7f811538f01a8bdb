"""``POST /v1/embed``: watermark a mesh and send it back in the format it came in."""

from __future__ import annotations

from fastapi import APIRouter, Request, Response

from app.deps import PoolDep
from app.forms import EmbedForm, PooledFormRoute
from app.logs import log_task
from app.problems import TOO_LITTLE_CAPACITY, problem_responses
from app.routes.common import MESH_PROBLEMS, as_response, embed_openapi_response

router = APIRouter(route_class=PooledFormRoute, tags=["watermark"])


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
    return as_response(task.render(embedded))
