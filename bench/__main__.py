"""``python -m bench <suite>``: robustness, paper, false-positives, speed, summary, or all.

``meshbench`` (issue 14) runs MeshBench's attack grid on its five closest shared meshes and puts the
published Cho and Wang figures beside ours (``meshbench.md``); not part of ``all``.

``formats`` and ``fuzz-formats`` (core.formats speed and fuzzing, issue 2) write ``formats.md``.
``pipelines`` (issue 13) runs gltfpack and glTF-Transform on marked GLBs (``pipelines.md``).
``identical --write FILE`` / ``--check FILE`` fingerprints every engine answer on the shared meshes
(byte-identity across refactorings).  ``capacity-keys`` checks that every payload length capacity
allows embeds, for many keys (``capacity_keys.md``).

Results go to ``--out`` (default ``bench/results``) as markdown, JSON and PNG.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

from bench.common import DEFAULT_OUT, engine_ready, meshes_dir

SUITES = ("robustness", "paper", "false-positives", "speed", "summary", "all")
ALL = ("robustness", "paper", "false-positives", "speed")


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m bench", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--quick", action="store_true", help="small meshes, fewer levels and seeds (minutes)")
    common.add_argument(
        "--meshes",
        nargs="+",
        metavar="NAME",
        help="shared mesh file names to use (default: per suite; see bench/common.py)",
    )
    common.add_argument("--out", default=str(DEFAULT_OUT), help="results directory (default: %(default)s)")
    common.add_argument("--seed", type=int, default=2006, help="base seed of payloads, keys and attacks")
    common.add_argument(
        "--jobs",
        type=int,
        default=min(2, os.cpu_count() or 1),
        help="worker processes (default: %(default)s)",
    )
    common.add_argument(
        "--attacks",
        nargs="+",
        metavar="ATTACK",
        help="robustness: only these attacks (names as in bench/attacks.py ATTACKS, or 'extract')",
    )
    common.add_argument(
        "--attack-seeds",
        type=int,
        default=3,
        help="robustness: seeds per level of the random attacks; meshbench: trials (payload and attack "
        "seeds) per mesh and method (default: %(default)s)",
    )
    common.add_argument(
        "--fig21-copies",
        type=int,
        default=0,
        help="paper: noisy copies per level and mesh for Fig. 21 (default 100, quick 10)",
    )
    common.add_argument(
        "--fp-detections",
        type=int,
        default=0,
        help="false-positives: total wrong-key detections (default 10000, quick 400)",
    )
    common.add_argument("--speed-runs", type=int, default=3, help="speed: runs per measurement (min 3)")
    sub = p.add_subparsers(dest="suite", required=True)
    helps = {
        "robustness": "attack grid: recovery rate and BER per attack, distortion, PNG plots",
        "paper": "Bors 2006 Table I, Table II and Fig. 21 reproduced",
        "false-positives": "wrong-key detections on marked and unmarked meshes",
        "speed": "embed/detect/capacity time and memory at 10k/100k/1M vertices",
        "summary": "bench/results/summary.md from the latest results",
        "all": "every suite, then the summary",
    }
    for s in SUITES:
        sub.add_parser(s, parents=[common], help=helps[s])
    mb = sub.add_parser("meshbench", parents=[common],
                        help="MeshBench's attacks and levels: raw BER beside the published Cho and Wang "
                        "figures")
    mb.add_argument("--msdm2-cli", metavar="PATH",
                    help="build of bench/msdm2/msdm2_cli.cpp (MEPP2's MSDM2) for the perceptual score "
                    "(default: $MESHMARK_MSDM2_CLI; without it MSDM2 is reported as not computed)")
    # mesh-format suites (issue 2): core.formats only, not part of "all"
    sub.add_parser("formats", parents=[common], help="core.formats read/write speed and memory vs trimesh")
    fz = sub.add_parser(
        "fuzz-formats", parents=[common], help="core.formats fuzz run over mutated real files"
    )
    fz.add_argument("--cases", type=int, default=10_000, help="fuzz cases (default: %(default)s)")
    fz.add_argument("--timeout", type=float, default=5.0, help="seconds per case before a hang (default: 5)")
    # jobs backend suite (issue 7): needs Redis, starts Celery workers; not part of "all"
    sub.add_parser("redis", parents=[common], help="jobs through Redis + Celery vs the in-process pool")
    sub.add_parser("http", parents=[common], help="HTTP overhead against the CLI; 1 vs 2 workers")
    # asset pipelines (issue 13): gltfpack and glTF-Transform from npm; not part of "all"
    sub.add_parser("pipelines", parents=[common],
                   help="gltfpack / glTF-Transform on marked GLBs, and marking their outputs")
    # leak tracing (issue 18): fingerprinted copies, collusions, innocents, the registry; not in "all"
    from bench.tracing import add_arguments as tracing_arguments

    tracing_arguments(sub.add_parser("tracing", parents=[common],
                                     help="leak tracing: copies, averages, innocents, SQLite vs PostgreSQL"))
    cost = sub.add_parser("cost", parents=[common],
                          help="reading time per byte of every format's hostile shapes, 1 KB to the limit")
    cost.add_argument("--shapes", nargs="+", metavar="SHAPE", help="only these shapes (default: all)")
    cost.add_argument("--limit", type=int, default=0, help="largest size, bytes (default: max_upload_bytes)")
    # byte-identity of every engine answer against a committed baseline (refactorings); not in "all"
    ident = sub.add_parser("identical", parents=[common],
                           help="fingerprint every engine answer on the shared meshes, or compare with one")
    which = ident.add_mutually_exclusive_group(required=True)
    which.add_argument("--write", metavar="FILE", help="record the fingerprints in FILE")
    which.add_argument("--check", metavar="FILE", help="compare with FILE; exit 1 on any difference")
    # capacity exactness over many keys (issue 14); not in "all"
    ck = sub.add_parser("capacity-keys", parents=[common],
                        help="capacity with many keys, then every payload length it allows embedded")
    ck.add_argument("--keys", type=int, default=50, help="keys key-0 ... (default: %(default)s)")
    ck.add_argument("--first-key", type=int, default=0,
                    help="the first key's number: keys key-F ... key-(F+K-1) (default: %(default)s)")
    ck.add_argument("--payloads", type=int, default=2,
                    help="random payloads per length (default: %(default)s)")
    return p


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    Path(args.out).mkdir(parents=True, exist_ok=True)
    if args.suite in ("formats", "fuzz-formats"):
        import importlib

        t = time.perf_counter()
        print(f"[bench] {args.suite} ...", flush=True)
        importlib.import_module(
            "bench.formats_speed" if args.suite == "formats" else "bench.fuzz_formats"
        ).run(args)
        print(
            f"[bench] {args.suite} done in {time.perf_counter() - t:.0f} s -> {Path(args.out) / 'formats.md'}"
        )
        return 0
    if args.suite == "pipelines":
        from bench import pipelines

        pipelines.run(args)
        print(f"[bench] pipelines -> {Path(args.out) / 'pipelines.md'}")
        return 0
    if args.suite == "cost":
        from bench import cost

        return cost.run(args)
    if args.suite == "http":
        from bench import http_service

        print(http_service.run(Path(args.out)))
        return 0
    if args.suite == "tracing":
        from bench import tracing

        tracing.run(args)
        written = "tracing_registry.md" if args.registry_only else "tracing.md"
        print(f"[bench] tracing -> {Path(args.out) / written}")
        return 0
    if args.suite == "identical":
        from bench import identical

        return identical.run(args)
    if args.suite == "capacity-keys":
        from bench import capacity_keys

        capacity_keys.run(args)
        return 0
    if args.suite == "redis":
        from bench import redis_throughput

        redis_throughput.run(args)
        return 0
    if args.suite != "summary":
        if not engine_ready():
            print("the engine (core/pipeline.py) is not available yet: nothing to benchmark", file=sys.stderr)
            return 2
        if not meshes_dir().is_dir():
            print(f"shared meshes not found at {meshes_dir()} (set MESHMARK_TEST_MESHES)", file=sys.stderr)
            return 2
    from bench import false_positives, meshbench, paper, robustness, speed, summary

    runners = {
        "robustness": robustness.run,
        "paper": paper.run,
        "false-positives": false_positives.run,
        "speed": speed.run,
        "meshbench": meshbench.run,
    }
    todo = list(ALL) if args.suite == "all" else [] if args.suite == "summary" else [args.suite]
    for s in todo:
        t = time.perf_counter()
        print(f"[bench] {s} ...", flush=True)
        runners[s](args)
        print(f"[bench] {s} done in {time.perf_counter() - t:.0f} s -> {args.out}", flush=True)
    summary.run(args)
    print(f"[bench] summary -> {Path(args.out) / 'summary.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
