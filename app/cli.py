"""``meshmark``: embed, detect and measure capacity on local files, serve the HTTP API, or run a
worker of the Redis jobs backend.

Exit codes: 0 success (detect: watermark found), 1 detect ran but found no watermark,
2 usage or input error (bad arguments, unreadable file, malformed mesh...), 3 internal error.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import traceback
from collections.abc import Sequence
from pathlib import Path
from typing import Any, NoReturn

from app.workers.process import one_blas_thread
from core import api
from core.allocator import tune_malloc
from core.errors import MeshMarkError
from core.formats import FORMATS
from core.options import check_key

EXIT_OK, EXIT_NOT_DETECTED, EXIT_USAGE, EXIT_INTERNAL = 0, 1, 2, 3
KEY_ENV = "MESHMARK_KEY"


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


def _read_key(args: argparse.Namespace) -> str:
    """``--key``, else ``--key-file`` (one trailing newline dropped), else ``$MESHMARK_KEY``."""
    if args.key is not None:
        key = args.key
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
        if key is None:
            raise _UsageError(f"give the watermark key with --key, --key-file or ${KEY_ENV}")
    check_key(key)
    return key


def _read_mesh(path: str) -> bytes:
    try:
        return Path(path).read_bytes()
    except OSError as exc:
        raise _UsageError(f"cannot read {path}: {exc.strerror}") from None


def _print_json(value: dict[str, Any]) -> None:
    try:
        print(json.dumps(value, separators=(",", ":"), allow_nan=False), flush=True)
    except BrokenPipeError:  # the reader went away (`| head`); the exit code still tells the outcome
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())


def _embed(args: argparse.Namespace) -> int:
    tune_malloc()
    key = _read_key(args)
    data = _read_mesh(args.input)
    options = api.Options(key=key, payload=args.payload, method=args.method, strength=args.strength)
    embedded = api.embed(data, options, filename=Path(args.input).name, progress=_progress_bar("embedding"))
    try:
        Path(args.output).write_bytes(embedded.data)
    except OSError as exc:
        raise _UsageError(f"cannot write {args.output}: {exc.strerror}") from None
    _print_json(embedded.report.to_dict())
    return EXIT_OK


def _detect(args: argparse.Namespace) -> int:
    tune_malloc()
    key = _read_key(args)
    data = _read_mesh(args.input)
    options = api.Options(key=key, payload=args.payload, method=args.method)
    result = api.detect(data, options, filename=Path(args.input).name, progress=_progress_bar("detecting"))
    _print_json(result.to_dict())
    return EXIT_OK if result.detected else EXIT_NOT_DETECTED


def _capacity(args: argparse.Namespace) -> int:
    tune_malloc()
    data = _read_mesh(args.input)
    options = api.Options(method=args.method, strength=args.strength)
    report = api.capacity(data, options, filename=Path(args.input).name)
    _print_json(report.to_dict())
    return EXIT_OK


def _serve(args: argparse.Namespace) -> int:
    import uvicorn
    from pydantic import ValidationError

    from app.config import Settings

    overrides = {k: v for k, v in (("host", args.host), ("port", args.port), ("workers", args.workers))
                 if v is not None}
    try:
        settings = Settings(**overrides)  # flags win over MESHMARK_* variables
    except ValidationError as exc:
        problems = "; ".join(f"{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in exc.errors())
        raise _UsageError(f"invalid settings: {problems}") from None

    from app.main import create_app

    logging.basicConfig(level=settings.log_level.upper(),
                        format="%(asctime)s %(levelname)s %(name)s %(message)s")
    # access lines come from app.middleware (with the route and the duration), not uvicorn
    # httptools and uvloop (dependencies) rather than uvicorn's pure-Python fallbacks: under
    # overload the API process spends its time reading uploads it refuses
    uvicorn.run(create_app(settings), host=settings.host, port=settings.port, log_level=settings.log_level,
                access_log=False, http="httptools", loop="uvloop")
    return EXIT_OK


def _worker(args: argparse.Namespace) -> int:
    from pydantic import ValidationError

    from app.config import Settings

    overrides = {k: v for k, v in (("worker_concurrency", args.concurrency), ("jobs_queue", args.queue))
                 if v is not None}
    try:
        settings = Settings(**overrides)
    except ValidationError as exc:
        problems = "; ".join(f"{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in exc.errors())
        raise _UsageError(f"invalid settings: {problems}") from None
    try:
        from app.redis_jobs.celery_app import run_worker
    except ImportError as exc:
        raise _UsageError(f"the Redis backend needs the 'redis' extra (pip install 'meshmark[redis]'): "
                          f"{exc}") from None
    one_blas_thread()
    try:
        run_worker(settings)
    except PermissionError as exc:
        raise _UsageError(str(exc)) from None
    return EXIT_OK


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="meshmark", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)

    def key_options(p: argparse.ArgumentParser) -> None:
        group = p.add_mutually_exclusive_group()
        group.add_argument("--key", help=f"watermark key (visible in `ps`; prefer --key-file or ${KEY_ENV})")
        group.add_argument("--key-file", help="file holding the key (one trailing newline is ignored)")

    def method_option(p: argparse.ArgumentParser, default: str | None) -> None:
        p.add_argument("--method", choices=api.METHODS, default=default,
                       help=f"embedding method (default: {default or 'try both'})")

    p = sub.add_parser("embed", help="watermark a mesh file")
    p.add_argument("input", help=f"mesh file ({', '.join(spec.label for spec in FORMATS.values())})")
    p.add_argument("output", help="where to write the watermarked mesh (same format)")
    key_options(p)
    p.add_argument("--payload", help="bitstring of 1-256 '0'/'1' (default: 32 bits derived from the key)")
    method_option(p, api.DEFAULT_METHOD)
    p.add_argument("--strength", type=float, help="boundary margin, > 0 (engine default if omitted)")
    p.set_defaults(run=_embed)

    p = sub.add_parser("detect", help="look for a watermark (exit 1 when none is found)")
    p.add_argument("input", help="mesh file")
    key_options(p)
    p.add_argument("--payload", help="expected payload, to get bit errors and a p-value")
    method_option(p, None)
    p.set_defaults(run=_detect)

    p = sub.add_parser("capacity", help="carriers and payload room of a mesh")
    p.add_argument("input", help="mesh file")
    method_option(p, api.DEFAULT_METHOD)
    p.add_argument("--strength", type=float, help="boundary margin, > 0")
    p.set_defaults(run=_capacity)

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
