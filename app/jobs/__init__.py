"""Asynchronous jobs: a store interface and the runner that feeds the worker pool."""

from app.jobs.runner import JobRunner, Runner
from app.jobs.store import FINISHED, InMemoryJobStore, Job, JobResult, JobStore

__all__ = ["FINISHED", "InMemoryJobStore", "Job", "JobResult", "JobRunner", "JobStore", "Runner"]
