"""A client of the MeshMark HTTP API for programs that mark or check models: a content-management
system, a batch script, ``meshmark --server``.  It needs only httpx: the engine is on the server.

It does what a careful integrator would do by hand:

* long work goes through the jobs API (``POST /v1/jobs/...``), followed to the end with a
  progress callback, then fetched and deleted, so no HTTP request stays open for minutes;
* ``429 busy`` and ``503`` answers (and connections that break mid-request) are retried, waiting
  what ``Retry-After`` says, at most ``retries`` times and never longer than ``max_wait`` each; a
  server that cannot be connected to fails at once;
* a watermarked mesh is streamed to disk and renamed into place when complete, never held whole
  in memory and never left half-written under its final name;
* a refusal raises :class:`ProblemError` carrying the RFC 9457 problem (``title``, ``detail``,
  ``type``...) and the request id to quote to the operator.

::

    from meshmark.client import Client

    with Client("http://127.0.0.1:8000") as mm:
        report = mm.embed("spot.obj", "spot.marked.obj", key="my secret key")
        found = mm.detect("spot.marked.obj", key="my secret key")

:class:`AsyncClient` has the same methods as coroutines.
"""

from __future__ import annotations

import asyncio
import email.utils
import hashlib
import hmac
import json
import os
import tempfile
import time
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any, BinaryIO

import httpx

#: called with the fraction of a job done, from 0 to 1
Progress = Callable[[float], None]
#: a mesh to upload: a path, or the file's bytes (then give ``filename``)
MeshSource = str | os.PathLike[str] | bytes
#: where a marked mesh goes: a path, or a binary file object (``sys.stdout.buffer``)
MeshTarget = str | os.PathLike[str] | BinaryIO

#: statuses worth another try: busy (429), not ready / worker failed / timed out (503)
RETRY_STATUSES = frozenset({429, 503})
SIGNATURE_HEADER = "X-MeshMark-Signature"


@dataclass
class ProblemError(Exception):
    """The service refused the request: the RFC 9457 problem it answered."""

    status: int
    title: str
    detail: str
    type: str = "about:blank"
    request_id: str | None = None
    problem: dict[str, Any] = field(default_factory=dict)

    def __str__(self) -> str:
        where = f" (request {self.request_id})" if self.request_id else ""
        return f"{self.title}: {self.detail}{where}"

    @classmethod
    def from_response(cls, response: httpx.Response) -> ProblemError:
        request_id = response.headers.get("x-request-id")
        try:
            body = response.json()
        except (ValueError, UnicodeDecodeError):
            body = None
        if isinstance(body, dict) and "title" in body:
            return cls.from_problem(body, request_id)
        text = response.text.strip()[:500] if response.content else ""
        return cls(response.status_code, response.reason_phrase or "HTTP error", text or "(no detail)",
                   request_id=request_id)

    @classmethod
    def from_problem(cls, body: dict[str, Any], request_id: str | None = None) -> ProblemError:
        return cls(int(body.get("status", 0)), str(body.get("title", "")), str(body.get("detail", "")),
                   str(body.get("type", "about:blank")), request_id, body)


def verify_signature(secret: str | bytes, body: bytes, header: str | None) -> bool:
    """Whether a job callback's ``X-MeshMark-Signature`` header (``sha256=<hex>``) is the
    HMAC-SHA256 of its raw body under the server's ``callback_secret``.  Check it before trusting
    the body."""
    if not header or not header.startswith("sha256="):
        return False
    key = secret.encode() if isinstance(secret, str) else secret
    expected = hmac.new(key, body, hashlib.sha256).hexdigest()
    return hmac.compare_digest(expected, header.removeprefix("sha256="))


# -- what both clients share ----------------------------------------------------------------------

def _retry_delay(response: httpx.Response | None, attempt: int, max_wait: float) -> float:
    """``Retry-After`` (seconds or an HTTP date) when the server gave one, else exponential."""
    value = response.headers.get("retry-after") if response is not None else None
    delay: float | None = None
    if value:
        if value.strip().isdigit():
            delay = float(value)
        else:
            when = email.utils.parsedate_to_datetime(value)
            delay = when.timestamp() - time.time() if when is not None else None
    if delay is None:
        delay = 0.5 * 2**attempt
    return min(max(delay, 0.0), max_wait)


@contextmanager
def _mesh_file(mesh: MeshSource, filename: str | None) -> Iterator[tuple[str, IO[bytes] | bytes]]:
    """``(file name, content)`` of an upload; a path is opened here (httpx streams it)."""
    if isinstance(mesh, bytes):
        yield filename or "mesh", mesh
        return
    path = Path(mesh)
    with path.open("rb") as f:
        yield filename or path.name, f


def _fields(**values: Any) -> dict[str, str]:
    return {k: str(v) for k, v in values.items() if v is not None}


def _report(response: httpx.Response) -> dict[str, Any]:
    report: dict[str, Any] = json.loads(response.headers["x-meshmark-report"])
    return report


@contextmanager
def _target(output: MeshTarget) -> Iterator[BinaryIO]:
    """A file to stream a mesh into: a temporary file beside ``output``, renamed over it only once
    complete (removed on failure), or ``output`` itself when it is a file object."""
    if not isinstance(output, str | os.PathLike):
        yield output
        return
    path = Path(output)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".part", dir=path.parent or ".")
    try:
        with os.fdopen(fd, "wb") as f:
            yield f
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


class _Base:
    def __init__(self, base_url: str, *, api_key: str | None, retries: int, max_wait: float,
                 poll_interval: float, timeout: float) -> None:
        self.retries, self.max_wait, self.poll_interval = retries, max_wait, poll_interval
        headers = {"User-Agent": "meshmark-client"}
        if api_key:
            headers["Authorization"] = f"Bearer {api_key}"
        self._options: dict[str, Any] = {"base_url": base_url.rstrip("/"), "headers": headers,
                                         "timeout": httpx.Timeout(timeout, connect=10.0)}

    def _broken(self, exc: httpx.TransportError, attempt: int) -> None:
        """A connection that broke mid-way (a restart, a proxy) may be tried again; one that could
        not be made is raised at once (nothing listens there: waiting would not help)."""
        if isinstance(exc, httpx.ConnectError | httpx.ConnectTimeout) or attempt == self.retries:
            raise exc

    def _retry_or_raise(self, response: httpx.Response | None, attempt: int) -> float:
        """Seconds to wait before trying again; raises the problem of a refusal (or of the last
        try).  ``response`` is None when the connection broke."""
        if response is not None and (response.status_code not in RETRY_STATUSES or attempt == self.retries):
            raise ProblemError.from_response(response)
        return _retry_delay(response, attempt, self.max_wait)

    @staticmethod
    def _settled(status: dict[str, Any]) -> dict[str, Any] | None:
        """The status of a job that has finished well, None while it runs; raises its problem
        when it failed or was cancelled."""
        if status["state"] in ("queued", "running"):
            return None
        if status["state"] != "succeeded":
            error = status.get("error") or {"status": 409, "title": "The job has no result",
                                            "detail": f"the job was {status['state']}"}
            raise ProblemError.from_problem(error, status.get("request_id"))
        return status

    @staticmethod
    def _request_headers() -> dict[str, str]:
        """A request id of our own, so that the server's log lines and our errors can be matched."""
        return {"X-Request-ID": uuid.uuid4().hex}


# -- synchronous ----------------------------------------------------------------------------------

class Client(_Base):
    """The MeshMark API, synchronously.  Use it as a context manager (it holds a connection pool).

    Parameters
    ----------
    base_url : str
        The service, e.g. ``http://127.0.0.1:8000``.
    api_key : str, optional
        One of the server's ``MESHMARK_API_KEYS``, sent as a bearer token.
    retries : int
        Further tries of a request answered 429 or 503, or whose connection broke.
    max_wait : float
        Longest wait between two tries, seconds, whatever ``Retry-After`` says.
    poll_interval : float
        Seconds between two looks at a running job.
    timeout : float
        Seconds without a byte from the server before a request fails.
    """

    def __init__(self, base_url: str, *, api_key: str | None = None, retries: int = 5,
                 max_wait: float = 30.0, poll_interval: float = 0.5, timeout: float = 120.0) -> None:
        super().__init__(base_url, api_key=api_key, retries=retries, max_wait=max_wait,
                         poll_interval=poll_interval, timeout=timeout)
        self.http = httpx.Client(**self._options)

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self.http.close()

    def _send(self, method: str, url: str, *, mesh: MeshSource | None = None, filename: str | None = None,
              data: dict[str, str] | None = None, headers: dict[str, str] | None = None,
              stream: bool = False) -> httpx.Response:
        """One request, tried again on 429/503 and on connection failures; a problem raises."""
        for attempt in range(self.retries + 1):
            response: httpx.Response | None = None
            try:
                if mesh is not None:
                    with _mesh_file(mesh, filename) as (name, content):
                        request = self.http.build_request(method, url, files={"mesh": (name, content)},
                                                          data=data, headers=headers)
                        response = self.http.send(request, stream=stream)
                else:
                    request = self.http.build_request(method, url, headers=headers)
                    response = self.http.send(request, stream=stream)
            except httpx.TransportError as exc:
                self._broken(exc, attempt)
            if response is not None:
                if response.is_success:
                    return response
                response.read()
            time.sleep(self._retry_or_raise(response, attempt))
        raise AssertionError("unreachable")

    # -- jobs ----------------------------------------------------------------------------------

    def submit(self, kind: str, mesh: MeshSource, *, filename: str | None = None, key: str | None = None,
               **fields: Any) -> str:
        """Start an ``embed`` or ``detect`` job; returns its URL path (``/v1/jobs/<id>``)."""
        response = self._send("POST", f"/v1/jobs/{kind}", mesh=mesh, filename=filename,
                              data=_fields(key=key, **fields), headers=self._request_headers())
        return str(response.headers["location"])

    def status(self, job: str) -> dict[str, Any]:
        status: dict[str, Any] = self._send("GET", job).json()
        return status

    def wait(self, job: str, progress: Progress | None = None) -> dict[str, Any]:
        """Follow a job until it finishes; raises the job's problem when it failed."""
        while True:
            status = self.status(job)
            if progress is not None:
                progress(float(status["progress"]))
            if (done := self._settled(status)) is not None:
                return done
            time.sleep(self.poll_interval)

    def download(self, job: str, output: MeshTarget | None = None) -> httpx.Response:
        """The result of a finished job; with ``output``, streamed there (the answer's body is then
        not kept)."""
        response = self._send("GET", f"{job}/result", stream=output is not None)
        if output is not None:
            try:
                with _target(output) as f:
                    for chunk in response.iter_bytes(1 << 20):
                        f.write(chunk)
            finally:
                response.close()
        return response

    def delete(self, job: str) -> None:
        try:
            self._send("DELETE", job)
        except ProblemError as exc:
            if exc.status != 404:  # gone already: expired, or deleted by someone else
                raise

    # -- the work ------------------------------------------------------------------------------

    def embed(self, mesh: MeshSource, output: MeshTarget, *, key: str, payload: str | None = None,
              method: str | None = None, strength: float | None = None, filename: str | None = None,
              progress: Progress | None = None) -> dict[str, Any]:
        """Watermark ``mesh`` into ``output`` (same format); returns the embedding report."""
        job = self.submit("embed", mesh, filename=filename, key=key, payload=payload, method=method,
                          strength=strength)
        try:
            self.wait(job, progress)
            return _report(self.download(job, output))
        finally:
            self.delete(job)

    def detect(self, mesh: MeshSource, *, key: str, payload: str | None = None, method: str | None = None,
               filename: str | None = None, progress: Progress | None = None) -> dict[str, Any]:
        """Look for the key's watermark; returns the detection result (``detected``...)."""
        job = self.submit("detect", mesh, filename=filename, key=key, payload=payload, method=method)
        try:
            self.wait(job, progress)
            result: dict[str, Any] = self.download(job).json()
            return result
        finally:
            self.delete(job)

    def capacity(self, mesh: MeshSource, *, key: str | None = None, method: str | None = None,
                 strength: float | None = None, filename: str | None = None) -> dict[str, Any]:
        """Carriers and payload room of ``mesh`` (a quick synchronous request); with ``key``, the
        carriers an embedding with that key will have."""
        response = self._send("POST", "/v1/capacity", mesh=mesh, filename=filename,
                              data=_fields(key=key, method=method, strength=strength),
                              headers=self._request_headers())
        report: dict[str, Any] = response.json()
        return report


# -- asynchronous ---------------------------------------------------------------------------------

class AsyncClient(_Base):
    """:class:`Client` for asyncio programs: the same parameters, the same methods as coroutines.

    A path given as ``mesh`` is read whole before it is sent (httpx's async client cannot stream
    a plain file); the result is still streamed to disk.
    """

    def __init__(self, base_url: str, *, api_key: str | None = None, retries: int = 5,
                 max_wait: float = 30.0, poll_interval: float = 0.5, timeout: float = 120.0) -> None:
        super().__init__(base_url, api_key=api_key, retries=retries, max_wait=max_wait,
                         poll_interval=poll_interval, timeout=timeout)
        self.http = httpx.AsyncClient(**self._options)

    async def __aenter__(self) -> AsyncClient:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.aclose()

    async def aclose(self) -> None:
        await self.http.aclose()

    async def _send(self, method: str, url: str, *, mesh: MeshSource | None = None,
                    filename: str | None = None, data: dict[str, str] | None = None,
                    headers: dict[str, str] | None = None, stream: bool = False) -> httpx.Response:
        files = None
        if mesh is not None:
            with _mesh_file(mesh, filename) as (name, content):
                body = content if isinstance(content, bytes) else await asyncio.to_thread(content.read)
            files = {"mesh": (name, body)}
        for attempt in range(self.retries + 1):
            response: httpx.Response | None = None
            try:
                request = self.http.build_request(method, url, files=files, data=data, headers=headers)
                response = await self.http.send(request, stream=stream)
            except httpx.TransportError as exc:
                self._broken(exc, attempt)
            if response is not None:
                if response.is_success:
                    return response
                await response.aread()
            await asyncio.sleep(self._retry_or_raise(response, attempt))
        raise AssertionError("unreachable")

    async def submit(self, kind: str, mesh: MeshSource, *, filename: str | None = None,
                     key: str | None = None, **fields: Any) -> str:
        response = await self._send("POST", f"/v1/jobs/{kind}", mesh=mesh, filename=filename,
                                    data=_fields(key=key, **fields), headers=self._request_headers())
        return str(response.headers["location"])

    async def status(self, job: str) -> dict[str, Any]:
        status: dict[str, Any] = (await self._send("GET", job)).json()
        return status

    async def wait(self, job: str, progress: Progress | None = None) -> dict[str, Any]:
        while True:
            status = await self.status(job)
            if progress is not None:
                progress(float(status["progress"]))
            if (done := self._settled(status)) is not None:
                return done
            await asyncio.sleep(self.poll_interval)

    async def download(self, job: str, output: MeshTarget | None = None) -> httpx.Response:
        response = await self._send("GET", f"{job}/result", stream=output is not None)
        if output is not None:
            try:
                with _target(output) as f:
                    async for chunk in response.aiter_bytes(1 << 20):
                        f.write(chunk)
            finally:
                await response.aclose()
        return response

    async def delete(self, job: str) -> None:
        try:
            await self._send("DELETE", job)
        except ProblemError as exc:
            if exc.status != 404:
                raise

    async def embed(self, mesh: MeshSource, output: MeshTarget, *, key: str, payload: str | None = None,
                    method: str | None = None, strength: float | None = None, filename: str | None = None,
                    progress: Progress | None = None) -> dict[str, Any]:
        job = await self.submit("embed", mesh, filename=filename, key=key, payload=payload, method=method,
                                strength=strength)
        try:
            await self.wait(job, progress)
            return _report(await self.download(job, output))
        finally:
            await self.delete(job)

    async def detect(self, mesh: MeshSource, *, key: str, payload: str | None = None,
                     method: str | None = None, filename: str | None = None,
                     progress: Progress | None = None) -> dict[str, Any]:
        job = await self.submit("detect", mesh, filename=filename, key=key, payload=payload, method=method)
        try:
            await self.wait(job, progress)
            result: dict[str, Any] = (await self.download(job)).json()
            return result
        finally:
            await self.delete(job)

    async def capacity(self, mesh: MeshSource, *, key: str | None = None, method: str | None = None,
                       strength: float | None = None, filename: str | None = None) -> dict[str, Any]:
        response = await self._send("POST", "/v1/capacity", mesh=mesh, filename=filename,
                                    data=_fields(key=key, method=method, strength=strength),
                                    headers=self._request_headers())
        report: dict[str, Any] = response.json()
        return report
