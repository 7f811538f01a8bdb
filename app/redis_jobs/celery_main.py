"""The Celery app built from ``MESHMARK_*`` variables, for Celery's own tools:
``celery -A app.redis_jobs.celery_main inspect active``, ``... status``, ``... purge -Q meshmark``.

Start workers with ``meshmark worker`` (it sets the worker options this backend relies on).
"""

from app.config import Settings
from app.redis_jobs.celery_app import make_celery

celery = make_celery(Settings())
