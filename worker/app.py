"""The Celery application of the worker: one job at a time per process (one per GPU), late acknowledgement, a
lost worker's message is rejected back to the queue, soft and hard time limits.

Importing this module never imports Warp: the engine is imported inside the task, i.e. in the pool's child
process after the fork, so CUDA is initialised there and never in the parent.
"""

from __future__ import annotations

import multiprocessing

from celery import Celery
from celery.signals import worker_process_init

from service.queue import celery_config
from service.settings import get_settings


def make_app() -> Celery:
    settings = get_settings()
    app = Celery("bonemesh-worker", include=["worker.tasks"])
    app.conf.update(
        celery_config(settings.redis_url, settings.queue),
        task_acks_late=True,
        task_reject_on_worker_lost=True,
        worker_prefetch_multiplier=1,
        worker_concurrency=1,
        task_soft_time_limit=settings.job_soft_time_limit,
        task_time_limit=settings.job_time_limit,
        worker_max_tasks_per_child=50,
        worker_hijack_root_logger=False,
        worker_send_task_events=False,
    )
    return app


app = make_app()


@worker_process_init.connect
def _allow_children(**_: object) -> None:
    """Celery's pool children are daemonic, and a daemonic process may not start processes; the decimation stage
    runs MeshLab in a process pool, so the child drops the flag (its own children are reaped by the pool)."""
    multiprocessing.current_process()._config["daemon"] = False  # the setter refuses on a started process
