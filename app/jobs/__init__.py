"""Asynchronous jobs: the job record and the store and runner interfaces, nothing that runs them
(the backends: :mod:`app.memory_jobs`, :mod:`app.redis_jobs`)."""

from app.jobs.runner import Runner, check_room
from app.jobs.status import JobStatus
from app.jobs.store import FINISHED, STATES, Job, JobState, JobStore, new_job_id

__all__ = ["FINISHED", "STATES", "Job", "JobState", "JobStatus", "JobStore", "Runner", "check_room",
           "new_job_id"]
