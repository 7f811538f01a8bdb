"""The ``redis`` jobs backend: job records in Redis, uploads and results in a blob store, the work
on Celery workers (``meshmark worker``).

Nothing in the service imports this package but the app factory (:func:`app.main.make_runner`,
when ``MESHMARK_JOBS_BACKEND=redis``) and the ``meshmark worker`` command, so a single machine
needs neither Celery nor Redis installed.

``store``: the job records (the API's
:class:`~app.jobs.JobStore` and the workers' side); ``runner``: the API's
:class:`~app.jobs.Runner`; ``worker``: one job as a worker runs it; ``celery_app``: the Celery
application and the worker process; ``celery_main``: the app for Celery's own tools.
"""
