"""Prometheus metrics with prometheus-client: request counters and latency, the worker pool and
the jobs (read at scrape time), the process (``process_*``: CPU, memory, open files) and the build
(``meshmark_build_info``).

Each app has a registry of its own (not the library's global one), so that several apps in one
process, as in the tests, do not share or clash over series.
"""

from __future__ import annotations

import platform
from collections.abc import Iterator, Mapping

from prometheus_client import (
    CollectorRegistry,
    Counter,
    Gauge,
    Histogram,
    Info,
    PlatformCollector,
    ProcessCollector,
    generate_latest,
)
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.registry import Collector

from app.overload import MemoryGuard, UploadBudget
from app.workers.pool import WorkerPool
from meshmark import __version__

#: request latency buckets, seconds: from a 429 (milliseconds) to a long job (the default timeout)
BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0, 120.0)
RESTART_REASONS = ("crashed", "timeout", "cancelled", "pool-broken")


class _ServiceCollector(Collector):
    """The pool's and the job store's figures as they are when scraped."""

    def __init__(self) -> None:
        self.pool: WorkerPool | None = None
        self.jobs: Mapping[str, int] = {}
        self.budget: UploadBudget | None = None
        self.guard: MemoryGuard | None = None
        self.result_bytes: int | None = None

    def collect(self) -> Iterator[Metric]:
        pool = self.pool
        if pool is not None:
            for name, help_, value in (
                ("meshmark_queue_depth", "Tasks admitted and waiting for a worker.",
                 pool.pending - pool.running),
                ("meshmark_tasks_in_flight", "Tasks running in a worker.", pool.running),
                ("meshmark_queue_capacity", "Task slots (running + waiting) before 429.", pool.slots),
                ("meshmark_workers_live", "Live worker processes.", len(pool.live_workers())),
            ):
                yield GaugeMetricFamily(name, help_, value=value)
            restarts = CounterMetricFamily("meshmark_worker_restarts", "Workers replaced after a failure.",
                                           labels=["reason"])
            for reason in RESTART_REASONS:
                restarts.add_metric([reason], pool.restarts[reason])
            yield restarts
            tasks = CounterMetricFamily("meshmark_tasks", "Finished tasks by kind and outcome.",
                                        labels=["kind", "outcome"])
            for (kind, outcome), n in sorted(pool.outcomes.items()):
                tasks.add_metric([kind, outcome], n)
            yield tasks
        figures = []
        if self.budget is not None:
            figures += [("meshmark_upload_bytes_in_flight", "Bytes of request bodies held by requests in "
                         "progress.", self.budget.in_flight),
                        ("meshmark_upload_budget_bytes", "Most bytes of bodies held at once before 429.",
                         self.budget.limit)]
        if self.guard is not None:
            figures.append(("meshmark_api_memory_limit_bytes", "Resident memory of the API process above "
                            "which new work is refused (0: no cap); compare process_resident_memory_bytes.",
                            self.guard.limit))
        if self.result_bytes is not None:
            figures.append(("meshmark_job_result_bytes", "Bytes of stored job results (memory backend: on "
                            "disk).", self.result_bytes))
        for name, help_, value in figures:
            yield GaugeMetricFamily(name, help_, value=value)
        jobs = GaugeMetricFamily("meshmark_jobs", "Stored jobs by state.", labels=["state"])
        for state, n in sorted(self.jobs.items()):
            jobs.add_metric([state], n)
        yield jobs


class Metrics:
    """The registry of one app and the instruments the middleware updates."""

    def __init__(self) -> None:
        self.registry = CollectorRegistry()
        ProcessCollector(registry=self.registry)
        PlatformCollector(registry=self.registry)
        Info("meshmark_build", "The running MeshMark.", registry=self.registry).info(
            {"version": __version__, "python": platform.python_version()})
        self.requests = Counter("meshmark_http_requests", "HTTP requests by method, route and status.",
                                ["method", "route", "status"], registry=self.registry)
        self.in_progress = Gauge("meshmark_http_requests_in_progress", "HTTP requests being handled.",
                                 registry=self.registry)
        self.duration = Histogram("meshmark_http_request_duration_seconds", "HTTP request latency by route.",
                                  ["route"], buckets=BUCKETS, registry=self.registry)
        self._service = _ServiceCollector()
        self.registry.register(self._service)

    def observe_request(self, method: str, route: str, status: int, seconds: float) -> None:
        self.requests.labels(method, route, str(status)).inc()
        self.duration.labels(route).observe(seconds)

    def watch(self, budget: UploadBudget, guard: MemoryGuard) -> None:
        """Report the upload budget and the memory cap of the app."""
        self._service.budget, self._service.guard = budget, guard

    def render(self, pool: WorkerPool | None, jobs: Mapping[str, int],
               result_bytes: int | None = None) -> bytes:
        """The exposition text, with the pool and job figures of this moment."""
        self._service.pool, self._service.jobs, self._service.result_bytes = pool, jobs, result_bytes
        return generate_latest(self.registry)
