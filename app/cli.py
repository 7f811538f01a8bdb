"""``meshmark``: embed, detect and measure capacity on local files (here, or on a MeshMark server
with ``--server URL``), issue fingerprinted copies and trace leaks (with the local registry),
serve the HTTP API, or run a worker of the Redis jobs backend.

A mesh argument may be ``-``: standard input, or for the output standard output (the report then
goes to standard error).

Exit codes: 0 success (detect: watermark found; trace: someone accused), 1 detect ran but found
no watermark (trace: no one accused),
2 usage or input error (bad arguments, unreadable file, malformed mesh, a refusal of the server),
3 internal error, 4 the server could not be reached or kept failing (5xx, 429 after the retries).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import socket
import sys
import traceback
from collections.abc import Sequence
from pathlib import Path
from typing import Any, BinaryIO, NoReturn

from app.workers.process import one_blas_thread
from core import api
from core.allocator import tune_malloc
from core.errors import MeshMarkError
from core.formats import FORMATS, detect_format
from core.options import check_key
from meshmark import __version__

EXIT_OK, EXIT_NOT_DETECTED, EXIT_USAGE, EXIT_INTERNAL, EXIT_SERVER = 0, 1, 2, 3, 4
KEY_ENV = "MESHMARK_KEY"
SERVER_ENV = "MESHMARK_SERVER"
API_KEY_ENV = "MESHMARK_API_KEY"
#: a mesh argument that means standard input (or output)
STDIO = "-"


class _UsageError(Exception):
    pass


def _progress_bar(label: str) -> api.Progress | None:
    """A one-line progress bar on stderr, only when stderr is a terminal."""
    if not sys.stderr.isatty():
        return None

    def show(fraction: float) -> None:
        done = int(fraction * 30)
        sys.stderr.write(f"\r{label} [{'#' * done}{'.' * (30 - done)}] {fraction:4.0%}")
        if fraction >= 1.0:
            sys.stderr.write("\n")
        sys.stderr.flush()

    return show


def _given_key(args: argparse.Namespace) -> str | None:
    """``--key``, else ``--key-file`` (one trailing newline dropped), else ``$MESHMARK_KEY``, else
    None."""
    if args.key is not None:
        key: str | None = args.key
    elif args.key_file is not None:
        try:
            key = Path(args.key_file).read_bytes().decode("utf-8")
        except OSError as exc:
            raise _UsageError(f"cannot read the key file: {exc.strerror}") from None
        except UnicodeDecodeError:
            raise _UsageError("the key file is not UTF-8") from None
        key = key.removesuffix("\n").removesuffix("\r")
    else:
        key = os.environ.get(KEY_ENV)
    if key is not None:
        check_key(key)
    return key


def _read_key(args: argparse.Namespace) -> str:
    key = _given_key(args)
    if key is None:
        raise _UsageError(f"give the watermark key with --key, --key-file or ${KEY_ENV}")
    return key


def _read_mesh(path: str) -> bytes:
    if path == STDIO:
        return sys.stdin.buffer.read()
    try:
        return Path(path).read_bytes()
    except OSError as exc:
        raise _UsageError(f"cannot read {path}: {exc.strerror}") from None


def _name(path: str) -> str | None:
    """The file name the engine cross-checks the content with (none for standard input)."""
    return None if path == STDIO else Path(path).name


def _check_output(data: bytes, args: argparse.Namespace) -> None:
    """The marked file keeps the input's format: an output named for another format is refused
    before any work (PLY bytes in a file called .obj would mislead every program that opens it)."""
    if args.output == STDIO:
        return
    spec = FORMATS[detect_format(data, _name(args.input))]
    suffix = Path(args.output).suffix.lower().removeprefix(".")
    if suffix not in spec.extensions:
        wanted = " or ".join(f".{ext}" for ext in spec.extensions)
        raise _UsageError(f"the marked file is {spec.label}, like the input: name the output {wanted}, "
                          f"not '{Path(args.output).name}' (MeshMark does not convert formats)")


def _print_json(value: dict[str, Any], stream: Any = None) -> None:
    stream = stream or sys.stdout
    try:
        print(json.dumps(value, separators=(",", ":"), allow_nan=False), file=stream, flush=True)
    except BrokenPipeError:  # the reader went away (`| head`); the exit code still tells the outcome
        os.dup2(os.open(os.devnull, os.O_WRONLY), stream.fileno())


def _write_output(path: str, data: bytes) -> None:
    if path == STDIO:
        sys.stdout.buffer.write(data)
        sys.stdout.buffer.flush()
        return
    try:
        Path(path).write_bytes(data)
    except OSError as exc:
        raise _UsageError(f"cannot write {path}: {exc.strerror}") from None


def _report_stream(args: argparse.Namespace) -> Any:
    """The report goes to standard output, unless the mesh does."""
    return sys.stderr if args.output == STDIO else sys.stdout


def _embed(args: argparse.Namespace) -> int:
    key = _read_key(args)
    data = _read_mesh(args.input)
    options = api.Options(key=key, payload=args.payload, method=args.method, strength=args.strength)
    _check_output(data, args)
    if args.server:
        return _remote(args, lambda mm: _remote_embed(mm, args, data, key))
    tune_malloc()
    embedded = api.embed(data, options, filename=_name(args.input), progress=_progress_bar("embedding"))
    _write_output(args.output, embedded.data)
    _print_json(embedded.report.to_dict(), _report_stream(args))
    return EXIT_OK


def _remote_embed(mm: Any, args: argparse.Namespace, data: bytes, key: str) -> int:
    output: str | BinaryIO = sys.stdout.buffer if args.output == STDIO else args.output
    report = mm.embed(data, output, key=key, payload=args.payload, method=args.method,
                      strength=args.strength, filename=_name(args.input) or "mesh",
                      progress=_progress_bar("embedding"))
    _print_json(report, _report_stream(args))
    return EXIT_OK


def _detect(args: argparse.Namespace) -> int:
    key = _read_key(args)
    data = _read_mesh(args.input)
    options = api.Options(key=key, payload=args.payload, method=args.method)
    if args.server:
        found: dict[str, Any] = _remote(args, lambda mm: mm.detect(
            data, key=key, payload=args.payload, method=args.method, filename=_name(args.input) or "mesh",
            progress=_progress_bar("detecting")))
    else:
        tune_malloc()
        found = api.detect(data, options, filename=_name(args.input),
                           progress=_progress_bar("detecting")).to_dict()
    _print_json(found)
    return EXIT_OK if found["detected"] else EXIT_NOT_DETECTED


def _capacity(args: argparse.Namespace) -> int:
    key = _given_key(args)
    data = _read_mesh(args.input)
    options = api.Options(key=key, method=args.method, strength=args.strength)
    if args.server:
        report: dict[str, Any] = _remote(args, lambda mm: mm.capacity(
            data, key=key, method=args.method, strength=args.strength, filename=_name(args.input) or "mesh"))
    else:
        tune_malloc()
        report = api.capacity(data, options, filename=_name(args.input)).to_dict()
    _print_json(report)
    return EXIT_OK


def _copy(args: argparse.Namespace) -> int:
    """A fingerprinted copy for ``--recipient``, recorded in the registry of the ``MESHMARK_*``
    settings (``MESHMARK_REGISTRY_PATH`` or ``MESHMARK_REGISTRY_URL``)."""
    from app.problems import ProblemError
    from app.tracing import open_registry, plan_copy, record_copy, run_copy

    key = _read_key(args)
    data = _read_mesh(args.input)
    options = api.Options(key=key, method=args.method, strength=args.strength)
    _check_output(data, args)
    tune_malloc()
    with open_registry(_settings()) as registry:
        try:
            plan = plan_copy(registry, data, options, args.recipient, args.asset_id)
            value = run_copy(plan, data, options, filename=_name(args.input),
                             progress=_progress_bar("marking"))
            stored = record_copy(registry, plan, options, value)
        except ProblemError as exc:
            raise _UsageError(exc.detail) from None
    _write_output(args.output, value.file.data)
    _print_json({"asset_id": stored.asset_id, "recipient": stored.recipient,
                 "codeword_bits": stored.codeword_bits, "score": round(value.score, 2),
                 "report": value.file.report.to_dict()}, _report_stream(args))
    return EXIT_OK


def _trace(args: argparse.Namespace) -> int:
    """Who leaked ``input``: exit 0 when someone is accused, 1 when no one is."""
    from app.problems import ProblemError
    from app.tracing import open_registry, plan_trace, rank_copies, run_trace

    key = _read_key(args)
    data = _read_mesh(args.input)
    if not 0 < args.threshold <= 0.5:
        raise _UsageError("--threshold must be in (0, 0.5]")
    tune_malloc()
    with open_registry(_settings()) as registry:
        try:
            plan = plan_trace(registry, args.asset_id, args.threshold, args.top)
        except ProblemError as exc:
            raise _UsageError(exc.detail) from None
        votes = run_trace(plan, data, key, filename=_name(args.input), progress=_progress_bar("tracing"))
        answer = rank_copies(registry, plan, votes)
    _print_json(answer)
    return EXIT_OK if answer["accused"] else EXIT_NOT_DETECTED


def _remote(args: argparse.Namespace, work: Any) -> Any:
    """``work(client)`` against ``--server``; the server's refusals become CLI errors."""
    import httpx

    from meshmark.client import Client, ProblemError

    try:
        with Client(args.server, api_key=os.environ.get(API_KEY_ENV) or None) as mm:
            return work(mm)
    except ProblemError as exc:
        if 400 <= exc.status < 500 and exc.status != 429:
            raise _UsageError(str(exc)) from None
        _fail(EXIT_SERVER, f"the server failed: {exc}")
    except httpx.TransportError as exc:
        _fail(EXIT_SERVER, f"cannot reach {args.server}: {exc}")


#: the top-level packages this distribution installs
OUR_PACKAGES = ("app", "core", "meshmark")


def foreign_owners() -> dict[str, list[str]]:
    """Top-level packages of ours that another installed distribution also provides (the generic
    ``app`` and ``core`` can collide: the second install overwrites the first one's files)."""
    from importlib.metadata import packages_distributions

    owners = packages_distributions()
    found = {name: sorted(d for d in set(owners.get(name, [])) if d.lower() != "meshmark")
             for name in OUR_PACKAGES}
    return {name: dists for name, dists in found.items() if dists}


def _warn_about_collisions() -> None:
    for package, dists in foreign_owners().items():
        logging.getLogger("meshmark.app").warning(
            "the top-level package '%s' is also installed by %s: one install overwrites the other's files; "
            "install meshmark in its own virtual environment (or use the Docker image)", package,
            ", ".join(dists))


def _settings(**overrides: Any) -> Any:
    """The service settings, flags over ``MESHMARK_*`` variables; an invalid one is a usage error."""
    from pydantic import ValidationError

    from app.config import Settings

    try:
        return Settings(**{k: v for k, v in overrides.items() if v is not None})
    except ValidationError as exc:
        problems = "; ".join(f"{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in exc.errors())
        raise _UsageError(f"invalid settings: {problems}") from None


def _listen(host: str, port: int) -> socket.socket:
    """The server's listening socket, bound here so that an address in use is a clear usage error
    rather than uvicorn's exit deep inside its start-up."""
    try:
        family, kind, proto, _, address = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)[0]
        sock = socket.socket(family, kind, proto)
    except OSError as exc:
        raise _UsageError(f"cannot listen on {host}:{port}: {exc.strerror or exc}") from None
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(address)
    except OSError as exc:
        sock.close()
        hint = " (another server is running there? choose one with --port)" if exc.errno == 98 else ""
        raise _UsageError(f"cannot listen on {host}:{port}: {exc.strerror}{hint}") from None
    sock.set_inheritable(True)
    return sock


def _serve(args: argparse.Namespace) -> int:
    import uvicorn

    from app.logs import configure_logging

    settings = _settings(host=args.host, port=args.port, workers=args.workers)
    from app.main import create_app  # after the settings are checked: the module makes a default app

    configure_logging(settings.log_level, settings.log_format)
    _warn_about_collisions()
    sock = _listen(settings.host, settings.port)
    # httptools and uvloop (dependencies) rather than uvicorn's pure-Python fallbacks: under
    # overload the API process spends its time reading uploads it refuses.  Access lines come
    # from app.middleware (with the route, the problem type and the request id), not uvicorn;
    # log_config=None keeps uvicorn's own lines in the one stream configure_logging set up.
    config = uvicorn.Config(create_app(settings), log_level=settings.log_level, access_log=False,
                            limit_concurrency=settings.max_connections,
                            log_config=None, http="httptools", loop="uvloop")
    uvicorn.Server(config).run(sockets=[sock])
    return EXIT_OK


def _worker(args: argparse.Namespace) -> int:
    settings = _settings(worker_concurrency=args.concurrency, jobs_queue=args.queue)
    try:
        from app.redis_jobs.celery_app import run_worker
    except ImportError as exc:
        raise _UsageError(f"the Redis backend needs the 'redis' extra (pip install 'meshmark[redis]'): "
                          f"{exc}") from None
    one_blas_thread()
    _warn_about_collisions()  # (Celery sets up its own logging later: this goes to stderr as is)
    try:
        run_worker(settings)
    except PermissionError as exc:
        raise _UsageError(str(exc)) from None
    return EXIT_OK


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="meshmark", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)

    def key_options(p: argparse.ArgumentParser) -> None:
        group = p.add_mutually_exclusive_group()
        group.add_argument("--key", help=f"watermark key (visible in `ps`; prefer --key-file or ${KEY_ENV})")
        group.add_argument("--key-file", help="file holding the key (one trailing newline is ignored)")

    def method_option(p: argparse.ArgumentParser, default: str | None, unset: str = "try both") -> None:
        p.add_argument("--method", choices=api.METHODS, default=default,
                       help=f"embedding method (default: {default or unset})")

    def server_option(p: argparse.ArgumentParser) -> None:
        p.add_argument("--server", metavar="URL", default=os.environ.get(SERVER_ENV) or None,
                       help=f"do the work on this MeshMark server (default: ${SERVER_ENV}; API key from "
                       f"${API_KEY_ENV})")

    mesh_help = f"mesh file ({', '.join(spec.label for spec in FORMATS.values())}), or - for standard input"

    p = sub.add_parser("embed", help="watermark a mesh file")
    p.add_argument("input", help=mesh_help)
    p.add_argument("output", help="where to write the watermarked mesh (same format and extension), or - "
                   "for standard output (the report then goes to standard error)")
    key_options(p)
    p.add_argument("--payload", help="bitstring of 1-256 '0'/'1' (default: 32 bits derived from the key)")
    method_option(p, None, api.AUTO_METHOD)
    p.add_argument("--strength", type=float, help="boundary margin, > 0 (engine default if omitted)")
    server_option(p)
    p.set_defaults(run=_embed)

    p = sub.add_parser("detect", help="look for a watermark (exit 1 when none is found)")
    p.add_argument("input", help=mesh_help)
    key_options(p)
    p.add_argument("--payload", help="expected payload, to get bit errors and a p-value")
    method_option(p, None)
    server_option(p)
    p.set_defaults(run=_detect)

    p = sub.add_parser("capacity", help="carriers and payload room of a mesh (with a key: exactly the "
                       "carriers an embedding with it will have)")
    p.add_argument("input", help=mesh_help)
    key_options(p)
    method_option(p, None, api.AUTO_METHOD)
    p.add_argument("--strength", type=float, help="boundary margin, > 0")
    server_option(p)
    p.set_defaults(run=_capacity)

    p = sub.add_parser("copy", help="a fingerprinted copy for one recipient, recorded in the registry "
                       "(MESHMARK_REGISTRY_PATH or MESHMARK_REGISTRY_URL)")
    p.add_argument("input", help=mesh_help)
    p.add_argument("output", help="where to write the recipient's copy (same format and extension), or -")
    p.add_argument("--recipient", required=True, help="who the copy is for (any text)")
    p.add_argument("--asset-id", help="the asset's id (default: sha256: and the SHA-256 of the input)")
    key_options(p)
    method_option(p, api.DEFAULT_METHOD)
    p.add_argument("--strength", type=float, help="boundary margin, > 0 (engine default if omitted)")
    p.set_defaults(run=_copy)

    p = sub.add_parser("trace", help="who leaked this copy (exit 0: someone accused, 1: no one)")
    p.add_argument("input", help=mesh_help)
    p.add_argument("--asset-id", help="trace among this asset's copies (default: every copy registered)")
    key_options(p)
    p.add_argument("--threshold", type=float, default=1e-9,
                   help="accuse at this false-accusation probability (default: %(default)g)")
    p.add_argument("--top", type=int, default=10, help="recipients listed (default: %(default)s)")
    p.set_defaults(run=_trace)

    p = sub.add_parser("serve", help="run the HTTP API (settings from MESHMARK_* variables)")
    p.add_argument("--host", help="bind address (default: $MESHMARK_HOST or 127.0.0.1)")
    p.add_argument("--port", type=int, help="port (default: $MESHMARK_PORT or 8000)")
    p.add_argument("--workers", type=int, help="worker processes (default: $MESHMARK_WORKERS or 2)")
    p.set_defaults(run=_serve)

    p = sub.add_parser("worker", help="run a Celery worker of the Redis jobs backend (settings from "
                       "MESHMARK_* variables: MESHMARK_REDIS_URL, MESHMARK_BLOB_DIR...)")
    p.add_argument("--concurrency", type=int,
                   help="worker processes (default: $MESHMARK_WORKER_CONCURRENCY or the CPU count)")
    p.add_argument("--queue", help="queue to serve (default: $MESHMARK_JOBS_QUEUE or meshmark)")
    p.set_defaults(run=_worker)
    return parser


def _fail(code: int, message: str) -> NoReturn:
    print(f"meshmark: error: {message}", file=sys.stderr)
    raise SystemExit(code)


def main(argv: Sequence[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    try:
        code: int = args.run(args)
    except (_UsageError, MeshMarkError) as exc:
        _fail(EXIT_USAGE, str(exc))
    except KeyboardInterrupt:
        _fail(EXIT_INTERNAL, "interrupted")
    except Exception:
        traceback.print_exc()
        _fail(EXIT_INTERNAL, "internal error (traceback above)")
    return code


if __name__ == "__main__":
    sys.exit(main())
