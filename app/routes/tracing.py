"""``POST /v1/copies`` and ``POST /v1/trace``: one fingerprinted copy per recipient, and who leaked one."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Request, Response
from pydantic import BaseModel, Field
from starlette.concurrency import run_in_threadpool

from app.deps import PoolDep
from app.forms import CopyForm, PooledFormRoute, TraceForm
from app.logs import log_task
from app.problems import COPY_CONFLICT, NO_COPIES, TOO_LITTLE_CAPACITY, problem_responses
from app.results import COPY_HEADERS
from app.routes.common import MESH_PROBLEMS, as_response, embed_openapi_response

router = APIRouter(route_class=PooledFormRoute, tags=["tracing"])


class RankedCopy(BaseModel):
    recipient: str
    asset_id: str
    method: str
    codeword_bits: int
    score: float = Field(description="Normalised correlation of the recipient's codeword with the suspect's "
                         "votes; an innocent's is above t with probability at most exp(-t^2/2).")
    false_accusation_probability: float = Field(description="Probability that some innocent among all "
                                                "copies scored scores this high (union bound).")
    accused: bool


class TraceResult(BaseModel):
    asset_id: str | None
    copies_scored: int
    threshold: float
    score_threshold: float = Field(description="The score at which the false-accusation probability "
                                   "reaches the threshold.")
    verdict: str = Field(description="`accused` or `no-one`.")
    accused: list[str]
    ranked: list[RankedCopy]


def _copy_responses() -> dict[int | str, dict[str, Any]]:
    out = embed_openapi_response("The recipient's marked copy, in the format it was uploaded in, with the "
                                 "headers of `POST /v1/embed` and these.")
    out[200]["headers"].update({name: {"schema": {"type": "string"}, "description": text}
                                for name, text in COPY_HEADERS.items()})
    return out


@router.post("/v1/copies", summary="Issue a fingerprinted copy", response_class=Response,
             responses={**_copy_responses(), **problem_responses(*MESH_PROBLEMS, TOO_LITTLE_CAPACITY,
                                                                 COPY_CONFLICT)})
async def issue_copy(task: CopyForm, pool: PoolDep, request: Request) -> Response:
    """Mark the mesh with a codeword of the recipient's own and record it in the registry (never
    the key). Asking again for the same asset and recipient gives the same codeword (409
    `copy-conflict` if the method or strength differ from the first copy's)."""
    value = await pool.run(task)
    rendered = await run_in_threadpool(task.render, value)
    log_task(request, task, carriers=value.file.report.carriers, format=value.file.format)
    return as_response(rendered)


@router.post("/v1/trace", summary="Trace a leaked copy", response_model=TraceResult,
             responses=problem_responses(*MESH_PROBLEMS, NO_COPIES))
async def trace(task: TraceForm, pool: PoolDep, request: Request) -> Response:
    """Score every registered copy of the asset (of every asset without `asset_id`) against the
    suspect mesh and rank the recipients. A recipient is accused when the probability that an
    innocent scores as high, over all the copies scored, is at most `threshold`."""
    votes = await pool.run(task)
    rendered = await run_in_threadpool(task.render, votes)
    log_task(request, task)
    return as_response(rendered)
