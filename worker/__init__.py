"""Celery worker (filled by the "service + worker" issue). Calls the engine."""
