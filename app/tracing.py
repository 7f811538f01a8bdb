"""Leak tracing for the service and the command line: issue a fingerprinted copy, trace a leak.

Each step runs where it must: the registry is read and written in the process that answers (the
API process, the Celery worker that renders a job, the command line), the engine runs in a
worker with plain bytes and numbers.

* Issue (``POST /v1/copies``): :func:`plan_copy` finds the recipient's copy of the asset (the same
  codeword again: idempotent) or draws a fresh one (the asset's codeword length once it has
  copies, else the engine picks it from the mesh's carriers, from a seed drawn here);
  :func:`run_copy` embeds it; :func:`record_copy` writes it to the registry.  Two requests
  for a new recipient at once: the first written wins, the other is ``copy-conflict`` (409) and
  a retry gets the winner's codeword.
* Trace (``POST /v1/trace``): :func:`plan_trace` lists the (method, length) groups of the asset's
  copies (every asset's without an asset id), :func:`run_trace` reads the suspect's votes for
  each, :func:`rank_copies` scores every registered codeword and ranks the recipients.
"""

from __future__ import annotations

import datetime as dt
import hashlib
import secrets
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import numpy as np

from app.config import Settings
from app.problems import COPY_CONFLICT, NO_COPIES, ProblemError
from app.registry import Copy, Registry, sqlite_url
from core.fingerprint import (
    VARIANTS,
    Fingerprinted,
    correlation_scores,
    embed_codeword,
    false_accusation,
    pack_codeword,
    random_codeword,
    read_votes,
    score_threshold,
    unpack_codeword,
)
from core.formats import DEFAULT_LIMITS, Limits
from core.options import Options
from core.reports import Progress

#: false-accusation probability at which a recipient is accused, unless the caller says otherwise
DEFAULT_THRESHOLD = 1e-9
#: recipients listed in a trace answer, unless the caller says otherwise
DEFAULT_TOP = 10
MAX_TOP = 1000
ASSET_ID_PATTERN = r"^[A-Za-z0-9._:-]{1,200}$"
RECIPIENT_PATTERN = r"^[^\u0000-\u001f\u007f]{1,500}$"


def asset_id_of(data: bytes) -> str:
    """The default asset id: a content hash of the cover file."""
    return "sha256:" + hashlib.sha256(data).hexdigest()


def registry_url(settings: Settings) -> str:
    url = settings.registry_url
    return url.get_secret_value() if url is not None else sqlite_url(settings.registry_path)


_lock = threading.Lock()
_url: str | None = None
_registry: Registry | None = None


@contextmanager
def open_registry(settings: Settings) -> Iterator[Registry]:
    """``settings``' registry, migrated, closed on exit (the command line)."""
    registry = Registry(registry_url(settings))
    try:
        registry.migrate()
        yield registry
    finally:
        registry.close()


def configure_registry(settings: Settings) -> None:
    """Make ``settings``' registry this process's (opened, and migrated, at its first use)."""
    global _url
    close_registry()
    _url = registry_url(settings)


def close_registry() -> None:
    global _registry
    with _lock:
        if _registry is not None:
            _registry.close()
        _registry = None


def current_registry() -> Registry:
    """This process's registry: the service's (:func:`configure_registry`), else that of the
    ``MESHMARK_*`` settings (a Celery worker rendering a copy job, the command line)."""
    global _registry
    with _lock:
        if _registry is None:
            registry = Registry(_url or registry_url(Settings()))
            registry.migrate()
            _registry = registry
        return _registry


@dataclass(frozen=True)
class CopyPlan:
    """What a copy task needs besides the mesh and the options."""

    asset_id: str
    recipient: str
    codeword: bytes | None = None   # packed bits of an existing or freshly drawn codeword
    codeword_bits: int | None = None
    seed: int | None = None         # the engine draws the codeword (first copy of an asset)


@dataclass(frozen=True)
class TracePlan:
    asset_id: str | None
    groups: tuple[tuple[str, int], ...]  # (method, codeword length) of the registered copies
    threshold: float = DEFAULT_THRESHOLD
    top: int = DEFAULT_TOP


def plan_copy(registry: Registry, data: bytes, options: Options, recipient: str,
              asset_id: str | None) -> CopyPlan:
    """The codeword of ``recipient``'s copy: the one issued before, or a fresh one."""
    asset = asset_id or asset_id_of(data)
    existing = registry.find(asset, recipient)
    if existing is not None:
        if existing.method != options.embed_method or existing.strength != options.margin:
            raise ProblemError(COPY_CONFLICT, f"this recipient's copy of the asset was issued with method "
                               f"{existing.method} and strength {existing.strength:g}: ask again with those "
                               "", method=existing.method,
                               strength=existing.strength)
        return CopyPlan(asset, recipient, existing.codeword, existing.codeword_bits)
    length = registry.asset_length(asset)
    rng = np.random.default_rng(secrets.randbits(128))
    if length is None:
        return CopyPlan(asset, recipient, seed=secrets.randbits(128))
    return CopyPlan(asset, recipient, pack_codeword(random_codeword(rng, length)), length)


def run_copy(plan: CopyPlan, data: bytes, options: Options, *, filename: str | None = None,
             limits: Limits = DEFAULT_LIMITS, progress: Progress | None = None) -> Fingerprinted:
    """The engine's part of a copy (in a worker)."""
    codeword = None
    if plan.codeword is not None and plan.codeword_bits is not None:
        codeword = unpack_codeword(plan.codeword, plan.codeword_bits)
    rng = np.random.default_rng(plan.seed) if plan.seed is not None else None
    return embed_codeword(data, options, codeword=codeword, rng=rng, filename=filename, limits=limits,
                          progress=progress)


def record_copy(registry: Registry, plan: CopyPlan, options: Options, value: Fingerprinted) -> Copy:
    """Write the copy to the registry; ``copy-conflict`` when another one won the race."""
    packed = pack_codeword(value.codeword)
    copy = Copy(plan.asset_id, plan.recipient, packed, len(value.codeword), options.embed_method,
                options.margin, dt.datetime.now(dt.UTC))
    stored = registry.issue(copy)
    if stored.codeword != packed:
        raise ProblemError(COPY_CONFLICT, "another copy for this recipient was issued at the same time: "
                           "send the request again to get that one")
    return stored


def plan_trace(registry: Registry, asset_id: str | None, threshold: float = DEFAULT_THRESHOLD,
               top: int = DEFAULT_TOP) -> TracePlan:
    groups = tuple((method, length) for method, length, _ in registry.groups(asset_id))
    if not groups:
        where = f"asset {asset_id}" if asset_id else "any asset"
        raise ProblemError(NO_COPIES, f"no copies are registered for {where}: nobody to trace")
    return TracePlan(asset_id, groups, threshold, top)


def run_trace(plan: TracePlan, data: bytes, key: str | bytes, *, filename: str | None = None,
              limits: Limits = DEFAULT_LIMITS, progress: Progress | None = None
              ) -> dict[tuple[str, int], np.ndarray]:
    """The suspect's votes for every group (in a worker)."""
    return read_votes(data, Options(key=key), list(plan.groups), filename=filename, limits=limits,
                      progress=progress)


def rank_copies(registry: Registry, plan: TracePlan, votes: dict[tuple[str, int], np.ndarray]
                ) -> dict[str, Any]:
    """Every registered codeword of the plan scored; the answer of ``POST /v1/trace``."""
    scores, owners = [], []
    for method, length in plan.groups:
        group = registry.codewords(plan.asset_id, method, length)
        scores.append(correlation_scores(votes[(method, length)], group.packed, length))
        owners += [(a, r, method, length) for a, r in zip(group.asset_ids, group.recipients, strict=True)]
    s = np.concatenate(scores) if scores else np.zeros(0)
    tests = len(VARIANTS) * max(len(s), 1)
    fap = false_accusation(s, tests)
    order = np.argsort(-s, kind="stable")
    ranked = [{"recipient": owners[i][1], "asset_id": owners[i][0], "method": owners[i][2],
               "codeword_bits": owners[i][3], "score": round(float(s[i]), 4),
               "false_accusation_probability": float(fap[i]), "accused": bool(fap[i] <= plan.threshold)}
              for i in order[:plan.top]]
    accused = [r["recipient"] for r in ranked if r["accused"]]
    accused += [owners[i][1] for i in order[plan.top:] if fap[i] <= plan.threshold]
    return {"asset_id": plan.asset_id, "copies_scored": len(s), "threshold": plan.threshold,
            "score_threshold": round(score_threshold(plan.threshold, tests), 4),
            "verdict": "accused" if accused else "no-one", "accused": accused, "ranked": ranked}
