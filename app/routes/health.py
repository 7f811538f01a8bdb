"""Liveness, readiness and metrics: open even when API keys are required."""

from __future__ import annotations

from fastapi import APIRouter, Request, Response
from prometheus_client import CONTENT_TYPE_LATEST

from app.problems import NOT_READY, ProblemError, problem_responses
from app.workers.pool import WorkerPool

router = APIRouter(tags=["health"])


@router.get("/healthz", summary="Liveness")
async def healthz() -> dict[str, str]:
    """200 while the process serves requests (it does not look at the workers)."""
    return {"status": "ok"}


@router.get("/readyz", summary="Readiness", responses=problem_responses(NOT_READY))
async def readyz(request: Request) -> dict[str, int | str]:
    """200 when at least one worker process is alive (and, with the Redis jobs backend, Redis
    answers); 503 `not-ready` otherwise."""
    pool: WorkerPool | None = getattr(request.app.state, "pool", None)
    live = pool.live_workers() if pool is not None else []
    if pool is None or not live:
        raise ProblemError(NOT_READY, "no live worker process", headers={"Retry-After": "1"})
    runner = getattr(request.app.state, "runner", None)
    jobs = await runner.ready() if runner is not None else {}
    return {"status": "ready", "workers": len(live), "queued": pool.pending - pool.running,
            "running": pool.running, **jobs}


@router.get("/metrics", summary="Prometheus metrics", response_class=Response,
            responses={200: {"content": {CONTENT_TYPE_LATEST: {"schema": {"type": "string"}}}}})
async def metrics(request: Request) -> Response:
    """Prometheus text exposition: requests, the worker pool, jobs, ``process_*`` and build info."""
    state = request.app.state
    runner = getattr(state, "runner", None)
    try:
        jobs = await runner.store.count() if runner is not None else {}
    except ProblemError:  # the job store is unreachable: the other figures still count
        jobs = {}
    result_bytes = getattr(runner.store, "result_bytes", None) if runner is not None else None
    return Response(state.metrics.render(getattr(state, "pool", None), jobs, result_bytes),
                    media_type=CONTENT_TYPE_LATEST)
