"""A real ``meshmark serve`` process for the hardening tests: started the way the README says, on a
free port, with its stderr kept for inspection; and raw-socket helpers for requests no HTTP
client library would send.  The load and HTTP benchmarks start their servers with the same
:func:`start_server`."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import psutil
import pytest

#: the CLI installed beside this interpreter (``pip install -e .``)
MESHMARK = Path(sys.executable).with_name("meshmark")


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on right now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def start_server(port: int, env: dict[str, str], out: Any = subprocess.DEVNULL, args: tuple[str, ...] = (),
                 timeout: float = 60) -> subprocess.Popen[bytes]:
    """``meshmark serve --port PORT *args`` with ``env`` added to this environment, its output
    (stdout and stderr) to ``out``; returns once ``/readyz`` answers 200.  Raises ``RuntimeError``
    (the process killed) when it exits first or is not ready within ``timeout`` seconds."""
    proc = subprocess.Popen([str(MESHMARK), "serve", "--port", str(port), *args], env={**os.environ, **env},
                            stdout=out, stderr=subprocess.STDOUT)
    deadline = time.monotonic() + timeout
    while True:
        try:
            if httpx.get(f"http://127.0.0.1:{port}/readyz", timeout=1).status_code == 200:
                return proc
        except httpx.TransportError:
            pass
        if proc.poll() is not None or time.monotonic() > deadline:
            proc.kill()
            proc.wait()
            raise RuntimeError("meshmark serve did not become ready")
        time.sleep(0.1)


@dataclass
class Server:
    base: str
    port: int
    proc: subprocess.Popen[bytes]
    log: Path

    def text(self) -> str:
        return self.log.read_text(errors="replace")


@contextmanager
def serve(log: Path, **env: str) -> Iterator[Server]:
    """``meshmark serve`` with ``MESHMARK_*`` settings from ``env``; stopped (SIGTERM, then SIGKILL)
    on exit unless the test stopped it already."""
    if not MESHMARK.exists():
        pytest.skip(f"{MESHMARK} not installed (pip install -e .)")
    port = free_port()
    environ = {"MESHMARK_WORKERS": "1", "MESHMARK_LOG_LEVEL": "info",
               **{f"MESHMARK_{k.upper()}": v for k, v in env.items()}}
    with open(log, "wb") as out:
        try:
            proc = start_server(port, environ, out)
        except RuntimeError:
            pytest.fail(f"server did not start: {log.read_text(errors='replace')}")
    server = Server(f"http://127.0.0.1:{port}", port, proc, log)
    try:
        yield server
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


def raw_exchange(port: int, request: bytes, *, body_chunks: list[bytes] | None = None,
                 timeout: float = 10.0) -> tuple[int, dict[str, str], bytes, float]:
    """Send raw bytes (then ``body_chunks`` one by one, while the server lets us), read the answer
    until the server closes or one full response has arrived.  Returns (status, headers, body,
    seconds to the first byte of the answer)."""
    start = time.perf_counter()
    with socket.create_connection(("127.0.0.1", port), timeout=timeout) as sock:
        sock.sendall(request)
        for chunk in body_chunks or []:
            try:
                sock.sendall(chunk)
            except (BrokenPipeError, ConnectionResetError):
                break
        data = b""
        first: float | None = None
        while True:
            try:
                piece = sock.recv(65536)
            except ConnectionResetError:
                break
            if not piece:
                break
            first = first if first is not None else time.perf_counter() - start
            data += piece
            head, sep, rest = data.partition(b"\r\n\r\n")
            if sep:
                headers = _headers(head)
                if "content-length" in headers and len(rest) >= int(headers["content-length"]):
                    break
    head, _, rest = data.partition(b"\r\n\r\n")
    status = int(head.split(b" ", 2)[1]) if head.startswith(b"HTTP/1.1 ") else 0
    return status, _headers(head), rest, first if first is not None else time.perf_counter() - start


def _headers(head: bytes) -> dict[str, str]:
    out = {}
    for line in head.split(b"\r\n")[1:]:
        name, _, value = line.partition(b":")
        out[name.strip().lower().decode("latin-1")] = value.strip().decode("latin-1")
    return out


def descendants(parent: int) -> list[int]:
    """Live descendants of ``parent`` (the fork server and the workers)."""
    try:
        return [p.pid for p in psutil.Process(parent).children(recursive=True) if alive(p.pid)]
    except psutil.NoSuchProcess:
        return []


def alive(pid: int) -> bool:
    try:
        return bool(psutil.Process(pid).status() != psutil.STATUS_ZOMBIE)
    except psutil.NoSuchProcess:
        return False
