"""Where one engine call spends its wall time, thread by thread: a sampled timeline.

    .venv/bin/python -m bench.timeline FILE [--op embed|detect] [--method ellipsoids]
                                            [--interval 0.005] [--bucket 0.1] [--out FILE.md]

The call is made twice in this process (the first warms the allocator and the caches, as
``bench speed``'s warm figure does); during the second a sampling thread reads every other thread's
Python stack (:func:`sys._current_frames`) every ``--interval`` seconds and keeps the innermost
frame that lies in ``core/``.  A thread whose stack has no such frame is idle (a pool thread waiting
for work); a thread waiting on a future (``Future.result``, a lock) is counted under the engine
line that waits but listed apart as *waiting*, not busy.  Prints (or writes) markdown:

* per thread: samples busy and waiting, as a share of the call;
* the functions with the most thread-seconds (busy samples x the wall time per sample, over all
  threads): the CPU the call spends where, which is what shortens a two-core run once both cores
  are busy;
* the timeline in buckets of ``--bucket`` seconds: each thread's most frequent function, and how
  many of the two cores were busy on average (1.0 or less: one core idle for that stretch, the
  place to overlap work).

Sampling is statistical: a 5 ms interval over a 3 s call is 600 samples per thread, so a function
needs a few dozen milliseconds to show.  The sampler itself takes the GIL for a few microseconds
per sample; numpy's large loops release it, so the engine's threads keep running meanwhile.  Only
the public entry points of :mod:`core.api` are called, on file bytes, as in ``bench speed``.
"""

from __future__ import annotations

import argparse
import collections
import functools
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from types import FrameType

from bench.common import KEY, environment, header, md_table

#: frames from these files are the engine's
CORE = str(Path(__file__).resolve().parents[1] / "core")
#: a thread whose innermost frame is in one of these waits (a lock, a condition, a future's result)
WAITING_IN = (threading.__file__, "concurrent/futures/")


@dataclass
class Sample:
    t: float
    #: thread name -> (innermost engine function "module.function", line, waiting)
    where: dict[str, tuple[str, int, bool]]


@dataclass
class Timeline:
    wall: float
    samples: list[Sample]

    def threads(self) -> list[str]:
        seen: dict[str, None] = {}
        for s in self.samples:
            for name in s.where:
                seen.setdefault(name, None)
        return list(seen)


@functools.cache
def _module(filename: str) -> str:
    """``core.mesh`` for ``.../core/mesh.py`` (made once per file: the sampler holds the GIL)."""
    return Path(filename).relative_to(Path(CORE).parent).with_suffix("").as_posix().replace("/", ".")


def _engine_frame(frame: FrameType | None) -> tuple[str, int, bool] | None:
    """Innermost frame of ``frame``'s stack that lies in ``core/``, and whether the thread is
    blocked (its innermost frame is in :mod:`threading` or :mod:`concurrent.futures`; other
    standard-library frames are work)."""
    blocked = frame is not None and any(w in frame.f_code.co_filename for w in WAITING_IN)
    f = frame
    while f is not None:
        name = f.f_code.co_filename
        if name.startswith(CORE):
            return f"{_module(name)}.{f.f_code.co_name}", f.f_lineno, blocked
        f = f.f_back
    return None


def sample(call, interval: float = 0.005) -> Timeline:
    """Run ``call()`` while sampling every other thread's innermost engine frame."""
    samples: list[Sample] = []
    stop = threading.Event()
    me = threading.get_ident()

    def run() -> None:
        sampler = threading.get_ident()
        while not stop.is_set():
            t = time.perf_counter()
            names = {th.ident: th.name for th in threading.enumerate()}
            where: dict[str, tuple[str, int, bool]] = {}
            for ident, frame in sys._current_frames().items():
                if ident == sampler:
                    continue
                got = _engine_frame(frame)
                if got is not None:
                    where["main" if ident == me else names.get(ident, str(ident))] = got
            samples.append(Sample(t, where))
            stop.wait(interval)

    th = threading.Thread(target=run, name="bench-timeline", daemon=True)
    t0 = time.perf_counter()
    th.start()
    try:
        call()
    finally:
        t1 = time.perf_counter()
        stop.set()
        th.join()
    return Timeline(t1 - t0, [Sample(s.t - t0, s.where) for s in samples if t0 <= s.t <= t1])


def report(tl: Timeline, bucket: float = 0.1, top: int = 25) -> str:
    """Markdown: threads, thread-seconds per function, and the bucketed timeline."""
    n = len(tl.samples) or 1
    dt = tl.wall / n  # time a sample stands for
    threads = tl.threads()
    lines = [f"Wall time of the sampled call: {tl.wall:.3f} s, {len(tl.samples)} samples "
             f"(one every {1e3 * dt:.1f} ms).", ""]
    rows = []
    for name in threads:
        busy = sum(1 for s in tl.samples if name in s.where and not s.where[name][2])
        wait = sum(1 for s in tl.samples if name in s.where and s.where[name][2])
        rows.append([name, f"{busy * dt:.3f}", f"{busy / n:.2f}", f"{wait * dt:.3f}"])
    lines += ["### Threads", "", md_table(["thread", "busy s", "busy share", "waiting s"], rows, "lrrr"), ""]
    per: collections.Counter[str] = collections.Counter()
    for s in tl.samples:
        for fn, _, blocked in s.where.values():
            if not blocked:
                per[fn] += 1
    total = sum(per.values())
    rows = [[fn, f"{c * dt:.3f}", f"{c / (total or 1):.3f}"] for fn, c in per.most_common(top)]
    lines += [f"### Thread-seconds by function (busy samples of every thread; {total * dt:.2f} s in all)", "",
              md_table(["function (innermost engine frame)", "thread-s", "share"], rows, "lrr"), ""]
    lines += [f"### Timeline ({bucket:g} s buckets; cores = busy threads per sample, averaged)", ""]
    buckets: dict[int, list[Sample]] = collections.defaultdict(list)
    for s in tl.samples:
        buckets[int(s.t / bucket)].append(s)
    rows = []
    for k in sorted(buckets):
        group = buckets[k]
        busy = sum(sum(1 for _, _, b in s.where.values() if not b) for s in group) / len(group)
        cells = []
        for name in threads:
            c = collections.Counter(s.where[name][0] for s in group
                                    if name in s.where and not s.where[name][2]).most_common(1)
            cells.append(f"{c[0][0]} ({c[0][1]})" if c else "")
        rows.append([f"{k * bucket:.2f}", f"{busy:.2f}"] + cells)
    lines += [md_table(["t (s)", "cores"] + threads, rows, "rr" + "l" * len(threads)), ""]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.timeline", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("file", type=Path, help="a mesh file (the speed benchmark's 1M mesh: bench.speed.make_1m)")
    p.add_argument("--op", choices=("embed", "detect"), default="embed")
    p.add_argument("--method", choices=("ellipsoids", "planes"), default="ellipsoids")
    p.add_argument("--interval", type=float, default=0.005, help="seconds between samples")
    p.add_argument("--bucket", type=float, default=0.1, help="seconds per timeline row")
    p.add_argument("--out", type=Path, help="write markdown here (default: print)")
    args = p.parse_args(argv)

    import core.pipeline  # noqa: F401  (imported before the timing, as bench speed does)
    from core.allocator import tune_malloc
    from core.api import detect_file, embed_file

    tune_malloc()
    data = args.file.read_bytes()
    name = args.file.name
    if args.op == "embed":
        def call() -> object:
            return embed_file(data, KEY, filename=name, method=args.method)
    else:
        marked = embed_file(data, KEY, filename=name, method=args.method).data

        def call() -> object:
            return detect_file(marked, KEY, filename=name, method=args.method)
    call()  # warm
    tl = sample(call, args.interval)
    env = environment()
    env["command"] = (f"python -m bench.timeline {name} --op {args.op} --method {args.method} "
                      f"--interval {args.interval:g} --bucket {args.bucket:g}")
    text = header(f"MeshMark sampled timeline: {args.op} of {name}", env,
                  ["- The second call in one process (the first warms it); the innermost frame in `core/` of "
                   "every thread, sampled. Threads: `main` is the caller's, `meshmark-rows` the rows' "
                   "worker, `meshmark-beside` the one for work beside the caller's (`core/parallel.py`)"])
    text += "\n" + report(tl, args.bucket)
    if args.out:
        args.out.write_text(text)
    else:
        sys.stdout.write(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
