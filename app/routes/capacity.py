"""``POST /v1/capacity``: how much a mesh can carry, without embedding."""

from __future__ import annotations

from fastapi import APIRouter, Response

from app.deps import PoolDep
from app.forms import CapacityForm, PooledFormRoute
from app.problems import problem_responses
from app.routes.common import MESH_PROBLEMS, as_response
from core.api import CapacityReport

router = APIRouter(route_class=PooledFormRoute, tags=["watermark"])


@router.post("/v1/capacity", summary="Measure watermark capacity", response_model=CapacityReport,
             responses=problem_responses(*MESH_PROBLEMS))
async def capacity(task: CapacityForm, pool: PoolDep) -> Response:
    """Carriers, the largest payload that fits once, and the expected distortion at `strength`."""
    report: CapacityReport = await pool.run(task)
    return as_response(task.render(report))
