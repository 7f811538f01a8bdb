"""``/v1/jobs``: the same work as ``/v1/embed`` and ``/v1/detect``, in the background.

A job is ``queued``, then ``running`` (with ``progress`` relayed from the worker), then
``succeeded``, ``failed`` (with the problem it would have answered) or ``cancelled``.  Finished
jobs and their results are kept for ``job_result_ttl_seconds``, then forgotten (404).
"""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Request, Response
from fastapi.responses import JSONResponse

from app.deps import Caller, RunnerDep, StoreDep
from app.forms import CallbackUrl, CopyForm, DetectForm, EmbedForm, StrictFormRoute
from app.jobs import Job, JobStatus, JobStore
from app.logs import log_task
from app.problems import (
    CALLBACK_NOT_ALLOWED,
    COPY_CONFLICT,
    JOB_FAILED,
    JOB_NOT_READY,
    NOT_FOUND,
    NOT_READY,
    TOO_LITTLE_CAPACITY,
    UNAUTHORIZED,
    ProblemError,
    problem_responses,
)
from app.routes.common import MESH_PROBLEMS, as_response, embed_openapi_response

router = APIRouter(route_class=StrictFormRoute, tags=["jobs"])


def _accepted(job: Job, request: Request) -> JSONResponse:
    location = str(request.url_for("get_job", job_id=job.id).path)
    return JSONResponse(JobStatus.of(job).model_dump(mode="json"), status_code=202,
                        headers={"Location": location})


async def _job(store: JobStore, job_id: str, caller: str | None) -> Job:
    """The job, when ``caller`` created it: another caller's job is answered like an unknown one."""
    job = await store.get(job_id)
    if job is None or job.owner != caller:
        raise ProblemError(NOT_FOUND, "no such job (unknown, deleted or expired)")
    return job


_CREATE: dict[int | str, dict[str, Any]] = {202: {
    "model": JobStatus, "description": "Accepted; poll the `Location`.",
    "headers": {"Location": {"schema": {"type": "string"}, "description": "/v1/jobs/{id}"}},
}}
_KNOWN: dict[int | str, dict[str, Any]] = problem_responses(NOT_FOUND, UNAUTHORIZED, NOT_READY)


@router.post("/v1/jobs/embed", summary="Start an embedding job", status_code=202, response_model=JobStatus,
             responses={**_CREATE, **problem_responses(*MESH_PROBLEMS, TOO_LITTLE_CAPACITY, NOT_READY,
                                                       CALLBACK_NOT_ALLOWED)})
async def create_embed_job(task: EmbedForm, callback_url: CallbackUrl, runner: RunnerDep, caller: Caller,
                           request: Request) -> JSONResponse:
    """Validate the form now, run the embedding in the background; the result has the same body
    and headers as `POST /v1/embed`.  With `callback_url`, the final status is also POSTed there."""
    job = await runner.submit(task, callback_url, caller)
    log_task(request, task, job=job.id)
    return _accepted(job, request)


@router.post("/v1/jobs/detect", summary="Start a detection job", status_code=202, response_model=JobStatus,
             responses={**_CREATE, **problem_responses(*MESH_PROBLEMS, NOT_READY, CALLBACK_NOT_ALLOWED)})
async def create_detect_job(task: DetectForm, callback_url: CallbackUrl, runner: RunnerDep, caller: Caller,
                            request: Request) -> JSONResponse:
    """Run a detection in the background; the result is the JSON of `POST /v1/detect`.  With
    `callback_url`, the final status is also POSTed there."""
    job = await runner.submit(task, callback_url, caller)
    log_task(request, task, job=job.id)
    return _accepted(job, request)


@router.post("/v1/jobs/copies", summary="Start a copy job", status_code=202, response_model=JobStatus,
             responses={**_CREATE, **problem_responses(*MESH_PROBLEMS, TOO_LITTLE_CAPACITY, COPY_CONFLICT,
                                                       NOT_READY, CALLBACK_NOT_ALLOWED)})
async def create_copy_job(task: CopyForm, callback_url: CallbackUrl, runner: RunnerDep, caller: Caller,
                          request: Request) -> JSONResponse:
    """`POST /v1/copies` in the background, for large files: the result has the same body and
    headers; the copy is in the registry once the job has succeeded."""
    job = await runner.submit(task, callback_url, caller)
    log_task(request, task, job=job.id)
    return _accepted(job, request)


@router.get("/v1/jobs/{job_id}", summary="Job status", response_model=JobStatus, responses=_KNOWN)
async def get_job(job_id: str, store: StoreDep, caller: Caller) -> JobStatus:
    return JobStatus.of(await _job(store, job_id, caller))


@router.get(
    "/v1/jobs/{job_id}/result", summary="Job result", response_class=Response,
    responses={**embed_openapi_response(
        "Embed jobs: the watermarked mesh with the `X-MeshMark-*` headers of `POST /v1/embed`. "
        "Detect jobs: the JSON of `POST /v1/detect`.",
        {"application/json": {"schema": {"$ref": "#/components/schemas/DetectResult"}}}),
        **problem_responses(NOT_FOUND, JOB_NOT_READY, JOB_FAILED, UNAUTHORIZED, NOT_READY)},
)
async def get_job_result(job_id: str, store: StoreDep, caller: Caller) -> Response:
    """409 `job-not-ready` (with `Retry-After`) until the job finishes; 409 `job-failed` (with the
    job's problem as `error`) when it failed or was cancelled."""
    job = await _job(store, job_id, caller)
    if job.state in ("queued", "running"):
        raise ProblemError(JOB_NOT_READY, f"the job is {job.state}", headers={"Retry-After": "1"},
                           state=job.state, progress=job.progress)
    result = await store.result(job)
    if result is None and job.state == "succeeded":  # deleted or expired since the line above
        raise ProblemError(NOT_FOUND, "no such job (unknown, deleted or expired)")
    if result is None:
        detail = "the job failed (see error)" if job.state == "failed" else "the job was cancelled"
        raise ProblemError(JOB_FAILED, detail, state=job.state, error=job.error)
    return as_response(result)


@router.delete(
    "/v1/jobs/{job_id}", summary="Cancel or delete a job", response_model=JobStatus,
    responses={200: {"description": "The job was queued or running: it is now `cancelled` (kept until it "
                                    "expires)."},
               204: {"description": "The job had finished: it and its result are deleted."}, **_KNOWN},
)
async def delete_job(job_id: str, runner: RunnerDep, store: StoreDep, caller: Caller) -> Any:
    job = await _job(store, job_id, caller)
    if job.done:
        await store.delete(job_id)
        return Response(status_code=204)
    cancelled = await runner.cancel(job_id)
    return JobStatus.of(cancelled or job)

