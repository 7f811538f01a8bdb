"""``POST /v1/detect``: blind detection from the mesh and the key alone."""

from __future__ import annotations

from fastapi import APIRouter, Request, Response

from app.deps import PoolDep
from app.forms import DetectForm, PooledFormRoute
from app.logs import log_task
from app.problems import problem_responses
from app.routes.common import MESH_PROBLEMS, as_response
from core.api import DetectResult

router = APIRouter(route_class=PooledFormRoute, tags=["watermark"])


@router.post("/v1/detect", summary="Detect a watermark", response_model=DetectResult,
             responses=problem_responses(*MESH_PROBLEMS))
async def detect(task: DetectForm, pool: PoolDep, request: Request) -> Response:
    """Look for the key's watermark. "Not found" is a 200 answer with `detected: false`;
    `false_positive_probability` says how likely a mesh without this watermark would score as high."""
    result: DetectResult = await pool.run(task)
    log_task(request, task, detected=result.detected, method=result.method)
    return as_response(task.render(result))
