"""Prometheus text exposition (format 0.0.4), written by hand: a few counters and one histogram."""

from __future__ import annotations

import bisect
from collections import Counter
from collections.abc import Iterable, Mapping

from app.workers.pool import WorkerPool

#: (name suffix, labels, value)
Sample = tuple[str, dict[str, str], float]

BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0, 120.0)


def _labels(**labels: str) -> str:
    def esc(v: str) -> str:
        return v.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n")

    return "{" + ",".join(f'{k}="{esc(v)}"' for k, v in labels.items()) + "}" if labels else ""


class Metrics:
    """Request counters and latency histogram; pool and job figures are read at scrape time."""

    def __init__(self) -> None:
        self.requests: Counter[tuple[str, str, str]] = Counter()
        self.in_progress = 0
        self._buckets: dict[str, list[int]] = {}
        self._sums: dict[str, float] = {}
        self._counts: Counter[str] = Counter()

    def observe_request(self, method: str, route: str, status: int, seconds: float) -> None:
        self.requests[(method, route, str(status))] += 1
        buckets = self._buckets.setdefault(route, [0] * len(BUCKETS))
        i = bisect.bisect_left(BUCKETS, seconds)
        if i < len(BUCKETS):
            buckets[i] += 1
        self._sums[route] = self._sums.get(route, 0.0) + seconds
        self._counts[route] += 1

    def render(self, pool: WorkerPool | None, jobs: Mapping[str, int]) -> str:
        out: list[str] = []

        def family(name: str, kind: str, help_: str, samples: Iterable[Sample]) -> None:
            out.append(f"# HELP {name} {help_}")
            out.append(f"# TYPE {name} {kind}")
            for suffix, labels, value in samples:
                out.append(f"{name}{suffix}{_labels(**labels)} {value:g}")

        family("meshmark_http_requests_total", "counter", "HTTP requests by method, route and status.",
               (("", {"method": m, "route": r, "status": s}, n)
                for (m, r, s), n in sorted(self.requests.items())))
        family("meshmark_http_requests_in_progress", "gauge", "HTTP requests being handled.",
               [("", {}, self.in_progress)])
        hist: list[Sample] = []
        for route in sorted(self._buckets):
            running = 0
            for bound, n in zip(BUCKETS, self._buckets[route], strict=True):
                running += n
                hist.append(("_bucket", {"route": route, "le": f"{bound:g}"}, running))
            hist.append(("_bucket", {"route": route, "le": "+Inf"}, self._counts[route]))
            hist.append(("_sum", {"route": route}, self._sums[route]))
            hist.append(("_count", {"route": route}, self._counts[route]))
        family("meshmark_http_request_duration_seconds", "histogram", "HTTP request latency by route.", hist)

        if pool is not None:
            family("meshmark_queue_depth", "gauge", "Tasks admitted and waiting for a worker.",
                   [("", {}, pool.pending - pool.running)])
            family("meshmark_tasks_in_flight", "gauge", "Tasks running in a worker.",
                   [("", {}, pool.running)])
            family("meshmark_queue_capacity", "gauge", "Task slots (running + waiting) before 429.",
                   [("", {}, pool.slots)])
            family("meshmark_workers_live", "gauge", "Live worker processes.",
                   [("", {}, len(pool.live_workers()))])
            reasons = ("crashed", "timeout", "cancelled", "pool-broken")
            family("meshmark_worker_restarts_total", "counter", "Workers replaced after a failure.",
                   (("", {"reason": r}, pool.restarts[r]) for r in reasons))
            family("meshmark_tasks_total", "counter", "Finished tasks by kind and outcome.",
                   (("", {"kind": k, "outcome": o}, n) for (k, o), n in sorted(pool.outcomes.items())))
        family("meshmark_jobs", "gauge", "Stored jobs by state.",
               (("", {"state": s}, n) for s, n in sorted(jobs.items())))
        return "\n".join(out) + "\n"
