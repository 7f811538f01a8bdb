"""``POST /v1/preview``: a mesh's geometry for a viewer, read by the engine's own readers, with the
displacement from an original as a heat map (what the web page at ``/`` draws)."""

from __future__ import annotations

from fastapi import APIRouter, Response

from app.deps import PoolDep
from app.forms import PreviewForm, PreviewFormRoute
from app.preview import PREVIEW_DESCRIPTION, PREVIEW_MEDIA_TYPE
from app.problems import problem_responses
from app.routes.common import MESH_PROBLEMS, as_response
from core.preview import PreviewGeometry

router = APIRouter(route_class=PreviewFormRoute, tags=["preview"])


@router.post(
    "/v1/preview", summary="Geometry for a 3-D preview", response_class=Response,
    responses={200: {"description": PREVIEW_DESCRIPTION,
                     "content": {PREVIEW_MEDIA_TYPE: {"schema": {"type": "string", "format": "binary"}}}},
               **problem_responses(*MESH_PROBLEMS)},
)
async def preview(task: PreviewForm, pool: PoolDep) -> Response:
    """Positions and triangles of every mesh part, as the engine reads them (same formats and
    limits as `/v1/embed`), in a compact binary form; with `original`, the per-vertex displacement
    relative to the bounding-box diagonal. Both files together must fit the request-body limit."""
    geometry: PreviewGeometry = await pool.run(task)
    return as_response(task.render(geometry))
