"""The Celery worker: thin tasks that run ``engine.reconstruct`` on queued jobs (``bonemesh worker``)."""
