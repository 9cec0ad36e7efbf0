"""The broker: the Celery settings the API's client and the worker share (``celery_config``), and the API's side
of it (``Queue``): send a job's wake-up message by task name (the API never imports the worker), and see which jobs
still have a message in Redis (waiting, or delivered but not yet acknowledged)."""

from __future__ import annotations

import json
import uuid
from functools import cached_property
from typing import Any

TASK_NAME = "bonemesh.reconstruct"
ORIENT_TASK_NAME = "bonemesh.orient"  # re-publish a finished job's outputs in another stack orientation


def celery_config(redis_url: str, queue: str) -> dict[str, Any]:
    """Broker settings shared by the API's client and the worker."""
    return {
        "broker_url": redis_url,
        "broker_connection_retry_on_startup": True,
        "broker_transport_options": {"visibility_timeout": 6 * 3600},
        "task_default_queue": queue,
        "task_ignore_result": True,
        "task_serializer": "json",
        "accept_content": ["json"],
    }


class Queue:
    """Enqueue jobs and look at the broker."""

    def __init__(self, redis_url: str, queue: str) -> None:
        self.redis_url = redis_url
        self.queue = queue

    @cached_property
    def _celery(self) -> Any:
        from celery import Celery

        app = Celery("bonemesh-api", set_as_current=False)
        app.conf.update(celery_config(self.redis_url, self.queue))
        return app

    @cached_property
    def _redis(self) -> Any:
        import redis

        return redis.Redis.from_url(self.redis_url, socket_timeout=5, socket_connect_timeout=5)

    def enqueue(self, job_id: str) -> None:
        """Send the job's message (the task id is the job id; a duplicate message is harmless)."""
        self._celery.send_task(TASK_NAME, args=[job_id], task_id=job_id, queue=self.queue)

    def enqueue_orient(self, job_id: str, orient: dict[str, Any]) -> None:
        """Send a finished job's re-orientation (``worker.tasks.orient_job``); its task id is not the job id, so the
        reconciler never takes it for the job's reconstruction."""
        task_id = f"orient-{job_id}-{uuid.uuid4().hex[:8]}"
        self._celery.send_task(ORIENT_TASK_NAME, args=[job_id, orient], task_id=task_id, queue=self.queue)

    def ping(self) -> None:
        self._redis.ping()

    def jobs_in_broker(self) -> set[str]:
        """Job ids with a message waiting in the queue or delivered and unacknowledged."""
        found: set[str] = set()
        keys = [self.queue, *(k.decode() for k in self._redis.scan_iter(match=f"{self.queue}\x06\x16*"))]
        for key in keys:
            found.update(_task_id(raw) for raw in self._redis.lrange(key, 0, -1))
        # a delivered, unacknowledged message is stored as [message, exchange, routing key]
        found.update(_task_id(raw, unacked=True) for raw in self._redis.hvals("unacked"))
        found.discard("")
        return found


def _task_id(raw: bytes | str, unacked: bool = False) -> str:
    """The task (= job) id of a stored Kombu message, or "" for anything else."""
    try:
        message = json.loads(raw)
        return str((message[0] if unacked else message)["headers"]["id"])
    except (ValueError, KeyError, IndexError, TypeError):
        return ""
