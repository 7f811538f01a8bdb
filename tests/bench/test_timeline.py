"""bench.timeline: the sampler sees the engine's threads, tells waiting from working, and adds up."""

from __future__ import annotations

import statistics
import threading
import time

import numpy as np
import trimesh

from bench.timeline import Sample, Timeline, report, sample


def _row(text: str, first: str) -> list[str]:
    for line in text.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if cells and cells[0] == first:
            return cells
    raise AssertionError(f"no row {first!r} in:\n{text}")


def test_a_thread_waiting_on_the_rows_worker_is_waiting_and_the_worker_busy():
    from core import parallel

    def chunk(lo: int, hi: int) -> int:
        if threading.current_thread().name.startswith("meshmark-rows"):
            # the worker's chunk, in the standard library's Python code (work, not waiting): the
            # caller has nothing left but to wait for it
            end = time.perf_counter() + 0.3
            while time.perf_counter() < end:
                statistics.fmean(range(2000))
        return lo

    # the rows' worker started before the sampling: its first use starts the thread, and under a
    # loaded machine the caller was sampled waiting for that start in submit (4 of 37 waiting
    # samples on a clean-clone CI run, where the test allows a tenth)
    parallel.by_chunks(lambda lo, hi: lo, 2, 1, split_from=0)
    tl = sample(lambda: parallel.by_chunks(chunk, 2, 1, split_from=0), interval=0.002)
    assert tl.wall >= 0.3
    main = [s.where["main"] for s in tl.samples if "main" in s.where]
    waiting = [w for w in main if w[2]]
    at = [w[0] for w in waiting]
    # waiting for the worker's chunk (and perhaps a sample of handing it over, in submit)
    assert at.count("core.parallel.by_chunks") >= 0.9 * len(at)
    assert len(waiting) >= 0.6 * len(tl.samples)
    rows = [w for s in tl.samples for name, w in s.where.items() if name.startswith("meshmark-rows")]
    assert rows and not any(w[2] for w in rows)  # the chunk is the worker's own work
    text = report(tl)
    assert float(_row(text, "main")[3]) >= 0.2  # waiting seconds
    assert float(_row(text, "main")[1]) < 0.1   # busy seconds


def test_report_adds_up_samples_per_thread_function_and_bucket():
    main_f, side_f = ("core.a.f", 1, False), ("core.b.g", 2, False)
    blocked = ("core.parallel.by_chunks", 3, True)
    samples = [Sample(k / 100, {"main": main_f if k < 6 else blocked, **({"side": side_f} if k % 2 else {})})
               for k in range(10)]
    tl = Timeline(wall=0.1, samples=samples)
    text = report(tl, bucket=0.05)
    assert _row(text, "main")[1:] == ["0.060", "0.60", "0.040"]
    assert _row(text, "side")[1:] == ["0.050", "0.50", "0.000"]
    assert _row(text, "core.a.f")[1:] == ["0.060", "0.545"]
    assert _row(text, "core.b.g")[1:] == ["0.050", "0.455"]
    assert "core.parallel.by_chunks" not in text  # waiting is nobody's work
    # buckets of 5 samples: main busy in all 5 of the first, side in 2; then main in 1, side in 3
    assert _row(text, "0.00")[1:4] == ["1.40", "core.a.f (5)", "core.b.g (2)"]
    assert _row(text, "0.05")[1:4] == ["0.80", "core.a.f (1)", "core.b.g (3)"]


def test_an_embedding_is_sampled_in_the_engine():
    from core.api import embed_file

    m = trimesh.creation.icosphere(subdivisions=4)
    rng = np.random.default_rng(3)
    v = m.vertices * (1 + 0.02 * rng.standard_normal((len(m.vertices), 1)))
    data = trimesh.Trimesh(v, m.faces, process=False).export(file_type="ply")
    tl = sample(lambda: embed_file(data, "timeline-key", filename="s.ply", method="planes"), interval=0.002)
    fns = {w[0] for s in tl.samples for w in s.where.values()}
    assert len(tl.samples) >= 10
    assert all(fn.startswith("core.") for fn in fns)
    assert any(fn.startswith(("core.embedding.", "core.analysis.", "core.mesh.", "core.sync.")) for fn in fns)
