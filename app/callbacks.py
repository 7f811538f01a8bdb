"""Job callbacks: the final status of a job POSTed to the URL its creator gave, signed.

* **Signed**: ``X-MeshMark-Signature: sha256=<hex>``, the HMAC-SHA256 of the exact body under the
  server's ``callback_secret`` (GitHub's webhook convention); a receiver recomputes it over the raw
  body before trusting it (:func:`meshmark.client.verify_signature`).  The body is the job status
  of ``GET /v1/jobs/{id}``; ``X-MeshMark-Job`` and ``X-Request-ID`` repeat its id and request id.
* **Retried**: a network failure, a timeout, 408, 429 or a 5xx is tried again after
  :data:`BACKOFF_SECONDS` (1, 2, 4, 8 s: five attempts in about 15 s); any other answer ends it (a
  receiver that answers 4xx has refused the delivery).  Redirects are not followed.
* **No path to SSRF**: a URL is taken only when its host is one of ``callback_hosts`` (default:
  none, so callbacks are off until an operator names the receivers), checked when the job is
  created; the scheme must be http or https, and user information in the URL is refused.
"""

from __future__ import annotations

import asyncio
import hashlib
import hmac
import logging
from urllib.parse import urlsplit

import httpx

from app.jobs.status import JobStatus
from app.jobs.store import Job

log = logging.getLogger("meshmark.callbacks")

SIGNATURE_HEADER = "X-MeshMark-Signature"
#: waits before the 2nd, 3rd... attempt
BACKOFF_SECONDS = (1.0, 2.0, 4.0, 8.0)
#: seconds for one attempt (connect + send + answer)
ATTEMPT_TIMEOUT = 10.0
#: answers worth another attempt
RETRY_STATUSES = frozenset({408, 425, 429, 500, 502, 503, 504})


class CallbackRefused(ValueError):
    """A callback URL that may not be used; the message is for the caller."""


def check_url(url: str, allowed_hosts: list[str]) -> str:
    """``url`` when it may receive callbacks: http(s), no user information, and a host (with its
    port, when the entry names one) among ``allowed_hosts``."""
    if not allowed_hosts:
        raise CallbackRefused("callbacks are off on this server (no host is allowed: "
                              "MESHMARK_CALLBACK_HOSTS)")
    try:
        parts = urlsplit(url)
        port = parts.port
    except ValueError:
        raise CallbackRefused("callback_url is not a valid URL") from None
    if parts.scheme not in ("http", "https") or not parts.hostname:
        raise CallbackRefused("callback_url must be an http:// or https:// URL with a host")
    if parts.username is not None or parts.password is not None:
        raise CallbackRefused("callback_url must not contain user information")
    host = parts.hostname.lower()
    if host not in allowed_hosts and f"{host}:{port}" not in allowed_hosts:
        raise CallbackRefused(f"callback host '{host}' is not among the hosts this server may call "
                              "(MESHMARK_CALLBACK_HOSTS)")
    return url


def signature(secret: bytes, body: bytes) -> str:
    return "sha256=" + hmac.new(secret, body, hashlib.sha256).hexdigest()


def request(job: Job, secret: bytes) -> tuple[bytes, dict[str, str]]:
    """The body and headers of the callback of a finished ``job``."""
    body = JobStatus.of(job).body()
    headers = {"Content-Type": "application/json", SIGNATURE_HEADER: signature(secret, body),
               "X-MeshMark-Job": job.id, "User-Agent": "meshmark-callback"}
    if job.request_id:
        headers["X-Request-ID"] = job.request_id
    return body, headers


def _judge(url: str, response: httpx.Response | None, error: Exception | None = None) -> bool | None:
    """True delivered, None worth another attempt, False refused for good."""
    if response is None:
        log.warning("callback to %s failed: %s", url, type(error).__name__)
        return None
    if response.is_success:
        return True
    log.warning("callback to %s answered %d", url, response.status_code)
    return None if response.status_code in RETRY_STATUSES else False


def attempt(client: httpx.Client, url: str, body: bytes, headers: dict[str, str]) -> bool | None:
    """One delivery (the Celery workers' side): see :func:`_judge`."""
    try:
        return _judge(url, client.post(url, content=body, headers=headers, timeout=ATTEMPT_TIMEOUT))
    except httpx.HTTPError as exc:
        return _judge(url, None, exc)


async def _attempt_async(client: httpx.AsyncClient, url: str, body: bytes,
                         headers: dict[str, str]) -> bool | None:
    try:
        return _judge(url, await client.post(url, content=body, headers=headers, timeout=ATTEMPT_TIMEOUT))
    except httpx.HTTPError as exc:
        return _judge(url, None, exc)


async def deliver(job: Job, secret: bytes) -> bool:
    """Deliver the callback of a finished ``job`` with retries (the in-process jobs backend)."""
    assert job.callback_url is not None
    body, headers = request(job, secret)
    async with httpx.AsyncClient(follow_redirects=False) as client:
        for wait in (0.0, *BACKOFF_SECONDS):
            await asyncio.sleep(wait)
            outcome = await _attempt_async(client, job.callback_url, body, headers)
            if outcome is not None:
                log.info("job %s callback %s", job.id, "delivered" if outcome else "refused by the receiver")
                return outcome
    log.error("job %s callback not delivered after %d attempts", job.id, len(BACKOFF_SECONDS) + 1)
    return False
